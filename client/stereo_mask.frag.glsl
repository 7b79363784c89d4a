#version 430
// Stereo shading reprojection's pixel culling mask as depth: pixels the reprojection covers get depth 0 (the
// near plane), so a later depth-tested (LESS) draw shades only the pixels to re-render, which keep depth 1.
uniform sampler2D u_mask;   // r = disoccluded, g = conservative edge reject

void main() {
    vec2 m = texelFetch(u_mask, ivec2(gl_FragCoord.xy), 0).rg;
    gl_FragDepth = (m.r > 0.5 || m.g > 0.5) ? 1.0 : 0.0;
}
