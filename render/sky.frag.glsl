#version 430
// The sky pass: the sky's colour on the pixels without geometry, which the depth test picks (the lighting pass
// shaded the others). On llvmpipe a branch on "is this sky" in the lighting shader ran the sky's code on every pixel.
#include "sky.glsl"

in vec2 v_uv;
uniform mat4 u_inv_view;
uniform vec4 u_extents;
uniform vec3 u_sky;
out vec4 f_color;

void main() {
    f_color = vec4(sky_colour(u_inv_view, u_extents, u_sky, v_uv), 1.0);
}
