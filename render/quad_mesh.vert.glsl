#version 430
// The layered-mesh draw; its body is shared with the browser viewer (server/viewer/shaders, GLSL ES 3.00).
#include "quad_mesh_vertex.glsl"
void main() {
    gl_Position = u_proj * layer_vertex();
}
