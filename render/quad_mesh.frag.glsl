#version 430
// The layered-mesh draw; its body is shared with the browser viewer (server/viewer/shaders, GLSL ES 3.00).
#include "quad_mesh_fragment.glsl"
