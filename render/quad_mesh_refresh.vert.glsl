#version 430
// The cached layers' draw (QuadMesh.set_current_view); its body is shared with the browser viewer
// (server/viewer/shaders, GLSL ES 3.00).
#include "quad_mesh_refresh_vertex.glsl"
