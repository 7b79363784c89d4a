// The one-pass peel's per-pixel lists (peel_list.frag.glsl builds them, peel_resolve.frag.glsl reads them): a
// head per pixel (row-major from GL's bottom-left pixel) and the fragments, each linked to the one stored before
// it at its pixel. Links count from 1 (fragment k is fragments[k - 1]) and END, 0, ends a list: llvmpipe reads 0
// in the lanes a loop has masked off, which must end the loop there too (with another END it ran such loops to
// its iteration limit: a pass 100 times slower).
const uint END = 0u;

struct PeelFragment {
    vec4 albedo;       // the G-buffer's outputs (render/material.glsl)
    vec4 normal;
    vec4 position;
    float depth;       // window depth
    int object_id;
    uint next;
    uint pad;
};

layout(std430, binding = 0) buffer PeelHeads {
    uint fragment_count;     // fragments that passed (more than the capacity: some were not stored)
    uint heads[];
};

layout(std430, binding = 1) buffer PeelFragments {
    PeelFragment fragments[];
};

uniform int u_list_width;      // pixels in a row of the heads
