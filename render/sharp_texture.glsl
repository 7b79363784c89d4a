// Colour reconstruction shared by every client's draw (the quad mesh, MeshWarp, ATW): one bilinear fetch whose
// weights rise over the middle 1/SHARPNESS of each texel interval instead of across all of it. Reprojected
// colour is sampled between texels almost everywhere; plain bilinear then averages neighbours at up to half and
// half, a blur the ground truth does not have, while nearest sampling turns magnified texels into blocks. At a
// texel's centre this returns the texel; SHARPNESS 1 is bilinear filtering, larger values tend to nearest.
// `tex` must be sampled with linear filtering (the one fetch interpolates between the two texels).
#ifndef SHARPNESS
#define SHARPNESS 1.5
#endif
// Where to fetch, with linear filtering, in a texture of `size` texels to sample `uv` so.
vec2 sharp_uv(vec2 size, vec2 uv) {
    vec2 p = uv * size - 0.5;           // texel-centre coordinates
    vec2 i = floor(p);
    vec2 f = clamp((p - i - 0.5) * SHARPNESS + 0.5, 0.0, 1.0);
    return (i + f + 0.5) / size;
}
vec4 sharp_texture(sampler2D tex, vec2 uv) {
    return texture(tex, sharp_uv(vec2(textureSize(tex, 0)), uv));
}
