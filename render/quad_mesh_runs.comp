#version 430
// Mesh runs (render/quadmesh.py): quads of one size side by side on one surface are drawn as one rectangle --
// corners the builder (quad_mesh.comp) made: its first quad's top-left, its last quad's bottom-right, ... -- and
// the other quads as empty triangles. Along a depth edge the quadtree leaves rows and columns of 1- and 2-pixel
// quads; drawn one by one they cost llvmpipe most of a frame's triangle setup.
// A run is a row of flattened quads, each continuing the last; runs of the same extent stacked in a column, each
// continuing the one above, make one rectangle. "Continues": the two quads' planes (the builder's) meet the ray
// through the middle of their shared edge at distances within u_tolerance of each other (relative), their normals
// within acos(u_min_cos). Rows break at every u_max_run-th place of their size's grid, columns at every u_max_stack-th,
// so a rectangle never leaves its block of u_max_run x u_max_stack places.
// With a parallax bound (u_parallax > 0) "continues" asks only that the planes meet there within `bound` (a depth
// error that moves the point at most QuadMesh.run_parallax_px pixels seen from RUN_PARALLAX_M beside the layer's
// camera; normals may differ, as a detailed scene's do from pixel to pixel), and a rectangle is drawn only if every
// quad of it lies within that bound of it (`fits`); else each of its rows that fits, and the other quads one by one.
// Five passes over the layer's flattened quads, their places uploaded by the CPU:
//   PASS 0 puts each quad in a grid of its size's aligned places (a later quad wins a place, as in the cache);
//   PASS 1 marks (ACROSS, in its grid cell) a quad that continues its left neighbour;
//   PASS 2: a marked quad draws nothing; any other starts a run and finds its last quad (run_last);
//   PASS 3 marks (DOWN) a run that continues the run of the same extent above it (both ends continue);
//   PASS 4: a run marked DOWN draws nothing; any other draws the rectangle of itself and the runs marked below it
//   (with a parallax bound it writes the indices of all of them, as `fits` decides).
layout(local_size_x = 64) in;
#include "quad.glsl"

layout(std430, binding = 0) readonly buffer Places { uvec4 places[]; };     // x, y, size_log2, first vertex
layout(std430, binding = 1) readonly buffer Planes { vec4 planes[]; };      // per 4 vertices: normal, offset
layout(std430, binding = 2) writeonly buffer Indices { uint indices[]; };
layout(std430, binding = 3) buffer Grid { uint grid[]; };   // place index + 1 (0 where none) | marks
layout(std430, binding = 4) buffer Last { uint run_last[]; };  // a run's first place -> its last place
const uint ACROSS = 0x80000000u, DOWN = 0x40000000u, PLACE = 0x3fffffffu;

uniform uint u_count;
uniform uint u_level_offset[12]; // where each size's grid starts in Grid
uniform uint u_max_run;
uniform uint u_max_stack;
uniform float u_tolerance;
uniform float u_min_cos;
uniform float u_parallax;

uint cell(uint x, uint y, uint s) {
    uint columns = (uint(u_size.x) + (1u << s) - 1u) >> s;
    return u_level_offset[s] + (y >> s) * columns + (x >> s);
}

// How far along the unit ray r a surface at distance t may move: u_tolerance of t, or with a parallax bound, as far
// as moves a point at view depth z = t * -r.z by u_parallax * z^2 in depth.
float bound(vec3 r, float t) {
    return max(u_tolerance * t, u_parallax * t * t * -r.z);
}

// Whether the planes of the quads starting at vertices a and b meet the ray through image point e (the middle
// of their shared edge) close together, facing the same way (with a parallax bound: within `bound`, either way).
bool continues(uint a, uint b, vec2 e) {
    vec4 pa = planes[a / 4u], pb = planes[b / 4u];
    vec3 r = normalize(ray_dir(e));
    float ta = ray_plane_t(r, pa.xyz, pa.w), tb = ray_plane_t(r, pb.xyz, pb.w);
    if (u_parallax > 0.0) return abs(ta - tb) <= bound(r, ta);
    return dot(pa.xyz, pb.xyz) >= u_min_cos && abs(ta - tb) <= u_tolerance * ta;
}

void draw(uint first, uint tl, uint tr, uint bl, uint br) {   // corners: vertex tl + 0, tr + 1, bl + 2, br + 3
    uint k0 = first / 2u * 3u;
    indices[k0] = tl; indices[k0 + 1u] = bl + 2u; indices[k0 + 2u] = tr + 1u;
    indices[k0 + 3u] = tr + 1u; indices[k0 + 4u] = bl + 2u; indices[k0 + 5u] = br + 3u;
}

void own(uint first) { draw(first, first, first, first, first); }   // the quad alone, as the builder made it
void empty(uint first) { for (uint j = 0u; j < 6u; ++j) indices[first / 2u * 3u + j] = first; }

// The mesh vertex at image point e of the quad starting at vertex v, as the builder made it (quad_mesh.comp).
vec3 corner(uint v, vec2 e) {
    vec4 pl = planes[v / 4u];
    return quad_corner_position(e, pl.xyz, pl.w, 0.0);
}

// Whether every quad of the rectangle whose corners are the quads at places tl, tr (top row) and bl, br (bottom
// row) lies within the parallax bound of it: its plane and the rectangle's two triangles (as `draw` makes them)
// meet the ray through its centre within `bound` of each other.
bool fits(uint tl, uint tr, uint bl, uint br) {
    uvec4 a = places[tl], b = places[tr], c = places[bl], d = places[br];
    uint s = a.z, size = 1u << s;
    vec2 lo = vec2(a.xy), hi = vec2(float(b.x + size), float(c.y + size));
    vec3 c00 = corner(a.w, lo), c10 = corner(b.w, vec2(hi.x, lo.y)), c01 = corner(c.w, vec2(lo.x, hi.y));
    vec3 c11 = corner(d.w, hi);
    for (uint y = a.y; y <= c.y; y += size) {
        for (uint x = a.x; x <= b.x; x += size) {
            uint m = (grid[cell(x, y, s)] & PLACE) - 1u;
            vec2 e = vec2(x, y) + 0.5 * float(size);
            vec3 r = normalize(ray_dir(e));
            vec4 own_plane = planes[places[m].w / 4u];
            float t = ray_plane_t(r, own_plane.xyz, own_plane.w);
            vec2 uv = (e - lo) / (hi - lo);
            vec3 o = uv.x + uv.y <= 1.0 ? c00 : c11;       // triangle (tl, bl, tr) or (tr, bl, br)
            vec3 n = cross(c10 - o, c01 - o);
            float t_rect = dot(n, o) / dot(n, r);
            if (!(abs(t_rect - t) <= bound(r, t))) return false;
        }
    }
    return true;
}

void main() {
    uint k = gl_GlobalInvocationID.x;
    if (k >= u_count) return;
    uvec4 p = places[k];
    uint s = p.z, size = 1u << s, here = cell(p.x, p.y, s);
#if PASS == 0
    atomicMax(grid[here], k + 1u);
#else
    uint held = grid[here];   // only the mark bits of a cell change after PASS 0
    if ((held & PLACE) != k + 1u) {   // a later quad holds this place: this one drawn as built
        if (PASS == 2) own(p.w);
        return;
    }
#if PASS == 1
    if ((p.x >> s) % u_max_run == 0u) return;
    uint left = grid[cell(p.x - size, p.y, s)] & PLACE;
    if (left != 0u && continues(places[left - 1u].w, p.w, vec2(p.x, float(p.y) + 0.5 * float(size))))
        atomicOr(grid[here], ACROSS);
#elif PASS == 2
    if ((held & ACROSS) != 0u) {
        empty(p.w);
        return;
    }
    uint last = k;
    for (uint x = p.x + size; x < uint(u_size.x); x += size) {
        uint next = grid[cell(x, p.y, s)];
        if ((next & ACROSS) == 0u) break;
        last = (next & PLACE) - 1u;
    }
    run_last[k] = last;
#elif PASS == 3
    if ((held & ACROSS) != 0u || (p.y >> s) % u_max_stack == 0u) return;
    uint up = grid[cell(p.x, p.y - size, s)];
    if ((up & PLACE) == 0u || (up & ACROSS) != 0u) return;
    uvec4 above = places[(up & PLACE) - 1u], a_end = places[run_last[(up & PLACE) - 1u]], end = places[run_last[k]];
    if (a_end.x == end.x && continues(above.w, p.w, vec2(float(p.x) + 0.5 * float(size), p.y))
            && continues(a_end.w, end.w, vec2(float(end.x) + 0.5 * float(size), p.y)))
        atomicOr(grid[here], DOWN);
#else
    if ((held & ACROSS) != 0u) return;
    if ((held & DOWN) != 0u) {
        if (!(u_parallax > 0.0)) empty(p.w);   // else its rectangle's first quad decides (below)
        return;
    }
    uint bottom = k;
    for (uint y = p.y + size; y < uint(u_size.y); y += size) {
        uint below = grid[cell(p.x, y, s)];
        if ((below & DOWN) == 0u) break;
        bottom = (below & PLACE) - 1u;
    }
    if (u_parallax > 0.0) {
        // the rectangle if every quad of it lies within the bound of it; else each row's run if its quads lie
        // within the bound of that, else each quad alone
        if (!fits(k, run_last[k], bottom, run_last[bottom])) {
            for (uint y = p.y; y <= places[bottom].y; y += size) {
                uint head = (grid[cell(p.x, y, s)] & PLACE) - 1u, last = run_last[head];
                bool row = fits(head, last, head, last);
                for (uint x = p.x; x <= places[last].x; x += size) {
                    uint m = (grid[cell(x, y, s)] & PLACE) - 1u;
                    if (!row) own(places[m].w);
                    else if (m != head) empty(places[m].w);
                }
                if (row) draw(places[head].w, places[head].w, places[last].w, places[head].w, places[last].w);
            }
            return;
        }
        for (uint y = p.y + size; y <= places[bottom].y; y += size)   // the rows below: drawn by this one
            empty(places[(grid[cell(p.x, y, s)] & PLACE) - 1u].w);
    }
    draw(p.w, p.w, places[run_last[k]].w, places[bottom].w, places[run_last[bottom]].w);
#endif
#endif
}
