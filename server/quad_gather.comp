#version 430
// Gathering (QUASAR 3.2.3): append every valid entry of one Quad Map to the output list. A quad whose offsets
// are all below delta_flatten (grown by the fovea scale away from the gaze, fovea.glsl) is flattened.
layout(local_size_x = 8, local_size_y = 8) in;
#include "quad.glsl"
#include "quad_entry.glsl"
#include "quad_tiles.glsl"
#include "fovea.glsl"

struct GatheredQuad {     // the layout render/quadmesh.py's quads_to_gpu writes
    uvec4 head;           // x, y, size_log2, flattened
    vec4 normal_depth;
    vec4 off[4];
};
layout(std430, binding = 0) readonly buffer Planes { vec4 planes[]; };
layout(std430, binding = 3) readonly buffer Offsets { vec4 offs[]; };
layout(std430, binding = 1) buffer Counter { uint count; };
layout(std430, binding = 2) writeonly buffer Gathered { GatheredQuad gathered[]; };
uniform ivec2 u_map_size;
uniform int u_level;
uniform uint u_capacity;
uniform float u_delta_flatten;

void main() {
    ivec2 p = tile_invocation();
    if (p.x < 0 || any(greaterThanEqual(p, u_map_size))) return;
    uint index = uint(p.y * u_map_size.x + p.x);
    vec4 plane = planes[index];
    if (plane.w <= 0.0) return;
    vec4 off[4];
    for (int s = 0; s < 4; ++s) off[s] = offs[4 * index + s];
    uint i = atomicAdd(count, 1u);
    if (i >= u_capacity) return;
    vec4 m = max(max(abs(off[0]), abs(off[1])), max(abs(off[2]), abs(off[3])));
    float fs = fovea_scale((vec2(p) + 0.5) * float(1 << u_level));
    bool flattened = max(max(m.x, m.y), max(m.z, m.w)) < u_delta_flatten * fs;
    GatheredQuad g;
    g.head = uvec4(uvec2(p << u_level), uint(u_level), flattened ? 1u : 0u);
    g.normal_depth = plane;
    for (int s = 0; s < 4; ++s) g.off[s] = flattened ? vec4(0.0) : off[s];
    gathered[i] = g;
}
