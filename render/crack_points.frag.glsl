#version 430
// Crack fill, second pass: a crack's colour and linear view depth (crack_points.vert.glsl).
in vec4 v_color;
in float v_depth;
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_depth;

void main() {
    f_color = vec4(v_color.rgb, 1.0);
    f_depth = v_depth;
}
