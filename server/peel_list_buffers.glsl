// The one-pass peel's per-pixel lists (peel_list.frag.glsl builds them, peel_resolve.frag.glsl reads them): a
// head per pixel (row-major from GL's bottom-left pixel) and the fragments, each linked to the one stored before
// it at its pixel. Links count from 1 (fragment k is fragments[k - 1]) and END, 0, ends a list. With 0xFFFFFFFF as
// END the resolve pass on llvmpipe took 100 times as long (170-220 ms instead of about 1 ms) and a loop bounded at
// 64 steps did not; our reading is that lanes a loop has masked off read 0 and never reach another END.
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
