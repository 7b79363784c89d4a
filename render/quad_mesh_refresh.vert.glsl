#version 430
// The layered-mesh draw of a cached layer (quad_mesh_refresh.frag.glsl): also where each vertex lies in the
// current view's clip space, interpolated (exactly: it is linear in the vertex's position) for the fragments.
#include "quad_mesh_vertex.glsl"
uniform mat4 u_eye_to_current;   // this eye's view space -> the current view's clip space
out vec4 v_current_clip;
void main() {
    vec4 p = layer_vertex();
    v_current_clip = u_eye_to_current * p;
    gl_Position = u_proj * p;
}
