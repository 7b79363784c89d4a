#version 430
// YORO Algorithm 3 (Patcher), one invocation per output pixel of the other eye. A covered pixel takes the
// dominant eye's colour at the source position the ImBuffer gives (linearly interpolated along x between
// neighbours on one surface). A disoccluded pixel is filled from the background side only (observation O2):
// a kernel as wide as the disocclusion and u_kernel_rows high walks away from the background edge, skips
// foreground samples, and weighs each sample with eq. 6, W = w/2 + 0.3 w (distance into the hole / width).
// The mask gets r = disoccluded, g = conservative edge reject (stereo shading reprojection's triangle filter:
// a covered pixel whose source lies within u_edge_radius of something nearer is not trusted).
// Built three times: HOLES 0 runs on every pixel, patches the covered ones and lists the disoccluded ones; HOLES 1
// runs on that list only (an indirect dispatch), with FIND_RUNS after the fused row pass (yoro_scan.comp), whose
// list comes without the disocclusions' records. The covered pixels' part is yoro_patch.glsl, which the fused
// row pass runs too. In one pass llvmpipe would run the hole kernel's loops for every covered pixel too (it
// executes both sides of a branch for all 8 lanes) -- for the same reason the synthesizer's fixed settings are
// compile-time: LINEAR (interpolate source colours along x), COARSE (the ImBuffer is narrower than the eye) and
// EDGES (compute the conservative edge reject; YORO alone, mode 1, has no use for it).
#if HOLES
layout(local_size_x = 64) in;
#else
layout(local_size_x = 8, local_size_y = 8) in;
#endif
layout(std430, binding = 3) buffer Holes { uint hole_count; uint holes[]; };   // (y << 16) | x

layout(rg32f, binding = 0) readonly uniform image2D u_imbuffer;
#ifndef FIND_RUNS
#define FIND_RUNS 0
#endif
#if HOLES && FIND_RUNS
layout(rgba32f, binding = 4) writeonly uniform image2D u_records;  // the disocclusions' (stereo_common.glsl)
#elif HOLES
layout(rgba32f, binding = 4) readonly uniform image2D u_records;
#endif
layout(rgba8, binding = 1) writeonly uniform image2D u_out;
layout(rg8, binding = 2) writeonly uniform image2D u_mask;
uniform int u_kernel_rows;          // Patcher kernel height h
uniform int u_kernel_max;           // Patcher kernel width cap (ImBuffer pixels)
#if FIND_RUNS
#define SAME_BITS LINEAR
layout(std430, binding = 5) readonly buffer SameBits { uint same_bits[]; };   // the row pass's (yoro_scan.comp)
#endif
#include "yoro_patch.glsl"

void main() {
    ivec2 size = imageSize(u_out);
#if HOLES
    uint h = gl_GlobalInvocationID.x;
    if (h >= hole_count) return;
    ivec2 p = ivec2(int(holes[h] & 0xffffu), int(holes[h] >> 16));
#else
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(p, size))) return;
#endif
    g_src_size = textureSize(u_color, 0);
    g_w = imageSize(u_imbuffer).x;
    int y = p.y;
    float q = (float(p.x) + 0.5) * float(g_w) / float(size.x) - 0.5;  // position in ImBuffer pixels
    int n = clamp(int(round(q)), 0, g_w - 1);
#if !HOLES
    vec4 r = imageLoad(u_imbuffer, ivec2(n, y));
    if (!is_covered(r)) {  // disoccluded: the second pass fills it
        holes[atomicAdd(hole_count, 1u)] = (uint(p.y) << 16) | uint(p.x);
        return;
    }
    patch_covered(p, size, q, r);
#else
    // Disoccluded: r = (left edge, background depth, width, background-side neighbour).
#if FIND_RUNS
    // The fused row pass listed the hole alone (a full-resolution ImBuffer, n = p.x): find its run, and record it
    // as the staged row sweep does (yoro_scan.comp).
    int a = n, b = n;
    while (a > 0 && !is_covered(imageLoad(u_imbuffer, ivec2(a - 1, y)))) --a;
    while (b < g_w - 1 && !is_covered(imageLoad(u_imbuffer, ivec2(b + 1, y)))) ++b;
    vec4 r = disocclusion_record(a, b, a > 0 ? imageLoad(u_imbuffer, ivec2(a - 1, y)).y : -1.0,
                                 b < g_w - 1 ? imageLoad(u_imbuffer, ivec2(b + 1, y)).y : -1.0);
    imageStore(u_records, ivec2(n, y), r);
#else
    vec4 r = imageLoad(u_records, ivec2(n, y));
#endif
    imageStore(u_mask, p, vec4(1.0, 0.0, 0.0, 0.0));
    int edge = int(r.w);
    if (edge < 0) { imageStore(u_out, p, vec4(0.0, 0.0, 0.0, 1.0)); return; }
    int dir = edge > n ? 1 : -1;
    float into = clamp(abs(q - float(edge)) / r.z, 0.0, 1.0);
    int width = min(int(r.z), u_kernel_max);
    vec3 acc = vec3(0.0);
    float remaining = 1.0;
    for (int k = 0; k < width; ++k) {
        int j = edge + dir * k;
        if (j < 0 || j >= g_w) break;
        for (int m = 0; m < u_kernel_rows; ++m) {
            int yy = y + ((m + 1) / 2) * ((m & 1) == 1 ? -1 : 1);  // rows y, y-1, y+1, y-2, ...
            if (yy < 0 || yy >= size.y) continue;
            vec4 s = imageLoad(u_imbuffer, ivec2(j, yy));
            if (!is_covered(s)) continue;                                           // another hole
            if (s.y < r.y && !same_surface(s.y, r.y)) continue;                   // foreground: skip
            float weight = remaining * 0.5 + 0.3 * remaining * into;              // eq. 6
            acc += color_at(source_x(j, s), yy) * weight;
            remaining -= weight;
        }
    }
    vec3 c = remaining < 1.0 ? acc / (1.0 - remaining)
                             : color_at(source_x(edge, imageLoad(u_imbuffer, ivec2(edge, y))), y);
    imageStore(u_out, p, vec4(c, 1.0));
#endif
}
