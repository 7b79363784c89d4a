#version 300 es
#define ATLAS_RGB
// The layered-mesh draw of the Python client (render/quad_mesh_fragment.glsl, #included by the server when it
// serves this file) in GLSL ES 3.00. Its second output (linear view depth) has no draw buffer on the canvas and is
// dropped; alpha 1 marks covered pixels (the page clears to 0 and counts the rest as holes).
precision highp float;
#include "quad_mesh_fragment.glsl"
void main() {
    f_color = vec4(layer_colour(), 1.0);
    f_depth = -v_view_pos.z;
}
