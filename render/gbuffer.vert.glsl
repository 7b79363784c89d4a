#version 430
// Geometry pass: transform a mesh into view space for the G-buffer.
in vec3 in_position;
in vec3 in_normal;
in vec2 in_uv;

uniform mat4 u_model;
uniform mat4 u_view;
uniform mat4 u_proj;

out vec3 v_view_pos;
out vec3 v_view_normal;
out vec3 v_obj_pos;
out vec3 v_obj_normal;
out vec2 v_uv;

void main() {
    vec4 view_pos = u_view * u_model * vec4(in_position, 1.0);
    v_view_pos = view_pos.xyz;
    v_view_normal = mat3(u_view) * mat3(transpose(inverse(u_model))) * in_normal;
    v_obj_pos = in_position;
    v_obj_normal = in_normal;
    v_uv = in_uv;
    gl_Position = u_proj * view_pos;
}
