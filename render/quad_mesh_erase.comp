#version 430
// Mesh edit (render/quadmesh.py): the triangles of freed quads become empty -- every index of a freed quad points
// at its first vertex -- so an edited mesh draws what a mesh built from scratch would, at the same places.
layout(local_size_x = 64) in;

layout(std430, binding = 0) readonly buffer Freed { uvec2 freed[]; };   // first vertex, vertex count
layout(std430, binding = 2) writeonly buffer Indices { uint indices[]; };

uniform uint u_count;

void main() {
    uint k = gl_GlobalInvocationID.x;
    if (k >= u_count) return;
    uvec2 f = freed[k];
    uint start = f.x / 2u * 3u;
    for (uint j = 0u; j < f.y / 2u * 3u; ++j) indices[start + j] = f.x;
}
