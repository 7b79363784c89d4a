#version 430
// Which pixels of a G-buffer hold geometry (nearer than u_max_depth), a bit each, 8x8 tiles at a time: a layer
// without sky quads needs the quad passes only there (quad_tiles.glsl), on its tiles or, where few of their
// pixels hold any, on the pixels themselves. One invocation per tile, two words: row j of the tile is byte j % 4
// of word j / 4 (little-endian: byte j of the eight), pixel i of the row its bit i; image rows counted from the top.
layout(local_size_x = 8, local_size_y = 8) in;
layout(std430, binding = 0) writeonly buffer Occupied { uvec2 occupied[]; };
uniform sampler2D u_position;   // view-space position, w > 0 where geometry (GL rows: bottom first)
uniform ivec2 u_size;
uniform ivec2 u_tiles;
uniform float u_max_depth;

void main() {
    ivec2 t = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(t, u_tiles))) return;
    uvec2 bits = uvec2(0u);
    for (int j = 0; j < 8; ++j) for (int i = 0; i < 8; ++i) {
        ivec2 p = t * 8 + ivec2(i, j);
        if (any(greaterThanEqual(p, u_size))) continue;
        vec4 P = texelFetch(u_position, ivec2(p.x, u_size.y - 1 - p.y), 0);
        if (P.w > 0.0 && -P.z <= u_max_depth) bits[j >> 2] |= 1u << uint(8 * (j & 3) + i);
    }
    occupied[t.y * u_tiles.x + t.x] = bits;
}
