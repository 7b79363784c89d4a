#version 430
// YORO Algorithm 2 (Reprojector stage 2), one invocation per row, so no two threads ever write one texel.
// Sweep 1 turns "where each source pixel lands" into "where each target pixel comes from": every source pixel
// writes the target pixel nearest to where it lands, and neighbours on one surface also fill the target pixels
// between them (sub-pixel source positions). Overlaps keep the nearest depth. Sweep 2 finds the target pixels
// nobody wrote (disocclusions) and records for each, in the records image, its run's left edge, width, and which
// neighbour is the background (the farther one), for the Patcher.
//
// FUSED (a full-resolution ImBuffer): the row pass of all three stages. Sweep 1 computes where each pixel lands
// itself (Algorithm 1, `landing_z`) instead of reading it from the targets image, and sweep 2 patches each
// covered pixel (Algorithm 3, `patch_covered`) and lists the disoccluded ones for the Patcher's hole pass, which
// finds each one's run and records it (yoro_patch.comp, FIND_RUNS) -- three fewer full-screen passes, each of
// which costs llvmpipe milliseconds at 960x540 whatever it does. The row loop has no run-finding branches
// (llvmpipe runs every branch of a loop's body for all 8 lanes each turn), and sweep 1 keeps, as bits, which
// neighbouring source pixels the Patcher's colour interpolation may blend (the depths it reads anyway), so
// sweep 2 fetches no depth (the same images in less time: docs/speed.md, stop 37).
layout(local_size_x = ROWS_PER_GROUP) in;   // 8 rows a workgroup (client/stereo.py): with 32, the two cores' shares
                                           // of 540 rows were 17 uneven groups (synthesis ~1 ms slower at 960x540)
#include "stereo_common.glsl"

layout(rg32f, binding = 1) uniform image2D u_imbuffer;
uniform float u_max_stretch;   // widest target gap (ImBuffer pixels) bridged between two neighbours
#if FUSED
layout(rgba8, binding = 2) writeonly uniform image2D u_out;
layout(rg8, binding = 3) writeonly uniform image2D u_mask;
layout(std430, binding = 3) buffer Holes { uint hole_count; uint holes[]; };   // (y << 16) | x
#define COARSE 0
#define SAME_BITS LINEAR
// Bit x % 32 of word y * ROW_WORDS + x / 32: source pixels x and x + 1 of row y are on one surface (`same_surface`
// of their depths, the test the Patcher's colour interpolation makes); ROW_WORDS = ceil(width / 32)
// (client/stereo.py). Sweep 1 writes its row's, sweep 2 and the hole pass (yoro_patch.comp, FIND_RUNS) read them.
layout(std430, binding = 5) buffer SameBits { uint same_bits[]; };
#include "yoro_patch.glsl"
#else
layout(rg32f, binding = 0) readonly uniform image2D u_targets;
layout(rgba32f, binding = 4) writeonly uniform image2D u_records;   // the disocclusions' (stereo_common.glsl)
#endif

// Where source pixel x of row y lands in the other eye, its depth there, and (FUSED) its source depth.
vec3 lands(int x, int y, ivec2 size) {
#if FUSED
    return landing_z(ivec2(x, y), size);
#else
    return vec3(imageLoad(u_targets, ivec2(x, y)).xy, 0.0);
#endif
}

void put(int t, int y, int w, float src_x, float depth) {
    if (t < 0 || t >= w) return;
    vec4 cur = imageLoad(u_imbuffer, ivec2(t, y));
    if (!is_covered(cur) || depth < cur.y)  // empty, or nearer than what is there: nearest wins
        imageStore(u_imbuffer, ivec2(t, y), vec4((src_x - float(t)) / float(w), depth, 0.0, 0.0));
}

// Two neighbouring source pixels on one surface whose landing spots are in order and close enough.
bool bridges(vec3 a, vec3 b) {
    float gap = b.x - a.x;
    return gap > 0.0 && gap <= u_max_stretch && same_surface(a.y, b.y);
}

void main() {
    int y = int(gl_GlobalInvocationID.x);
    ivec2 size = imageSize(u_imbuffer);
    if (y >= size.y) return;
    int w = size.x;
    // The row starts unset: (0, -1) everywhere, cleared by the caller (client/stereo.py).

    // Sweep 1: scatter along the row. A pixel bridged to a neighbour covers the target pixels up to it by
    // interpolation; its own nearest target pixel is written only on a side no bridge covers.
    vec3 right = vec3(0.0);
    vec3 c = lands(w - 1, y, size);
    bool bridged_right = false;
#if FUSED
#if SAME_BITS
    uint bits = 0u;
#endif
#endif
    for (int x = w - 1; x >= 0; --x) {
        vec3 left = x > 0 ? lands(x - 1, y, size) : c;
#if FUSED
#if SAME_BITS
        if (x < w - 1 && same_surface(c.z, right.z)) bits |= 1u << uint(x & 31);
        if ((x & 31) == 0) {   // a word is done (x is the same in all lanes)
            same_bits[y * ROW_WORDS + (x >> 5)] = bits;
            bits = 0u;
        }
#endif
#endif
        bool bridged_left = x > 0 && bridges(left, c);
        bridged_right = x < w - 1 && bridges(c, right);
        if (bridged_right) {
            float gap = right.x - c.x;
            for (int t = int(ceil(c.x)); float(t) < right.x; ++t) {
                float f = (float(t) - c.x) / gap;
                put(t, y, w, float(x) + f, mix(c.y, right.y, f));
            }
        }
        float t0 = round(c.x);
        bool covered = (bridged_right && t0 >= c.x) || (bridged_left && t0 < c.x);
        if (abs(t0) < 1e8 && !covered) put(int(t0), y, w, float(x) + (t0 - c.x), c.y);
        right = c;
        c = left;
    }

#if FUSED
    // Sweep 2: patch each covered pixel, list the disoccluded ones.
    g_src_size = textureSize(u_color, 0);
    g_w = w;
    for (int t = 0; t < w; ++t) {
        vec4 r = imageLoad(u_imbuffer, ivec2(t, y));
        if (is_covered(r)) patch_covered(ivec2(t, y), size, float(t), r);
        else holes[atomicAdd(hole_count, 1u)] = (uint(y) << 16) | uint(t);
    }
#else
    // Sweep 2: record each disocclusion run.
    int t = 0;
    while (t < w) {
        if (is_covered(imageLoad(u_imbuffer, ivec2(t, y)))) {
            ++t;
            continue;
        }
        int a = t;
        while (t < w && !is_covered(imageLoad(u_imbuffer, ivec2(t, y)))) ++t;
        int b = t - 1;
        float dl = a > 0 ? imageLoad(u_imbuffer, ivec2(a - 1, y)).y : -1.0;
        float dr = b < w - 1 ? imageLoad(u_imbuffer, ivec2(b + 1, y)).y : -1.0;
        vec4 record = disocclusion_record(a, b, dl, dr);
        for (int k = a; k <= b; ++k) imageStore(u_records, ivec2(k, y), record);
    }
#endif
}
