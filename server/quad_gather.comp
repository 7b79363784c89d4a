#version 430
// Gathering (QUASAR 3.2.3) of the last Quad Map: the merge passes append the quads of every finer map as they
// leave them unmerged (quad_merge.comp); what the last map holds is appended here.
layout(local_size_x = 8, local_size_y = 8) in;
#include "quad.glsl"
#include "quad_entry.glsl"
#include "quad_tiles.glsl"
#include "fovea.glsl"
#include "quad_append.glsl"

layout(std430, binding = 0) readonly buffer Planes { vec4 planes[]; };
layout(std430, binding = 3) readonly buffer Offsets { vec4 offs[]; };
uniform ivec2 u_map_size;
uniform int u_level;

void main() {
    ivec2 p = tile_invocation();
    if (p.x < 0 || any(greaterThanEqual(p, u_map_size))) return;
    uint index = uint(p.y * u_map_size.x + p.x);
    vec4 plane = planes[index];
    if (plane.w <= 0.0) return;
    vec4 off[4];
    for (int s = 0; s < 4; ++s) off[s] = offs[4 * index + s];
    append_quad(p, u_level, plane, off);
}
