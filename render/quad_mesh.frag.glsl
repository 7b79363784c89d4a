#version 430
// The layered-mesh draw; its body is shared with the browser viewer (server/viewer/shaders, GLSL ES 3.00).
#include "quad_mesh_fragment.glsl"
void main() {
    f_color = vec4(layer_colour(), 1.0);
    f_depth = -v_view_pos.z;
}
