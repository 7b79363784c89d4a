#version 430
// Which 8x8 tiles of a G-buffer hold geometry (nearer than u_max_depth): a layer without sky quads needs the
// quad passes only there (quad_tiles.glsl). One invocation per tile; image rows counted from the top.
layout(local_size_x = 8, local_size_y = 8) in;
layout(std430, binding = 0) writeonly buffer Occupied { uint occupied[]; };
uniform sampler2D u_position;   // view-space position, w > 0 where geometry (GL rows: bottom first)
uniform ivec2 u_size;
uniform ivec2 u_tiles;
uniform float u_max_depth;

void main() {
    ivec2 t = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(t, u_tiles))) return;
    bool geometry = false;
    for (int j = 0; j < 8; ++j) for (int i = 0; i < 8; ++i) {
        ivec2 p = min(t * 8 + ivec2(i, j), u_size - 1);
        vec4 P = texelFetch(u_position, ivec2(p.x, u_size.y - 1 - p.y), 0);
        geometry = geometry || (P.w > 0.0 && -P.z <= u_max_depth);
    }
    occupied[t.y * u_tiles.x + t.x] = geometry ? 1u : 0u;
}
