// Camera conventions every shader shares (the GLSL side of render/camera.py). View space looks down -Z with +Y
// up. A frustum is given by its extents (left, right, bottom, top) on a plane at distance `near` in front of
// the camera; render/camera.py's Frustum.unit_extents gives them at distance 1 (near = 1).
#ifndef QUADCAST_CAMERA_GLSL
#define QUADCAST_CAMERA_GLSL

// Linear view depth (metres along -Z) that stands for "nothing hit" (sky): beyond any real depth.
const float SKY_DEPTH = 1e30;

// Whether a G-buffer view-space position texel holds sky, i.e. nothing was drawn there: render/material.glsl
// writes w = shininess > 0 wherever there is geometry, and the G-buffer is cleared to 0.
bool is_sky(vec4 view_position) {
    return !(view_position.w > 0.0);
}

// A linear view depth that holds sky: 0 (nothing drawn), negative, NaN, or SKY_DEPTH and beyond.
bool is_sky_depth(float depth) {
    return !(depth > 0.0 && depth < SKY_DEPTH);
}

// The (unnormalised) view-space ray through point p of an image `size` across, ending on the plane z = -near:
// p is measured from the image corner at (extents.x, extents.z) towards (extents.y, extents.w). With GL's
// bottom-left origin pass the extents as they are; for a top-left origin (image rows counted from the top)
// pass extents.xywz.
vec3 view_ray(vec4 extents, float near, vec2 p, vec2 size) {
    return vec3(extents.x + (extents.y - extents.x) * p.x / size.x,
                extents.z + (extents.w - extents.z) * p.y / size.y,
                -near);
}

// The same from a point given as a fraction of the image (uv in [0, 1]^2, from the (extents.x, extents.z) corner).
vec3 view_ray(vec4 extents, float near, vec2 uv) {
    return view_ray(extents, near, uv, vec2(1.0));
}

#endif
