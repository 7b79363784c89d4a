#version 430
// YORO Algorithm 3 (Patcher), one invocation per output pixel of the other eye. A covered pixel takes the
// dominant eye's colour at the source position the ImBuffer gives (linearly interpolated along x between
// neighbours on one surface). A disoccluded pixel is filled from the background side only (observation O2):
// a kernel as wide as the disocclusion and u_kernel_rows high walks away from the background edge, skips
// foreground samples, and weighs each sample with eq. 6, W = w/2 + 0.3 w (distance into the hole / width).
// The mask gets r = disoccluded, g = conservative edge reject (stereo shading reprojection's triangle filter:
// a covered pixel whose source lies within u_edge_radius of something nearer is not trusted).
// Built twice: HOLES 0 runs on every pixel, patches the covered ones and lists the disoccluded ones; HOLES 1 runs
// on that list only (an indirect dispatch). In one pass llvmpipe would run the hole kernel's loops for every
// covered pixel too (it executes both sides of a branch for all 8 lanes) -- for the same reason the synthesizer's
// fixed settings are compile-time: LINEAR (interpolate source colours along x), COARSE (the ImBuffer is
// narrower than the eye) and EDGES (compute the conservative edge reject; YORO alone, mode 1, has no use for it).
#if HOLES
layout(local_size_x = 64) in;
#else
layout(local_size_x = 8, local_size_y = 8) in;
#endif
#include "stereo_common.glsl"

layout(std430, binding = 3) buffer Holes { uint hole_count; uint holes[]; };   // (y << 16) | x

layout(rgba32f, binding = 0) readonly uniform image2D u_imbuffer;
layout(rgba8, binding = 1) writeonly uniform image2D u_out;
layout(rg8, binding = 2) writeonly uniform image2D u_mask;
uniform sampler2D u_color;          // dominant eye, lit sRGB (GL rows, bottom first)
uniform int u_kernel_rows;          // Patcher kernel height h
uniform int u_kernel_max;           // Patcher kernel width cap (ImBuffer pixels)
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
    if (same_surface(source_depth(a), source_depth(b))) return mix(ca, cb, f);
    return f < 0.5 ? ca : cb;
#endif
}

// Source x (source pixel-centre units) of ImBuffer texel (j, y) holding record r.
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
    vec4 r = imageLoad(u_imbuffer, ivec2(n, y));
#if !HOLES
    if (r.z != 0.0) {  // disoccluded: the second pass fills it
        holes[atomicAdd(hole_count, 1u)] = (uint(p.y) << 16) | uint(p.x);
        return;
    }
    // Covered: sample the dominant eye where this pixel comes from.
    int i0 = clamp(int(floor(q)), 0, g_w - 1), i1 = min(i0 + 1, g_w - 1);
    vec4 r0 = imageLoad(u_imbuffer, ivec2(i0, y)), r1 = imageLoad(u_imbuffer, ivec2(i1, y));
    float shift = r.x, depth = r.y;
    float u = (float(p.x) + 0.5) / float(size.x);
    if (r0.z == 0.0 && r1.z == 0.0 && same_surface(r0.y, r1.y)) {
        float f = clamp(q - float(i0), 0.0, 1.0);
        shift = mix(r0.x, r1.x, f);
        depth = mix(r0.y, r1.y, f);
    }
#if COARSE
    else {
        // Coarse ImBuffer at a depth edge: keep the neighbour whose shift lands on its own surface.
        vec4 other = (n == i0) ? r1 : r0;
        float sx_n = (u + r.x) * float(g_src_size.x) - 0.5;
        float sx_o = (u + other.x) * float(g_src_size.x) - 0.5;
        if (other.z == 0.0 && !same_surface(source_depth(ivec2(round(sx_n), y)), r.y)
                && same_surface(source_depth(ivec2(round(sx_o), y)), other.y)) {
            shift = other.x;
            depth = other.y;
        }
    }
#endif
    float sx = (u + shift) * float(g_src_size.x) - 0.5;
    imageStore(u_out, p, vec4(color_at(sx, y), 1.0));
#if EDGES
    imageStore(u_mask, p, vec4(0.0, near_edge(sx, y, depth) ? 1.0 : 0.0, 0.0, 0.0));
#else
    imageStore(u_mask, p, vec4(0.0));
#endif
#else
    // Disoccluded: r = (left edge, background depth, width, background-side neighbour).
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
            if (s.z != 0.0) continue;                                               // another hole
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
