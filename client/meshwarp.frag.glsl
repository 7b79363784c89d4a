#version 430
// MeshWarp: the mesh is textured with the decoded frame it was built from.
#include "atlas_colour.glsl"
in vec2 v_uv;   // in the decoded frame, bottom row first

out vec4 f_color;

void main() {
    f_color = vec4(atlas_colour(vec2(v_uv.x, 1.0 - v_uv.y)), 1.0);
}
