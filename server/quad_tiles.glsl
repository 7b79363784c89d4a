// The quad passes run on a list of 8x8 tiles of their map, not on the whole grid: Mesa's llvmpipe runs every
// instruction of a shader for 8 lanes even where all of them are masked off, so the only way to skip pixels a
// mask leaves out is not to launch them. One workgroup per listed tile; a tile is (ty << 16) | tx.
layout(std430, binding = 5) readonly buffer Tiles { uint tiles[]; };
uniform int u_tile_base;     // this map's first entry in `tiles`
uniform int u_tile_count;
uniform int u_tile_stride;   // workgroups per row of the dispatch

// The map entry this invocation handles; (-1, -1) past the end of the list.
ivec2 tile_invocation() {
    int i = int(gl_WorkGroupID.y) * u_tile_stride + int(gl_WorkGroupID.x);
    if (i >= u_tile_count) return ivec2(-1);
    uint t = tiles[u_tile_base + i];
    return ivec2(int(t & 0xffffu), int(t >> 16)) * 8 + ivec2(gl_LocalInvocationID.xy);
}
