#version 430
// Depth-only steps around a peel pass (server/layers.py), by u_step:
// 0, cull (before a layer-by-layer peel pass): depth 0 where the previous layer holds nothing, so the depth test
//    rejects every fragment there before the peel shader runs -- it would discard them all (nothing in front:
//    nothing hidden) but, with a discard in it, llvmpipe shades them first.
// 1, restore (after it, u_position = the peeled layer): depth 1 again wherever that layer holds nothing, as a plain
//    pass leaves it (the depth-tested lighting relies on it).
// 2, behind (before the one-pass peel's list, drawn with the depth test GREATER): where the visible layer holds
//    something, the window depth of the view depth z0 (1 + u_connectivity) from which peel_list.frag.glsl keeps
//    fragments, less a margin far above the depth buffer's rounding; 1 where it holds nothing. The fragments its
//    first test would discard -- the visible surface's own, most of them -- then never reach the shader.
#include "camera.glsl"
uniform sampler2D u_position;
uniform int u_step;
uniform vec2 u_near_far;        // step 2: the peel camera's near and far planes
uniform float u_connectivity;   // step 2
void main() {
    vec4 v = texelFetch(u_position, ivec2(gl_FragCoord.xy), 0);
    bool empty = is_sky(v);
    if (u_step == 2) {
        float n = u_near_far.x, f = u_near_far.y;
        float z = min(-v.z * (1.0 + u_connectivity), f);
        float window = 0.5 * ((f + n) / (f - n) - 2.0 * f * n / ((f - n) * z)) + 0.5;   // the projection's
        gl_FragDepth = empty ? 1.0 : clamp(window - 1e-6, 0.0, 1.0);
    } else if (u_step == 1) {
        if (!empty) discard;
        gl_FragDepth = 1.0;
    } else {
        gl_FragDepth = empty ? 0.0 : 1.0;
    }
}
