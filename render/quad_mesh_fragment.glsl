// Layered-mesh rendering: colour from the decoded video atlas; view position for depth-based masks.
in vec3 v_uvw;
in vec3 v_view_pos;
uniform sampler2D u_atlas;
layout(location = 0) out vec4 f_color;
layout(location = 1) out vec4 f_position;
void main() {
    f_color = vec4(texture(u_atlas, v_uvw.xy / v_uvw.z).rgb, 1.0);
    f_position = vec4(v_view_pos, 1.0);
}
