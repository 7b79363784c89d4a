#version 430
// Quad generation (QUASAR 3.2.1): one quad proxy per G-buffer pixel with 16 depth offsets. Each of the 3x3
// lattice points of the pixel (corners, edge midpoints, centre) is projected onto the pixel's own plane and the
// planes of the neighbours that share it; neighbours within delta_max (normalised depth) are averaged in. The
// neighbours' planes come from quad_planes.comp, computed once per pixel.
layout(local_size_x = 8, local_size_y = 8) in;
#include "quad.glsl"
#include "quad_entry.glsl"
#include "quad_tiles.glsl"

layout(std430, binding = 0) writeonly buffer Planes0 { vec4 planes[]; };
layout(std430, binding = 1) writeonly buffer Offsets0 { vec4 offs[]; };
#include "quad_pixel.glsl"
uniform sampler2D u_pixel_planes;   // quad_planes.comp
uniform bool u_exclude_inner;   // wide FOV: skip pixels whose ray lies inside the main view's frustum
uniform vec4 u_inner_frustum;   // the main view's l, r, b, t at distance 1
uniform float u_delta_max;

void main() {
    ivec2 p = tile_invocation();
    if (p.x < 0 || any(greaterThanEqual(p, u_size))) return;
    uint index = uint(p.y * u_size.x + p.x);
    vec3 n0, P0;
    if (!load(p, n0, P0)) { planes[index] = vec4(0.0); return; }
    if (u_exclude_inner) {
        vec2 r = P0.xy / -P0.z;
        if (r.x > u_inner_frustum.x && r.x < u_inner_frustum.y && r.y > u_inner_frustum.z && r.y < u_inner_frustum.w) {
            planes[index] = vec4(0.0);
            return;
        }
    }
    n0 = limit_grazing(n0, normalize(-P0), u_max_angle);
    float d0 = dot(n0, P0);

    // Neighbour planes (3x3 block; the centre is the pixel itself), as quad_planes.comp left them.
    vec3 nn[9];
    float dn[9];
    bool ok[9];
    for (int j = 0; j < 3; ++j) for (int i = 0; i < 3; ++i) {
        int k = j * 3 + i;
        ivec2 q = p + ivec2(i - 1, j - 1);
        bool inside = all(greaterThanEqual(q, ivec2(0))) && all(lessThan(q, u_size));
        vec4 e = texelFetch(u_pixel_planes, clamp(q, ivec2(0), u_size - 1), 0);
        if (!inside) e = vec4(0.0);
        ok[k] = (k != 4) && e.xyz != vec3(0.0);
        nn[k] = e.xyz;
        dn[k] = e.w;
    }

    // Offsets at the 3x3 lattice points (a, b) in half-pixel steps from the pixel's top-left corner. The
    // neighbours touching lattice point (a, b) are listed out (dx in {-1, 0} at a = 0, {0} at a = 1, {0, 1} at
    // a = 2, likewise dy; the pixel itself, k = 4, is its own plane): constant indices keep the arrays in
    // registers.
    float lattice[9];
#define LATTICE_BEGIN(A, B) { \
        vec2 q = vec2(p) + 0.5 * vec2(A, B); \
        vec3 r = normalize(ray_dir(q)); \
        float t_own = ray_plane_t(r, n0, d0); \
        float z_own = normalized_depth(depth_along(q, t_own)); \
        float sum = t_own; \
        float count = 1.0;
#define NEIGHBOUR(K) \
        if (ok[K]) { \
            float t = ray_plane_t(r, nn[K], dn[K]); \
            if (abs(normalized_depth(depth_along(q, t)) - z_own) < u_delta_max) { sum += t; count += 1.0; } \
        }
#define LATTICE_END(A, B) lattice[(B) * 3 + (A)] = sum / count - t_own; }
    LATTICE_BEGIN(0, 0) NEIGHBOUR(0) NEIGHBOUR(1) NEIGHBOUR(3) LATTICE_END(0, 0)
    LATTICE_BEGIN(1, 0) NEIGHBOUR(1) LATTICE_END(1, 0)
    LATTICE_BEGIN(2, 0) NEIGHBOUR(1) NEIGHBOUR(2) NEIGHBOUR(5) LATTICE_END(2, 0)
    LATTICE_BEGIN(0, 1) NEIGHBOUR(3) LATTICE_END(0, 1)
    LATTICE_BEGIN(1, 1) LATTICE_END(1, 1)
    LATTICE_BEGIN(2, 1) NEIGHBOUR(5) LATTICE_END(2, 1)
    LATTICE_BEGIN(0, 2) NEIGHBOUR(3) NEIGHBOUR(6) NEIGHBOUR(7) LATTICE_END(0, 2)
    LATTICE_BEGIN(1, 2) NEIGHBOUR(7) LATTICE_END(1, 2)
    LATTICE_BEGIN(2, 2) NEIGHBOUR(5) NEIGHBOUR(7) NEIGHBOUR(8) LATTICE_END(2, 2)
    for (int s = 0; s < 4; ++s) {
        vec4 o;
        for (int c = 0; c < 4; ++c) o[c] = lattice[((s >> 1) + (c >> 1)) * 3 + (s & 1) + (c & 1)];
        offs[4 * index + s] = o;
    }
    planes[index] = vec4(n0, -P0.z);
}
