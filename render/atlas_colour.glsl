// The decoded colour atlas as every client's draw samples it (the quad mesh, MeshWarp, ATW): `atlas_colour(uv)`,
// uv counted from the picture's top-left corner, reconstructed as sharp_texture.glsl does.
//
// The atlas arrives as 8-bit 4:2:0 planes (BT.601 limited range, chroma sited at the centre of each 2x2 block, as
// codec/encoder.py makes it) and is converted here, per fragment: u_atlas holds luma, u_atlas_chroma Cb and Cr at
// half size, both with linear filtering and uploaded top row first (render/atlas_texture.py). Each plane is
// sharpened on its own grid; with chroma sited at block centres the same uv finds its place in the half-size
// plane. (Until stop 65 the chroma was fetched at the luma grid's sharpened uv, which over the half-size plane is
// no sharper than plain bilinear filtering; FLIP scores colour: README, "Colour coded finer".) Converting the whole
// atlas to RGBA first cost a full-screen pass over an atlas about four times the display's size each frame (11 ms
// of a 60 ms client frame on llvmpipe at 960x540); the draw fetches two textures instead of one only where a
// fragment is shaded.
//
// With ATLAS_RGB defined, u_atlas is an RGBA picture instead (the browser viewer's decoded VideoFrame).
#include "sharp_texture.glsl"
uniform sampler2D u_atlas;
#ifdef ATLAS_RGB
vec3 atlas_colour(vec2 uv) {
    return sharp_texture(u_atlas, uv).rgb;
}
#else
uniform sampler2D u_atlas_chroma;
vec3 atlas_colour(vec2 uv) {
    vec2 at = sharp_uv(vec2(textureSize(u_atlas, 0)), uv);
    float l = (texture(u_atlas, at).r - 16.0 / 255.0) * (255.0 / 219.0);
    vec2 cbcr = (texture(u_atlas_chroma, sharp_uv(vec2(textureSize(u_atlas_chroma, 0)), uv)).rg - 128.0 / 255.0)
                * (255.0 / 224.0);
    return clamp(vec3(l + 1.402 * cbcr.y, l - 0.344136 * cbcr.x - 0.714136 * cbcr.y, l + 1.772 * cbcr.x), 0.0, 1.0);
}
#endif
