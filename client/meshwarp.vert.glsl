#version 430
// MeshWarp: a grid mesh with one vertex per depth pixel, unprojected with the server's camera and drawn from the
// display's pose. gl_VertexID = row * width + column, rows bottom-up as in GL textures. The outermost vertices
// sit on the image border (not the pixel centres) so the mesh spans the whole server frustum. Sky pixels become
// points at infinity (w = 0) in their viewing direction: no parallax, and triangles joining geometry to sky
// stretch towards the horizon. Triangles across depth discontinuities are kept (a connected "rubber sheet").
#include "camera.glsl"

uniform sampler2D u_depth;  // R32F linear view depth in metres, 0 = sky
uniform vec4 u_extents;     // the server camera's frustum l, r, b, t at distance 1
uniform mat4 u_mvp;         // display projection * display view * server camera-to-world

out vec2 v_uv;

void main() {
    ivec2 size = textureSize(u_depth, 0);
    ivec2 px = ivec2(gl_VertexID % size.x, gl_VertexID / size.x);
    float z = texelFetch(u_depth, px, 0).r;
    vec2 uv = (vec2(px) + 0.5) / vec2(size);
    if (px.x == 0) uv.x = 0.0; else if (px.x == size.x - 1) uv.x = 1.0;
    if (px.y == 0) uv.y = 0.0; else if (px.y == size.y - 1) uv.y = 1.0;
    vec3 dir = view_ray(u_extents, 1.0, uv);  // server view space, z = -1
    v_uv = uv;
    if (!is_sky_depth(z)) {
        gl_Position = u_mvp * vec4(dir * z, 1.0);
    } else {
        gl_Position = u_mvp * vec4(dir, 0.0);
        gl_Position.z = gl_Position.w * 0.99999;  // just inside the far plane, behind all geometry
    }
}
