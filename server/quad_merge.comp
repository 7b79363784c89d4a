#version 430
// Quad merging (QUASAR 3.2.2): 2x2 quads of Quad Map l become one quad of map l+1 when their planes are similar
// (plane-equation distance < delta_sim), or, in the first coarse passes, when they have no depth discontinuity
// (normalised centre depths within delta_max). Merged children are cleared; unmerged ones mark their parent so
// no larger quad covers them, and, as no later pass can merge them, are gathered here (quad_append.glsl).
// Offsets are recomputed against the averaged plane from the children's corners.
// Foveated (fovea.glsl): away from the gaze, delta_sim grows by the fovea scale and the coarse passes go on
// log2(scale) levels further.
layout(local_size_x = 8, local_size_y = 8) in;
#include "quad.glsl"
#include "quad_entry.glsl"
#include "quad_tiles.glsl"
#include "fovea.glsl"
#include "quad_append.glsl"

layout(std430, binding = 0) buffer PlanesIn { vec4 plane_in[]; };
layout(std430, binding = 1) readonly buffer OffsetsIn { float off_in[]; };   // 16 per entry
layout(std430, binding = 2) writeonly buffer PlanesOut { vec4 plane_out[]; };
layout(std430, binding = 3) writeonly buffer OffsetsOut { vec4 off_out[]; }; // 4 per entry
uniform ivec2 u_in_size;
uniform ivec2 u_out_size;
uniform int u_out_level;       // output quads span 2^u_out_level pixels
uniform int u_coarse_passes;   // levels up to this one also merge continuous quads
uniform float u_delta_sim;
uniform float u_delta_max;
uniform float u_max_angle;

// Gather the valid children of an output entry that does not merge them (children are at level u_out_level - 1).
void append_children(ivec2 p, vec4 plane[4], uint child_index[4]) {
    for (int c = 0; c < 4; ++c) {
        if (!(plane[c].w > 0.0)) continue;
        uint b = 16u * child_index[c];
        vec4 off[4];
        for (int s = 0; s < 4; ++s)
            off[s] = vec4(off_in[b + 4u * uint(s)], off_in[b + 4u * uint(s) + 1u], off_in[b + 4u * uint(s) + 2u],
                          off_in[b + 4u * uint(s) + 3u]);
        append_quad(2 * p + ivec2(c & 1, c >> 1), u_out_level - 1, plane[c], off);
    }
}

// Merge four valid children into output entry out_index if their planes are similar enough (see the top);
// false, writing nothing, if not.
bool merge_children(ivec2 p, vec4 plane[4], uint child_index[4], uint out_index) {
    float child_size = float(1 << (u_out_level - 1));
    // Plane equations (n, d) of the children, their centre depths.
    vec4 eq[4];
    float z[4];
    for (int c = 0; c < 4; ++c) {
        vec2 centre = (vec2(2 * p + ivec2(c & 1, c >> 1)) + 0.5) * child_size;
        eq[c] = vec4(plane[c].xyz, plane_d(plane[c].xyz, centre, plane[c].w));
        z[c] = normalized_depth(plane[c].w);
    }
    float fs = fovea_scale((vec2(p) + 0.5) * child_size * 2.0);
    float delta_sim = u_delta_sim * fs;
    bool coarse = u_out_level <= u_coarse_passes + int(floor(log2(fs)));
    bool similar = true, continuous = true;
    for (int a = 0; a < 4; ++a) for (int b = a + 1; b < 4; ++b) {
        similar = similar && distance(eq[a], eq[b]) < delta_sim;
        continuous = continuous && abs(z[a] - z[b]) < u_delta_max;
    }
    if (!(similar || (coarse && continuous))) return false;

    vec4 avg = (eq[0] + eq[1] + eq[2] + eq[3]) * 0.25;
    float len_n = length(avg.xyz);
    if (len_n < 1e-3) return false;
    vec3 n = avg.xyz / len_n;
    float d = avg.w / len_n;
    float size = child_size * 2.0;
    vec2 origin = vec2(p) * size;
    vec2 centre = origin + 0.5 * size;
    vec3 rc = normalize(ray_dir(centre));
    n = limit_grazing(n, -rc, u_max_angle);
    float t_centre = ray_plane_t(rc, n, d);
    d = dot(n, rc * t_centre);
    // Sub-quad c of the merged quad is child c; its corner k is child c's outer corner k (the child's offset
    // off[k][k]: sub-quad k, corner k).
    for (int c = 0; c < 4; ++c) {
        vec2 child_origin = origin + child_size * vec2(c & 1, c >> 1);
        vec4 o;
        for (int k = 0; k < 4; ++k) {
            vec2 q = child_origin + child_size * vec2(k & 1, k >> 1);
            vec3 r = normalize(ray_dir(q));
            float t_surface = ray_plane_t(r, eq[c].xyz, eq[c].w) + off_in[16 * child_index[c] + 5 * k];
            o[k] = t_surface - ray_plane_t(r, n, d);
        }
        off_out[4 * out_index + c] = o;
    }
    plane_out[out_index] = vec4(n, depth_along(centre, t_centre));
    for (int c = 0; c < 4; ++c) plane_in[child_index[c]] = vec4(0.0, 0.0, 0.0, EMPTY);
    return true;
}

void main() {
    ivec2 p = tile_invocation();
    if (p.x < 0 || any(greaterThanEqual(p, u_out_size))) return;
    uint out_index = uint(p.y * u_out_size.x + p.x);

    // Only the children's planes are read until the four of them are known to merge.
    vec4 plane[4];
    uint child_index[4];
    int valid = 0, empty = 0;
    for (int c = 0; c < 4; ++c) {
        ivec2 q = 2 * p + ivec2(c & 1, c >> 1);
        if (any(greaterThanEqual(q, u_in_size))) { empty++; plane[c] = vec4(0.0); continue; }
        child_index[c] = uint(q.y * u_in_size.x + q.x);
        plane[c] = plane_in[child_index[c]];
        if (plane[c].w > 0.0) valid++;
        else if (plane[c].w == EMPTY) empty++;
    }
    if (empty == 4) { plane_out[out_index] = vec4(0.0, 0.0, 0.0, EMPTY); return; }
    if (valid == 4 && merge_children(p, plane, child_index, out_index)) return;
    plane_out[out_index] = vec4(0.0, 0.0, 0.0, MARKED);
    append_children(p, plane, child_index);
}

