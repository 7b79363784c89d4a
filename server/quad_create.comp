#version 430
// Quad generation (QUASAR 3.2.1): one quad proxy per G-buffer pixel with 16 depth offsets. Each of the 3x3
// lattice points of the pixel (corners, edge midpoints, centre) is projected onto the pixel's own plane and the
// planes of the neighbours that share it; neighbours within delta_max (normalised depth) are averaged in.
layout(local_size_x = 8, local_size_y = 8) in;
#include "quad.glsl"
#include "quad_entry.glsl"

layout(std430, binding = 0) writeonly buffer QuadMap0 { QuadEntry quads[]; };
uniform sampler2D u_position;   // view-space position, w > 0 where geometry (GL rows: bottom first)
uniform sampler2D u_normal;
uniform usampler2D u_mask;      // optional: only pixels with mask != 0 get quads
uniform bool u_use_mask;
uniform bool u_exclude_inner;   // wide FOV: skip pixels whose ray lies inside the main view's frustum
uniform vec4 u_inner_frustum;   // the main view's l, r, b, t at distance 1
uniform float u_delta_max;
uniform float u_max_angle;      // radians: normals are kept within this angle of the view ray
uniform float u_sky_distance;   // > 0: pixels with no geometry get a camera-facing quad this far away
uniform float u_max_depth;      // geometry farther than this (view depth) gets no quad: the far field shows it

bool load(ivec2 p, out vec3 n, out vec3 pos) {
    if (any(lessThan(p, ivec2(0))) || any(greaterThanEqual(p, u_size))) return false;
    ivec2 g = ivec2(p.x, u_size.y - 1 - p.y);
    if (u_use_mask && texelFetch(u_mask, g, 0).r == 0u) return false;
    vec4 P = texelFetch(u_position, g, 0);
    if (P.w > 0.0 && -P.z > u_max_depth) return false;
    if (P.w <= 0.0) {
        if (u_sky_distance <= 0.0) return false;
        pos = normalize(ray_dir(vec2(p) + 0.5)) * u_sky_distance;
        n = -normalize(pos);
        return true;
    }
    pos = P.xyz;
    n = normalize(texelFetch(u_normal, g, 0).xyz);
    return true;
}

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(p, u_size))) return;
    uint index = uint(p.y * u_size.x + p.x);
    QuadEntry e;
    e.plane = vec4(0.0);
    for (int s = 0; s < 4; ++s) e.off[s] = vec4(0.0);

    vec3 n0, P0;
    if (!load(p, n0, P0)) { quads[index] = e; return; }
    if (u_exclude_inner) {
        vec2 r = P0.xy / -P0.z;
        if (r.x > u_inner_frustum.x && r.x < u_inner_frustum.y && r.y > u_inner_frustum.z && r.y < u_inner_frustum.w) {
            quads[index] = e;
            return;
        }
    }
    n0 = limit_grazing(n0, normalize(-P0), u_max_angle);
    float d0 = dot(n0, P0);

    // Neighbour planes (3x3 block; the centre is the pixel itself).
    vec3 nn[9];
    float dn[9];
    bool ok[9];
    for (int j = 0; j < 3; ++j) for (int i = 0; i < 3; ++i) {
        int k = j * 3 + i;
        vec3 n, P;
        ok[k] = (k != 4) && load(p + ivec2(i - 1, j - 1), n, P);
        if (ok[k]) { n = limit_grazing(n, normalize(-P), u_max_angle); nn[k] = n; dn[k] = dot(n, P); }
    }

    // Offsets at the 3x3 lattice points (a, b) in half-pixel steps from the pixel's top-left corner.
    float lattice[9];
    for (int b = 0; b < 3; ++b) for (int a = 0; a < 3; ++a) {
        vec2 q = vec2(p) + 0.5 * vec2(a, b);
        vec3 r = normalize(ray_dir(q));
        float t_own = ray_plane_t(r, n0, d0);
        float z_own = normalized_depth(depth_along(q, t_own));
        float sum = t_own;
        float count = 1.0;
        // Neighbours touching lattice point (a, b): dx in {-1, 0} at a = 0, {0} at a = 1, {0, 1} at a = 2.
        for (int dy = (b == 0 ? -1 : 0); dy <= (b == 2 ? 1 : 0); ++dy)
            for (int dx = (a == 0 ? -1 : 0); dx <= (a == 2 ? 1 : 0); ++dx) {
                int k = (dy + 1) * 3 + (dx + 1);
                if (!ok[k]) continue;
                float t = ray_plane_t(r, nn[k], dn[k]);
                if (abs(normalized_depth(depth_along(q, t)) - z_own) < u_delta_max) { sum += t; count += 1.0; }
            }
        lattice[b * 3 + a] = sum / count - t_own;
    }
    for (int s = 0; s < 4; ++s) for (int c = 0; c < 4; ++c) {
        int a = (s & 1) + (c & 1);
        int b = (s >> 1) + (c >> 1);
        e.off[s][c] = lattice[b * 3 + a];
    }
    e.plane = vec4(n0, -P0.z);
    quads[index] = e;
}
