#version 430
// Quad generation, first stage: the plane of every pixel the create pass (quad_create.comp) may read as a
// neighbour -- its unit normal, kept within u_max_angle of the view ray, and offset dot(n, position) -- or a zero
// normal where the pixel gets no quad. Once per pixel, where the create pass would redo it for each of a pixel's
// eight neighbours. Runs on the create pass's tiles and the ring of tiles around them.
layout(local_size_x = 8, local_size_y = 8) in;
#include "quad.glsl"
#include "quad_tiles.glsl"
#include "quad_pixel.glsl"

// Into a buffer, which the caller copies into the texture the create pass fetches from: on llvmpipe an RGBA32F
// image store costs several times a buffer store (a full 960x540 pass ~5-10 ms more), a copy ~1 ms.
layout(std430, binding = 7) writeonly buffer PixelPlanes { vec4 pixel_planes[]; };   // row p.y, column p.x

void main() {
    ivec2 p = tile_invocation();
    if (p.x < 0 || any(greaterThanEqual(p, u_size))) return;
    vec3 n, P;
    vec4 e = vec4(0.0);
    if (load(p, n, P)) {
        n = limit_grazing(n, normalize(-P), u_max_angle);
        e = vec4(n, dot(n, P));
    }
    pixel_planes[p.y * u_size.x + p.x] = e;
}
