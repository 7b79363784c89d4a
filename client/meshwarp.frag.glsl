#version 430
// MeshWarp: the mesh is textured with the decoded frame it was built from.
#include "sharp_texture.glsl"
in vec2 v_uv;

uniform sampler2D u_frame;  // decoded colour, bottom row first

out vec4 f_color;

void main() {
    f_color = vec4(sharp_texture(u_frame, v_uv).rgb, 1.0);
}
