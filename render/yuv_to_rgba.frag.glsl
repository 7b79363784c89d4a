#version 430
// A decoded H.264 picture (8-bit 4:2:0, BT.601 limited range, chroma sited at the centre of each 2x2 block, as
// codec/encoder.py makes it) to RGBA, once per received frame (render/atlas_texture.py). Chroma is interpolated
// bilinearly in float from its four nearest samples, as a video player's shader does; FFmpeg's fast conversion
// repeats each chroma sample over its 2x2 pixels instead, an error of a level or two on most pixels that FLIP
// scores like coding error. The samples are fetched with texture() from NEAREST-filtered planes (clamped to the
// edge): on llvmpipe that is cheaper than texelFetch, and its own linear filter of an 8-bit texture is coarser.
// Planes are uploaded as decoded, top row first; u_bottom_first writes the picture bottom row first (GL's order).
uniform sampler2D u_y;          // luma, full size
uniform sampler2D u_uv;         // Cb, Cr, half size
uniform bool u_bottom_first;
layout(location = 0) out vec4 f_color;
void main() {
    vec2 size = vec2(textureSize(u_y, 0));
    vec2 pixel = gl_FragCoord.xy;                                   // the pixel's centre, in luma texels
    if (u_bottom_first) pixel.y = size.y - pixel.y;
    float y = texture(u_y, pixel / size).r;
    // the centre in chroma samples (sample i at i + 0.5), the four nearest samples' centres and the weights
    vec2 chroma_size = vec2(textureSize(u_uv, 0));
    vec2 c = pixel * 0.5 - 0.5;
    vec2 i = floor(c);
    vec2 f = c - i;
    vec2 a = (i + 0.5) / chroma_size, b = (i + 1.5) / chroma_size;
    vec2 chroma = mix(mix(texture(u_uv, a).rg, texture(u_uv, vec2(b.x, a.y)).rg, f.x),
                      mix(texture(u_uv, vec2(a.x, b.y)).rg, texture(u_uv, b).rg, f.x), f.y);
    float l = (y - 16.0 / 255.0) * (255.0 / 219.0);
    vec2 cbcr = (chroma - 128.0 / 255.0) * (255.0 / 224.0);
    f_color = vec4(clamp(vec3(l + 1.402 * cbcr.y, l - 0.344136 * cbcr.x - 0.714136 * cbcr.y, l + 1.772 * cbcr.x),
                         0.0, 1.0), 1.0);
}
