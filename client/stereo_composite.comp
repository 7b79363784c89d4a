#version 430
// Stereo shading reprojection, last step: re-rendered colour where the mask asked for it, reprojected elsewhere.
layout(local_size_x = 8, local_size_y = 8) in;

layout(rgba8, binding = 0) writeonly uniform image2D u_out;
uniform sampler2D u_reprojected;
uniform sampler2D u_rerendered;
uniform sampler2D u_mask;   // r = disoccluded, g = conservative edge reject

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(p, imageSize(u_out)))) return;
    vec2 m = texelFetch(u_mask, p, 0).rg;
    bool redo = m.r > 0.5 || m.g > 0.5;
    vec3 c = redo ? texelFetch(u_rerendered, p, 0).rgb : texelFetch(u_reprojected, p, 0).rgb;
    imageStore(u_out, p, vec4(c, 1.0));
}
