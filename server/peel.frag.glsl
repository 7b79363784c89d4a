#version 430
// Effective Depth Peeling, one layer a pass: the next hidden layer keeps, per pixel, the nearest fragment behind
// the previous layer that could become visible from somewhere inside the view sphere (peel_visibility.glsl).
#include "material.glsl"
#include "camera.glsl"
#include "peel_visibility.glsl"

uniform sampler2D u_prev_position;     // previous layer's view positions (w > 0 where geometry)

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    float z = -v_view_pos.z;
    vec4 prev = texelFetch(u_prev_position, px, 0);
    if (is_sky(prev)) discard;                               // nothing in front: nothing hidden here
    if (z <= -prev.z * (1.0 + u_connectivity)) discard;      // already peeled, or the same surface
    if (!potentially_visible(px, z)) discard;
    write_gbuffer();
}
