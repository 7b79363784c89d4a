#version 430
// The visible layer's farthest depth over blocks, for the peel pass's early reject (server/peel.frag.glsl), all
// levels side by side in one image: level 0 holds the visible depth of each pixel (SKY_DEPTH where it shows sky),
// level k (half the size of level k-1, rounded up) the largest of its 2 x 2 children, so texel p >> k of level k
// covers pixel p. One invocation per texel of the level being built.
layout(local_size_x = 8, local_size_y = 8) in;
#include "camera.glsl"
layout(r32f, binding = 0) uniform image2D u_levels;
uniform ivec4 u_out;   // the level built: x offset in the image, width, height
#if LEVEL0
uniform sampler2D u_position;   // the visible layer's view positions (w > 0 where geometry)
#else
uniform ivec4 u_in;    // the level below
#endif

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(p, u_out.yz))) return;
#if LEVEL0
    vec4 v = texelFetch(u_position, p, 0);
    float m = is_sky(v) ? SKY_DEPTH : -v.z;
#else
    ivec2 last = u_in.yz - 1;
    float m = 0.0;
    for (int j = 0; j < 2; ++j)
        for (int i = 0; i < 2; ++i) {
            ivec2 q = min(2 * p + ivec2(i, j), last);
            m = max(m, imageLoad(u_levels, ivec2(u_in.x + q.x, q.y)).r);
        }
#endif
    imageStore(u_levels, ivec2(u_out.x + p.x, p.y), vec4(m));
}
