// The layered-mesh draw of a cached layer (QuadMesh.set_current_view): its colour and, where the newest frame's
// own view saw the same surface, the mean with that view's colour. The cached colour was taken from an older
// view, often at a steeper angle, and each picture carries its own coding error: their mean is closer to the truth
// than either. "Saw": the point lies in that view's frustum and the two colours agree within a tolerance in every
// channel; where something else was in front of it there (another colour) the cached colour stays.
#include "sharp_texture.glsl"
in vec3 v_uvw;
in vec3 v_view_pos;
in vec4 v_current_clip;             // the point in the current view's clip space
uniform sampler2D u_atlas;
uniform vec4 u_uv_rect;             // the layer's atlas rect in uv, half a texel in: (u0, v0, u1, v1)
uniform vec4 u_current_rect;        // the current view's colour in the atlas: (u, v, width, height) in uv
uniform vec4 u_current_uv_rect;     // the same, half a texel in: (u0, v0, u1, v1)
uniform float u_current_agreement;
uniform float u_current_weight;
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_depth;
void main() {
    vec3 color = sharp_texture(u_atlas, clamp(v_uvw.xy / v_uvw.z, u_uv_rect.xy, u_uv_rect.zw)).rgb;
    vec4 clip = v_current_clip;
    if (clip.w > 0.0 && all(lessThan(abs(clip.xy), vec2(clip.w)))) {
        vec2 t = clip.xy / clip.w * 0.5 + 0.5;                                  // bottom row first, as GL renders
        vec2 uv = u_current_rect.xy + vec2(t.x, 1.0 - t.y) * u_current_rect.zw;   // the atlas: top row first
        vec3 current = sharp_texture(u_atlas, clamp(uv, u_current_uv_rect.xy, u_current_uv_rect.zw)).rgb;
        vec3 difference = abs(current - color);
        if (max(difference.r, max(difference.g, difference.b)) < u_current_agreement)
            color = mix(color, current, u_current_weight);
    }
    f_color = vec4(color, 1.0);
    f_depth = -v_view_pos.z;
}
