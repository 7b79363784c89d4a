#version 300 es
// WebGL2 form of render/quad_mesh.frag.glsl: colour from the decoded video atlas, sampled projectively. Alpha 1
// marks covered pixels (the page clears to 0 and counts the rest as holes).
precision highp float;
in vec3 v_uvw;
uniform sampler2D u_atlas;
out vec4 f_color;
void main() {
    f_color = vec4(texture(u_atlas, v_uvw.xy / v_uvw.z).rgb, 1.0);
}
