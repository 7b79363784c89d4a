#version 430
// Lighting pass: Blinn-Phong with a PCF-shadowed sun and point lights; sRGB 8-bit output. It shades pixels with
// geometry; the sky pass (render/sky.frag.glsl) colours the others, picked by depth (DeferredRenderer.lighting_pass).
// With SKY_BRANCH it colours sky pixels itself, telling them by their position, for G-buffers whose depth does not
// (a culled geometry pass's). llvmpipe runs both sides of that branch on every pixel.
#include "camera.glsl"
#include "sky.glsl"
#ifndef SKY_BRANCH
#define SKY_BRANCH 0
#endif

in vec2 v_uv;

uniform sampler2D u_albedo;
uniform sampler2D u_normal;
uniform sampler2D u_position;
uniform sampler2DShadow u_shadow_map;

uniform mat4 u_inv_view;
uniform vec4 u_extents;           // the camera's frustum l, r, b, t at distance 1
uniform mat4 u_light_vp;          // world -> sun clip space
uniform vec3 u_sun_dir_view;      // direction the sunlight travels, in view space
uniform vec3 u_sun_color;         // colour * intensity
uniform vec3 u_ambient;
uniform vec3 u_sky;
uniform float u_shadow_texel;

const int MAX_LIGHTS = 16;
uniform int u_num_lights;
uniform vec3 u_light_pos[MAX_LIGHTS];    // view space
uniform vec3 u_light_color[MAX_LIGHTS];  // colour * intensity
uniform float u_light_radius[MAX_LIGHTS];

out vec4 f_color;

float sun_visibility(vec3 world_pos, vec3 world_normal) {
    vec4 lp = u_light_vp * vec4(world_pos + world_normal * 0.03, 1.0);
    vec3 s = lp.xyz / lp.w * 0.5 + 0.5;
    if (any(lessThan(s.xy, vec2(0.0))) || any(greaterThan(s.xy, vec2(1.0))) || s.z > 1.0) return 1.0;
    // 4 bilinear (hardware 2x2 PCF) taps = a 3x3-texel soft edge.
    float v = 0.0;
    for (int i = 0; i < 4; ++i) {
        vec2 o = (vec2(i & 1, i >> 1) - 0.5) * u_shadow_texel;
        v += texture(u_shadow_map, vec3(s.xy + o, s.z - 0.0015));
    }
    return v * 0.25;
}

vec3 tonemap(vec3 c) {
    c = vec3(1.0) - exp(-c * 1.4);
    return pow(c, vec3(1.0 / 2.2));
}

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 pos = texelFetch(u_position, px, 0);
#if SKY_BRANCH
    if (is_sky(pos)) {
        f_color = vec4(sky_colour(u_inv_view, u_extents, u_sky, v_uv), 1.0);
        return;
    }
#endif
    vec4 alb = texelFetch(u_albedo, px, 0);
    vec4 nrm = texelFetch(u_normal, px, 0);
    vec3 n = normalize(nrm.xyz);
    vec3 v = normalize(-pos.xyz);
    float spec_k = nrm.w;
    float shininess = pos.w;

    vec3 world_pos = (u_inv_view * vec4(pos.xyz, 1.0)).xyz;
    vec3 world_n = mat3(u_inv_view) * n;

    vec3 color = u_ambient * alb.rgb * (0.6 + 0.4 * n.y);
    vec3 l = -u_sun_dir_view;
    float ndl = max(dot(n, l), 0.0);
    if (ndl > 0.0) {
        float vis = sun_visibility(world_pos, world_n);
        vec3 h = normalize(l + v);
        color += vis * u_sun_color * (alb.rgb * ndl + spec_k * pow(max(dot(n, h), 0.0), shininess) * ndl);
    }
    for (int i = 0; i < u_num_lights; ++i) {
        vec3 d = u_light_pos[i] - pos.xyz;
        float dist = length(d);
        float x = dist / u_light_radius[i];
        float window = clamp(1.0 - x * x * x * x, 0.0, 1.0);
        float atten = window * window / (dist * dist + 1.0);
        vec3 li = d / max(dist, 1e-4);
        float nl = max(dot(n, li), 0.0);
        vec3 h = normalize(li + v);
        color += atten * u_light_color[i] * (alb.rgb * nl + spec_k * pow(max(dot(n, h), 0.0), shininess) * nl);
    }
    color += alb.rgb * alb.a;  // emissive
    f_color = vec4(tonemap(color), 1.0);
}
