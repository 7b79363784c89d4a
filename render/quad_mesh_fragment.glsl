// Layered-mesh rendering: colour from the decoded video atlas (alpha 1 where the mesh covers the pixel); linear
// view depth for depth-based masks and the stereo synthesis (0, the clear value, where nothing was drawn).
in vec3 v_uvw;
in vec3 v_view_pos;
uniform sampler2D u_atlas;
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_depth;
void main() {
    f_color = vec4(texture(u_atlas, v_uvw.xy / v_uvw.z).rgb, 1.0);
    f_depth = -v_view_pos.z;
}
