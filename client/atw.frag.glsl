#version 430
// ATW: rotation-only reprojection of the last decoded frame to the display's current orientation.
// u_h is the homography display NDC (x, y, 1) -> frame NDC (homogeneous): K_frame * R_frame^T * R_now * K_now^-1.
// Directions behind the frame's camera are pushed out to its border, and clamp-to-edge sampling fills everything
// outside the frame with the closest edge pixel in that direction.
// Alpha says what the pixel shows (client.method.PixelCoverage): 1 = the frame's content in this direction,
// 0.5 = only the repeated edge pixel (outside the frame), 0 = nothing (the clear value).
#include "atlas_colour.glsl"
in vec2 v_uv;

uniform mat3 u_h;

out vec4 f_color;

void main() {
    vec3 q = u_h * vec3(v_uv * 2.0 - 1.0, 1.0);
    bool in_front = q.z > 0.0;
    q.z = max(q.z, max(1e-6 * length(q.xy), 1e-30));
    vec2 uv = q.xy / q.z * 0.5 + 0.5;
    bool inside = in_front && all(greaterThanEqual(uv, vec2(0.0))) && all(lessThanEqual(uv, vec2(1.0)));
    // the frame's uv, bottom row first; atlas_colour's planes count rows from the top (clamped to the edge)
    f_color = vec4(atlas_colour(vec2(uv.x, 1.0 - uv.y)), inside ? 1.0 : 0.5);
}
