#version 300 es
// The layered-mesh draw of the Python client (render/quad_mesh_vertex.glsl, #included by the server when it serves
// this file) in GLSL ES 3.00.
precision highp float;
#include "quad_mesh_vertex.glsl"
void main() {
    gl_Position = u_proj * layer_vertex();
}
