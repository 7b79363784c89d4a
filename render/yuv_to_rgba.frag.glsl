#version 430
// The atlas as the draws see it at each texel's centre (AtlasTexture.read_rgb): atlas_colour.glsl's conversion,
// drawn into an RGBA texture of the atlas's size, the picture's bottom row first (GL's order).
#include "atlas_colour.glsl"
layout(location = 0) out vec4 f_color;
void main() {
    vec2 size = vec2(textureSize(u_atlas, 0));
    vec2 pixel = vec2(gl_FragCoord.x, size.y - gl_FragCoord.y);   // the pixel's centre, top row first
    f_color = vec4(atlas_colour(pixel / size), 1.0);
}
