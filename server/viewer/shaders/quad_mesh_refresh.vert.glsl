#version 300 es
// The Python client's draw of its cached layer (render/quad_mesh_refresh_vertex.glsl, #included by the server when
// it serves this file) in GLSL ES 3.00: where the newest frame's own view saw the surface, a weighted mean of both
// colours.
precision highp float;
#include "quad_mesh_refresh_vertex.glsl"
