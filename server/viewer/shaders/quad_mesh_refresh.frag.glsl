#version 300 es
#define ATLAS_RGB
// The Python client's draw of its cached layer (render/quad_mesh_refresh_fragment.glsl, #included by the server when
// it serves this file) in GLSL ES 3.00: where the newest frame's own view saw the surface, a weighted mean of both
// colours.
precision highp float;
#include "quad_mesh_refresh_fragment.glsl"
