// The quad passes run on a list of 8x8 tiles of their map, not on the whole grid: Mesa's llvmpipe runs every
// instruction of a shader for 8 lanes even where all of them are masked off, so the only way to skip pixels a
// mask leaves out is not to launch them. One workgroup per listed tile; a tile is (ty << 16) | tx.
layout(std430, binding = 5) readonly buffer Tiles { uint tiles[]; };
uniform int u_tile_base;     // this map's first entry in `tiles`
uniform int u_tile_count;
uniform int u_tile_stride;   // workgroups per row of the dispatch

// Or, where u_pixel_count > 0, one invocation per listed entry ((y << 16) | x), 64 a workgroup: the passes under
// a sparse mask, where a listed tile's masked-out entries would cost as much as its kept ones.
layout(std430, binding = 8) readonly buffer Pixels { uint listed_pixels[]; };
uniform int u_pixel_base;    // this map's first entry in `listed_pixels`
uniform int u_pixel_count;

// The map entry this invocation handles; (-1, -1) past the end of the list.
ivec2 tile_invocation() {
    if (u_pixel_count > 0) {
        int k = (int(gl_WorkGroupID.y) * u_tile_stride + int(gl_WorkGroupID.x)) * 64 + int(gl_LocalInvocationIndex);
        if (k >= u_pixel_count) return ivec2(-1);
        uint c = listed_pixels[u_pixel_base + k];
        return ivec2(int(c & 0xffffu), int(c >> 16));
    }
    int i = int(gl_WorkGroupID.y) * u_tile_stride + int(gl_WorkGroupID.x);
    if (i >= u_tile_count) return ivec2(-1);
    uint t = tiles[u_tile_base + i];
    return ivec2(int(t & 0xffffu), int(t >> 16)) * 8 + ivec2(gl_LocalInvocationID.xy);
}
