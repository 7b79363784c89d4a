// Shared by the YORO stages: reading the dominant eye's depth and the ImBuffer's conventions.
//
// Depth source: the G-buffer's view-space position (RGBA32F, w > 0 where geometry) when u_depth_is_position,
// else a linear-depth R32F texture (metres along -Z; 0, negative or inf = nothing hit). GL rows, bottom first.
// Sky pixels get SKY_DEPTH (render/camera.glsl) and reproject as points at infinity (no disparity).
//
// ImBuffer texel (RG32F, intermediate width x eye height):
//   covered pixel:  (source u - target u, depth in the other eye)
//   anything else:  (0, -1)
// and, at each disocclusion's texels only, the records image (RGBA32F, the same size):
//   (left edge x, background depth, width, background-side neighbour x or -1)
// Two images, not one RGBA32F texel for both: llvmpipe's image loads and stores cost with the channels they move,
// and every pass but the Patcher's hole pass reads only the first two (the synthesis 12-14% faster at 960x540).

#ifndef QUADCAST_STEREO_COMMON_GLSL
#define QUADCAST_STEREO_COMMON_GLSL
#include "camera.glsl"

bool is_covered(vec4 imbuffer_texel) {
    return imbuffer_texel.y >= 0.0;
}

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

// YORO Algorithm 1 for ImBuffer pixel i of an ImBuffer `size` across: lift the dominant eye's depth sample at the
// pixel's uv to a view-space point and move it with one matrix into the other eye's clip space. Returns (x where
// it lands, in ImBuffer pixel-centre units, -1e9 behind the other eye; its depth there, SKY_DEPTH for sky);
// `landing_z` also returns the source depth it read.
uniform mat4 u_reproject;   // dominant eye view space -> other eye clip space (M of YORO eq. 5)
uniform vec4 u_extents;     // dominant eye's frustum l, r, b, t at distance 1

vec3 landing_z(ivec2 i, ivec2 size) {
    vec2 uv = (vec2(i) + 0.5) / vec2(size);
    ivec2 src = ivec2(uv * vec2(textureSize(u_depth, 0)));
    float z = source_depth(src);
    vec3 ray = view_ray(u_extents, 1.0, uv);
    vec4 p = z < SKY_DEPTH ? vec4(ray * z, 1.0) : vec4(ray, 0.0);  // sky: a direction (point at infinity)
    vec4 c = u_reproject * p;
    float x = -1e9;  // behind the other eye: lands nowhere
    if (c.w > 0.0) x = (c.x / c.w * 0.5 + 0.5) * float(size.x) - 0.5;
    return vec3(x, z < SKY_DEPTH ? c.w : SKY_DEPTH, z);
}

vec2 landing(ivec2 i, ivec2 size) {
    return landing_z(i, size).xy;
}

// The record of the disocclusion at ImBuffer texels a..b of a row, whose neighbours' depths are dl (texel a - 1)
// and dr (texel b + 1), -1 where the row ends: its background is the farther neighbour.
vec4 disocclusion_record(int a, int b, float dl, float dr) {
    vec4 record = vec4(float(a), SKY_DEPTH, float(b - a + 1), -1.0);
    if (dl >= 0.0 || dr >= 0.0) record.yw = dr >= dl ? vec2(dr, float(b + 1)) : vec2(dl, float(a - 1));
    return record;
}

#endif
