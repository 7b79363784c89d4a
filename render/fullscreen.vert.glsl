#version 430
// A triangle covering the viewport; v_uv in [0, 1]. At NDC depth u_z (0 unless set; 1 = the far plane).
out vec2 v_uv;
uniform float u_z;
void main() {
    vec2 p = vec2((gl_VertexID << 1) & 2, gl_VertexID & 2);
    v_uv = p;
    gl_Position = vec4(p * 2.0 - 1.0, u_z, 1.0);
}
