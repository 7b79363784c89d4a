// Shared by the YORO stages: reading the dominant eye's depth and the ImBuffer's conventions.
//
// Depth source: the G-buffer's view-space position (RGBA32F, w > 0 where geometry) when u_depth_is_position,
// else a linear-depth R32F texture (metres along -Z; 0, negative or inf = nothing hit). GL rows, bottom first.
// Sky pixels get SKY_DEPTH (render/camera.glsl) and reproject as points at infinity (no disparity).
//
// ImBuffer texel (RGBA32F, intermediate width x eye height):
//   covered pixel:  (source u - target u, depth in the other eye, 0, 0)
//   disocclusion:   (left edge x, background depth, width, background-side neighbour x or -1)

#include "camera.glsl"

uniform sampler2D u_depth;
uniform bool u_depth_is_position;
uniform float u_continuity;   // neighbours on one surface differ in depth by less than this fraction

float source_depth(ivec2 p) {
    ivec2 size = textureSize(u_depth, 0);
    p = clamp(p, ivec2(0), size - 1);
    vec4 t = texelFetch(u_depth, p, 0);
    if (u_depth_is_position) return is_sky(t) ? SKY_DEPTH : max(-t.z, 1e-6);
    return is_sky_depth(t.r) ? SKY_DEPTH : t.r;
}

bool same_surface(float a, float b) {
    if (a >= SKY_DEPTH || b >= SKY_DEPTH) return a >= SKY_DEPTH && b >= SKY_DEPTH;
    return abs(a - b) <= u_continuity * min(a, b);
}
