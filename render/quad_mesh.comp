#version 430
// Mesh reconstruction: every quad becomes 4 sub-quads = 16 vertices (view space of its layer camera, atlas uv)
// and 24 indices. One invocation per quad.
layout(local_size_x = 64) in;
#include "quad.glsl"

struct Quad {            // as uploaded by render/quadmesh.py
    uvec4 head;          // x, y, size_log2, unused
    vec4 normal_depth;   // view-space normal, depth of the plane on the centre ray
    vec4 off[4];         // 16 depth offsets (0 when flattened)
};
layout(std430, binding = 0) readonly buffer Quads { Quad quads[]; };
layout(std430, binding = 1) writeonly buffer Vertices { float vertices[]; };  // 5 floats each: xyz, uv
layout(std430, binding = 2) writeonly buffer Indices { uint indices[]; };

uniform uint u_count;
uniform uint u_base_quad;     // where this layer's quads start in the shared buffers
uniform vec4 u_atlas_rect;    // x, y, w, h of this layer's colour in the atlas (pixels, top-left origin)
uniform vec2 u_atlas_size;

void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= u_count) return;
    Quad q = quads[u_base_quad + i];
    float size = float(1u << q.head.z);
    vec2 origin = vec2(q.head.xy);
    vec3 n = q.normal_depth.xyz;
    float d = plane_d(n, origin + 0.5 * size, q.normal_depth.w);
    uint v0 = 16u * (u_base_quad + i);
    for (uint s = 0u; s < 4u; ++s) {
        for (uint c = 0u; c < 4u; ++c) {
            vec2 p = quad_corner_point(origin, size, int(s), int(c));
            vec3 pos = quad_corner_position(p, n, d, q.off[s][c]);
            vec2 uv = (u_atlas_rect.xy + p / vec2(u_size) * u_atlas_rect.zw) / u_atlas_size;
            uint v = (v0 + 4u * s + c) * 5u;
            vertices[v] = pos.x; vertices[v + 1u] = pos.y; vertices[v + 2u] = pos.z;
            vertices[v + 3u] = uv.x; vertices[v + 4u] = uv.y;
        }
        uint k = (u_base_quad + i) * 24u + 6u * s;
        uint b = v0 + 4u * s;
        indices[k] = b; indices[k + 1u] = b + 2u; indices[k + 2u] = b + 1u;
        indices[k + 3u] = b + 1u; indices[k + 4u] = b + 2u; indices[k + 5u] = b + 3u;
    }
}
