#version 430
// Atlas foveation (server/foveation.py): one view of the atlas drawn into its rect, each pixel at the pixel size its
// eccentricity from the gaze allows -- the view's own colour near the gaze, its box-filtered copies at 1/2, 1/4, ...
// of its size (the texture's mip levels) farther out, bilinear within a level and blended linearly between the two
// levels around log2 of the pixel scale (fovea.glsl's scale, capped at the operating point's atlas factor).
in vec2 v_uv;                 // over the rect, bottom row first (fullscreen.vert.glsl)
uniform sampler2D u_view;     // the view's colour, rect-sized, with its mip levels
uniform vec4 u_extents;       // the view camera's frustum at unit distance: left, right, bottom, top
out vec4 f_color;
vec3 ray_dir(vec2 uv) {
    return vec3(mix(u_extents.x, u_extents.y, uv.x), mix(u_extents.z, u_extents.w, uv.y), -1.0);
}
#include "fovea.glsl"
void main() {
    float level = log2(max(fovea_scale(v_uv), 1.0));
    f_color = vec4(textureLod(u_view, v_uv, level).rgb, 1.0);
}
