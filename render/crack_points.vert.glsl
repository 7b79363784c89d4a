#version 430
// Crack fill, second pass (render/quadmesh.py, MeshView): each crack crack_find.frag.glsl listed, as a one-pixel
// point at its depth, so that the layers drawn after it are depth-tested against it as against the surface.
uniform mat4 u_proj;
uniform ivec2 u_size;
layout(std430, binding = 0) readonly buffer Cracks {
    uvec4 command;
    uvec4 cracks[];
};
out vec4 v_color;
out float v_depth;

void main() {
    uvec4 c = cracks[gl_VertexID];
    float depth = uintBitsToFloat(c.z);
    vec4 clip = u_proj * vec4(0.0, 0.0, -depth, 1.0);
    vec2 ndc = (vec2(c.xy) + 0.5) / vec2(u_size) * 2.0 - 1.0;
    gl_Position = vec4(ndc, clip.z / clip.w, 1.0);
    gl_PointSize = 1.0;
    v_color = unpackUnorm4x8(c.w);
    v_depth = depth;
}
