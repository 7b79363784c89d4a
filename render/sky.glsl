// The sky's colour where a view has no geometry: a gradient from the horizon up, display-encoded. Shared by the
// lighting pass (render/lighting.frag.glsl, for G-buffers whose empty pixels it cannot tell by depth) and the sky
// pass (render/sky.frag.glsl).
#ifndef QUADCAST_SKY_GLSL
#define QUADCAST_SKY_GLSL
#include "camera.glsl"

// `uv` in [0, 1]^2 of a view with frustum `extents` (at distance 1) and view-to-world matrix `inv_view`.
vec3 sky_colour(mat4 inv_view, vec4 extents, vec3 sky, vec2 uv) {
    vec3 dir = normalize(mat3(inv_view) * view_ray(extents, 1.0, uv));
    vec3 c = mix(sky * 0.9, sky * vec3(0.75, 0.85, 1.1), clamp(dir.y, 0.0, 1.0));
    return pow(clamp(c, 0.0, 1.0), vec3(1.0 / 2.2));
}

#endif
