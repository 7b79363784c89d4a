#version 430
// Layered-mesh rendering: a layer's vertices are in its camera's view space; u_layer_to_view takes them to the
// current eye's view space.
in vec3 in_position;
in vec2 in_uv;
uniform mat4 u_layer_to_view;
uniform mat4 u_proj;
out vec2 v_uv;
out vec3 v_view_pos;
void main() {
    vec4 p = u_layer_to_view * vec4(in_position, 1.0);
    v_view_pos = p.xyz;
    v_uv = in_uv;
    gl_Position = u_proj * p;
}
