#version 430
// Mesh reconstruction of one layer: a quad with depth offsets becomes 4 sub-quads = 16 vertices (view space of
// its layer camera, atlas uv) and 24 indices; a flattened quad (a plane, no offsets) one quad = 4 vertices and 6
// indices. One invocation per quad; where each quad's vertices go (its indices: 3/2 of that) is decided on the CPU.
// Built twice, with FLATTENED 1 and 0: each dispatch takes one kind of quad, as llvmpipe would run both branches of
// an if for every quad of a mixed batch. The quads stay in their own order; `order` lists the flattened ones first,
// then the others (render/quadmesh.py), and a dispatch takes its part of that list.
layout(local_size_x = 64) in;
#include "quad.glsl"

struct Quad {            // as uploaded by render/quadmesh.py
    uvec4 head;          // x, y, size_log2, first vertex | flattened << 31
    vec4 normal_depth;   // view-space normal, depth of the plane on the centre ray
    vec4 off[4];         // 16 depth offsets (0 when flattened)
};
layout(std430, binding = 0) readonly buffer Quads { Quad quads[]; };
layout(std430, binding = 1) writeonly buffer Vertices { float vertices[]; };  // 5 floats each: xyz, uv
layout(std430, binding = 2) writeonly buffer Indices { uint indices[]; };
layout(std430, binding = 3) readonly buffer Order { uint order[]; };
layout(std430, binding = 4) writeonly buffer Planes { vec4 planes[]; };  // a flattened quad's plane, per 4 vertices

uniform uint u_first;         // this dispatch's quads: order[u_first .. u_count - 1]
uniform uint u_count;
uniform vec4 u_atlas_rect;    // x, y, w, h of this layer's colour in the atlas (pixels, top-left origin)
uniform vec2 u_atlas_size;

void emit(uint v, vec2 p, vec3 pos) {
    vec2 uv = (u_atlas_rect.xy + p / vec2(u_size) * u_atlas_rect.zw) / u_atlas_size;
    vertices[5u * v] = pos.x; vertices[5u * v + 1u] = pos.y; vertices[5u * v + 2u] = pos.z;
    vertices[5u * v + 3u] = uv.x; vertices[5u * v + 4u] = uv.y;
}

void quad_indices(uint k, uint b) {   // two triangles of the (sub-)quad whose corners start at vertex b
    indices[k] = b; indices[k + 1u] = b + 2u; indices[k + 2u] = b + 1u;
    indices[k + 3u] = b + 1u; indices[k + 4u] = b + 2u; indices[k + 5u] = b + 3u;
}

void main() {
    uint k = u_first + gl_GlobalInvocationID.x;
    if (k >= u_count) return;
    Quad q = quads[order[k]];
    float size = float(1u << q.head.z);
    vec2 origin = vec2(q.head.xy);
    vec3 n = q.normal_depth.xyz;
    float d = plane_d(n, origin + 0.5 * size, q.normal_depth.w);
    uint v0 = q.head.w & 0x7fffffffu;
#if FLATTENED
    for (uint c = 0u; c < 4u; ++c) {     // the whole quad, one plane
        vec2 p = quad_corner_point(origin, 2.0 * size, 0, int(c));
        emit(v0 + c, p, quad_corner_position(p, n, d, 0.0));
    }
    quad_indices(v0 / 2u * 3u, v0);
    planes[v0 / 4u] = vec4(n, d);   // for the runs (quad_mesh_runs.comp)
#else
    for (uint s = 0u; s < 4u; ++s) {
        for (uint c = 0u; c < 4u; ++c) {
            vec2 p = quad_corner_point(origin, size, int(s), int(c));
            emit(v0 + 4u * s + c, p, quad_corner_position(p, n, d, q.off[s][c]));
        }
        quad_indices(v0 / 2u * 3u + 6u * s, v0 + 4u * s);
    }
#endif
}
