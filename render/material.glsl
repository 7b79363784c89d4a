// Material sampling and G-buffer outputs shared by every geometry-pass fragment shader.
// ALBEDO says where the albedo comes from, fixed per program (render/renderer.py, MaterialProgram: one program per
// source, the draw picks an object's): 0 the texture at the mesh's UVs, 1 the texture triplanar in object space,
// 2 no texture (white: the base colour alone). In one program with the source a uniform, llvmpipe ran both ways of
// sampling for every fragment, untextured or not (docs/speed.md, stop 43).
#ifndef ALBEDO
#define ALBEDO 0
#endif
in vec3 v_view_pos;
in vec3 v_view_normal;
in vec3 v_obj_pos;
in vec3 v_obj_normal;
in vec2 v_uv;

uniform sampler2D u_texture;
uniform vec4 u_base_color;
uniform float u_uv_scale;
uniform float u_specular;
uniform float u_shininess;
uniform vec3 u_emissive;
uniform int u_object_id;

layout(location = 0) out vec4 f_albedo;    // linear albedo, a = emissive strength
layout(location = 1) out vec4 f_normal;    // view-space normal, w = specular
layout(location = 2) out vec4 f_position;  // view-space position, w = shininess (> 0 marks geometry)
layout(location = 3) out int f_object_id;

vec3 srgb_to_linear(vec3 c) { return pow(c, vec3(2.2)); }

vec4 sample_albedo() {
#if ALBEDO == 2
    return vec4(1.0);
#elif ALBEDO == 1
    // Triplanar with the dominant axis only: one texture fetch (flat faces look the same as with blending).
    vec3 w = abs(v_obj_normal);
    vec3 p = v_obj_pos * u_uv_scale;
    vec2 uv = (w.x >= w.y && w.x >= w.z) ? p.zy : (w.y >= w.z ? p.xz : p.xy);
    return texture(u_texture, uv);
#else
    return texture(u_texture, v_uv);
#endif
}

void write_gbuffer() {
    vec4 tex = sample_albedo();
    vec3 albedo = srgb_to_linear(tex.rgb) * u_base_color.rgb;
    // Where the vertex normals give no direction (a mesh's zero normals, or ones cancelling across the triangle:
    // render/scene.py repairs what it can), the surface faces the eye: a NaN normal would make NaN quads and light.
    vec3 n = v_view_normal;
    n = normalize(dot(n, n) > 1e-12 ? n : -v_view_pos);
    if (!gl_FrontFacing) n = -n;           // two-sided surfaces (thin railings, planes)
    if (dot(n, -v_view_pos) < 0.0) n = -n;  // the normal faces the camera
    f_albedo = vec4(albedo + u_emissive, length(u_emissive));
    f_normal = vec4(n, u_specular);
    f_position = vec4(v_view_pos, u_shininess);
    f_object_id = u_object_id;
}
