#version 430
// Atlas composition: draw one layer's colour into its rectangle of the video atlas (scaled if the rect is smaller).
in vec2 v_uv;
uniform sampler2D u_layer;
out vec4 f_color;
void main() {
    f_color = vec4(texture(u_layer, v_uv).rgb, 1.0);
}
