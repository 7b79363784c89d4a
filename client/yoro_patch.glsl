// YORO Algorithm 3 (Patcher) for a covered pixel of the other eye, shared by the Patcher (yoro_patch.comp) and the
// fused row pass (yoro_scan.comp, FUSED): the dominant eye's colour at the source position the ImBuffer gives
// (linearly interpolated along x between neighbours on one surface), and the mask (r = 0: not disoccluded; g = the
// conservative edge reject of stereo shading reprojection's triangle filter when EDGES: a covered pixel whose
// source lies within u_edge_radius of something nearer is not trusted). The includer declares the images
// u_imbuffer, u_out (rgba8) and u_mask (rg8) and the defines LINEAR, COARSE and EDGES (see yoro_patch.comp);
// with SAME_BITS the includer declares the buffer `same_bits[]` (ROW_WORDS words a row) of the bits the fused row
// pass keeps (yoro_scan.comp), which `same_neighbours` reads instead of fetching both depths.
#include "stereo_common.glsl"
#ifndef SAME_BITS
#define SAME_BITS 0
#endif
#if SAME_BITS
// Whether source pixels x and x + 1 of row y are on one surface: bit x % 32 of word y * ROW_WORDS + x / 32.
bool same_neighbours(int x, int y) {
    return ((same_bits[y * ROW_WORDS + (x >> 5)] >> uint(x & 31)) & 1u) != 0u;
}
#endif

uniform sampler2D u_color;          // dominant eye, lit sRGB (GL rows, bottom first)
uniform float u_edge_radius;        // conservative filter: triangle vertex distance (pixels); 0 = off
uniform float u_edge_disparity;     // ... disparity step (pixels) that counts as a foreground edge
uniform float u_disparity_scale;    // focal length (pixels) x baseline (metres): disparity = scale / depth

ivec2 g_src_size;
int g_w;  // ImBuffer width

vec3 color_at(float sx, int y) {
#if !LINEAR
    return texelFetch(u_color, ivec2(clamp(int(round(sx)), 0, g_src_size.x - 1), y), 0).rgb;
#else
    float x0 = floor(sx);
    float f = sx - x0;
    ivec2 a = ivec2(clamp(int(x0), 0, g_src_size.x - 1), y);
    ivec2 b = ivec2(clamp(int(x0) + 1, 0, g_src_size.x - 1), y);
    vec3 ca = texelFetch(u_color, a, 0).rgb, cb = texelFetch(u_color, b, 0).rgb;
#if SAME_BITS   // a == b at the row's ends
    if (a.x == b.x || same_neighbours(a.x, y)) return mix(ca, cb, f);
#else
    if (same_surface(source_depth(a), source_depth(b))) return mix(ca, cb, f);
#endif
    return f < 0.5 ? ca : cb;
#endif
}

// Source x (source pixel-centre units) of covered ImBuffer texel (j, y), which holds r.
float source_x(int j, vec4 r) {
    return ((float(j) + 0.5) / float(g_w) + r.x) * float(g_src_size.x) - 0.5;
}

bool near_edge(float sx, int y, float depth) {
    if (u_edge_radius <= 0.0 || depth >= SKY_DEPTH) return false;
    float nearest = SKY_DEPTH;
    vec2 offs[3] = vec2[3](vec2(0.0, 1.0), vec2(-0.8660254, -0.5), vec2(0.8660254, -0.5));
    for (int k = 0; k < 3; ++k) {
        vec2 p = vec2(sx, float(y)) + offs[k] * u_edge_radius;
        nearest = min(nearest, source_depth(ivec2(round(p))));
    }
    return (1.0 / nearest - 1.0 / depth) * u_disparity_scale > u_edge_disparity;
}

// Output pixel p (of an eye `size` across), at ImBuffer position q, covered: r is the ImBuffer texel nearest q.
void patch_covered(ivec2 p, ivec2 size, float q, vec4 r) {
    int y = p.y;
    float shift = r.x, depth = r.y;
    float u = (float(p.x) + 0.5) / float(size.x);
#if COARSE
    // Between two ImBuffer texels: interpolate on one surface; at a depth edge keep the neighbour whose shift
    // lands on its own surface. (At full resolution q is a texel centre and r is the answer.)
    int n = clamp(int(round(q)), 0, g_w - 1);
    int i0 = clamp(int(floor(q)), 0, g_w - 1), i1 = min(i0 + 1, g_w - 1);
    vec4 r0 = imageLoad(u_imbuffer, ivec2(i0, y)), r1 = imageLoad(u_imbuffer, ivec2(i1, y));
    if (is_covered(r0) && is_covered(r1) && same_surface(r0.y, r1.y)) {
        float f = clamp(q - float(i0), 0.0, 1.0);
        shift = mix(r0.x, r1.x, f);
        depth = mix(r0.y, r1.y, f);
    } else {
        vec4 other = (n == i0) ? r1 : r0;
        float sx_n = (u + r.x) * float(g_src_size.x) - 0.5;
        float sx_o = (u + other.x) * float(g_src_size.x) - 0.5;
        if (is_covered(other) && !same_surface(source_depth(ivec2(round(sx_n), y)), r.y)
                && same_surface(source_depth(ivec2(round(sx_o), y)), other.y)) {
            shift = other.x;
            depth = other.y;
        }
    }
#endif
    float sx = (u + shift) * float(g_src_size.x) - 0.5;
    imageStore(u_out, p, vec4(color_at(sx, y), 1.0));
#if EDGES   // the mask was cleared to 0 (client/stereo.py): only a rejected pixel's g is written
    if (near_edge(sx, y, depth)) imageStore(u_mask, p, vec4(0.0, 1.0, 0.0, 0.0));
#endif
}
