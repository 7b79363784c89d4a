#version 300 es
// WebGL2 form of render/quad_mesh.comp (WebGL2 has no compute shaders): run once per applied frame with
// transform feedback, one instance per quad and 16 points each (4 sub-quads x 4 corners), so the captured buffer
// is laid out as the compute shader's vertices: quad i, sub-quad s, corner c at 16 i + 4 s + c, xyz in the layer
// camera's view space and the atlas uv. The geometry helpers are render/quad.glsl itself (the server resolves
// the #include when it serves this file).
precision highp float;
precision highp int;
#include "quad.glsl"

in vec4 a_head;            // x, y, size_log2, unused (render/quadmesh.py quads_to_gpu's row)
in vec4 a_normal_depth;    // view-space normal, depth of the plane on the centre ray
in vec4 a_off0;            // depth offsets of sub-quad 0 (TL), corners TL TR BL BR
in vec4 a_off1;
in vec4 a_off2;
in vec4 a_off3;
uniform vec4 u_atlas_rect;     // x, y, w, h of this layer's colour in the atlas (pixels, top-left origin)
uniform vec2 u_atlas_size;
out vec3 v_position;
out vec2 v_uv;

void main() {
    int s = gl_VertexID / 4;
    int c = gl_VertexID - 4 * s;
    float size = float(1 << int(a_head.z));
    vec2 origin = a_head.xy;
    vec3 n = a_normal_depth.xyz;
    float d = plane_d(n, origin + 0.5 * size, a_normal_depth.w);
    vec2 p = quad_corner_point(origin, size, s, c);
    vec4 off = s == 0 ? a_off0 : s == 1 ? a_off1 : s == 2 ? a_off2 : a_off3;
    v_position = quad_corner_position(p, n, d, off[c]);
    v_uv = (u_atlas_rect.xy + p / vec2(u_size) * u_atlas_rect.zw) / u_atlas_size;
    gl_Position = vec4(0.0);
    gl_PointSize = 1.0;
}
