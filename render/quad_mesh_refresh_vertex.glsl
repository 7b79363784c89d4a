// The layered-mesh draw of a cached layer (quad_mesh_refresh_fragment.glsl): also where each vertex lies in the
// current view's clip space, interpolated (exactly: it is linear in the vertex's position) for the fragments --
// the vertex where it is, not where a depth scale or the far-plane clamp moved it along the eye ray.
#include "quad_mesh_vertex.glsl"
uniform mat4 u_layer_to_current;   // the layer camera's view space -> the current view's clip space
out vec4 v_current_clip;
void main() {
    v_current_clip = u_layer_to_current * vec4(in_position, 1.0);
    gl_Position = u_proj * layer_vertex();
}
