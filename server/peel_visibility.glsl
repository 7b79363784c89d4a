// Effective Depth Peeling's test (QUASAR 3.3, after Kim & Lee 2023), shared by the layer-by-layer peel
// (peel.frag.glsl) and the one-pass peel (peel_list.frag.glsl). A fragment at depth z behind the visible surface
// at depth z0 shifts against it by up to f * r * (1/z0 - 1/z) pixels when the eye moves by r; it is potentially
// visible if, within that radius, the visible layer is farther than the fragment (an edge it can appear from
// behind). Needs camera.glsl and MAX_DEPTH_LEVELS.

uniform sampler2D u_visible_position;  // the visible layer's view positions (w > 0 where geometry)
uniform sampler2D u_visible_max;       // its farthest depth over blocks, levels side by side (peel_depth_max.comp)
uniform ivec4 u_max_levels[MAX_DEPTH_LEVELS];   // per level: x offset in u_visible_max, width, height
uniform int u_max_level;               // the last level built (-1: no early reject)
uniform float u_focal_px;              // pixels per unit of x/z
uniform float u_viewcell_radius;       // metres
uniform float u_connectivity;          // relative depth gap that still counts as the same surface
uniform int u_max_radius_px;

float visible_depth(ivec2 p) {
    vec4 v = texelFetch(u_visible_position, clamp(p, ivec2(0), textureSize(u_visible_position, 0) - 1), 0);
    return is_sky(v) ? SKY_DEPTH : -v.z;
}

// Whether a fragment at pixel px and view depth z (behind the visible layer there) could be seen from somewhere
// in the view sphere.
bool potentially_visible(ivec2 px, float z) {
    float z0 = visible_depth(px);
    float radius = u_focal_px * u_viewcell_radius * (1.0 / min(z0, z) - 1.0 / z);
    radius = min(radius, float(u_max_radius_px));
    if (radius < 0.5) return false;
    // Early reject: every ring sample below lies in the square px +- reach (clamped to the image), which the
    // coarsest level needed covers with at most 2 x 2 texels; if the visible layer is nearer than the threshold
    // everywhere in it, no sample can pass. The same fragments survive as without it, for fewer fetches.
    int reach = int(radius + 1.0);
    int level = findMSB(2 * reach) + 1;                   // 2^level > 2 * reach
    if (level <= u_max_level) {
        // (one texture at lod 0: llvmpipe takes an explicit lod per 2 x 2 quad, not per fragment)
        int x0 = u_max_levels[level].x;
        ivec2 top = u_max_levels[0].yz - 1;
        ivec2 a = clamp(px - reach, ivec2(0), top) >> level;
        ivec2 b = clamp(px + reach, ivec2(0), top) >> level;
        float farthest = max(max(texelFetch(u_visible_max, ivec2(x0 + a.x, a.y), 0).r,
                                 texelFetch(u_visible_max, ivec2(x0 + b.x, a.y), 0).r),
                             max(texelFetch(u_visible_max, ivec2(x0 + a.x, b.y), 0).r,
                                 texelFetch(u_visible_max, ivec2(x0 + b.x, b.y), 0).r));
        if (farthest < z * (1.0 - u_connectivity)) return false;
    }
    for (int ring = 1; ring <= 3; ++ring) {
        float rr = radius * float(ring) / 3.0;
        for (int k = 0; k < 8; ++k) {
            float a = 0.7853982 * float(k) + 0.3926991 * float(ring & 1);
            ivec2 q = px + ivec2(round(rr * vec2(cos(a), sin(a))));
            if (visible_depth(q) >= z * (1.0 - u_connectivity)) return true;
        }
    }
    return false;
}
