// Gathering (QUASAR 3.2.3): a quad that no later pass will merge is appended to the output list. One whose
// offsets are all below delta_flatten (grown by the fovea scale away from the gaze, fovea.glsl) is flattened.
// Needs quad.glsl and fovea.glsl.
struct GatheredQuad {     // the layout render/quadmesh.py's quads_to_gpu writes
    uvec4 head;           // x, y, size_log2, flattened
    vec4 normal_depth;
    vec4 off[4];
};
layout(std430, binding = 4) buffer Counter { uint count; };
layout(std430, binding = 6) writeonly buffer Gathered { GatheredQuad gathered[]; };
uniform uint u_capacity;
uniform float u_delta_flatten;

// The quad of Quad Map `level` at entry p: its plane and 16 offsets.
void append_quad(ivec2 p, int level, vec4 plane, vec4 off[4]) {
    uint i = atomicAdd(count, 1u);
    if (i >= u_capacity) return;
    vec4 m = max(max(abs(off[0]), abs(off[1])), max(abs(off[2]), abs(off[3])));
    float fs = fovea_scale((vec2(p) + 0.5) * float(1 << level));
    bool flattened = max(max(m.x, m.y), max(m.z, m.w)) < u_delta_flatten * fs;
    GatheredQuad g;
    g.head = uvec4(uvec2(p << level), uint(level), flattened ? 1u : 0u);
    g.normal_depth = plane;
    for (int s = 0; s < 4; ++s) g.off[s] = flattened ? vec4(0.0) : off[s];
    gathered[i] = g;
}
