#version 430
// Shadow pass: the sun's orthographic view.
in vec3 in_position;
uniform mat4 u_light_mvp;
void main() {
    gl_Position = u_light_mvp * vec4(in_position, 1.0);
}
