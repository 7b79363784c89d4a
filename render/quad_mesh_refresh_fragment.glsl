// The layered-mesh draw of a cached layer (QuadMesh.set_current_view): its colour and, where the newest frame's
// own view saw the same surface, a weighted mean with that view's colour. The cached colour was taken from an older
// view, often at a steeper angle, and each picture carries its own coding error: their mean is closer to the truth
// than either. The cached colour weighs more: it comes from a reference frame, which QUASAR's server codes 6
// quantizer steps finer than the residual frame that brings the current view (DEFAULT_IPRATIO in
// protocol/methods.py), so its coding error is about half as large (README, "Reference frames coded finer": a share
// of 0.3 for the current colour instead of 0.5 lowered the courtyard rows' FLIP by 1.5-3%). "Saw": the point lies in
// that view's frustum and the two colours agree within a tolerance in every channel; where something else was in
// front of it there (another colour) the cached colour stays.
#include "quad_mesh_fragment.glsl"
in vec4 v_current_clip;             // the point in the current view's clip space
uniform vec4 u_current_rect;        // the current view's colour in the atlas: (u, v, width, height) in uv
uniform vec4 u_current_uv_rect;     // the same, half a texel in: (u0, v0, u1, v1)
const float CURRENT_AGREEMENT = 0.2;   // the most the two colours may differ in any channel (0..1)
const float CURRENT_WEIGHT = 0.3;      // the current colour's share where they agree
void main() {
    vec3 color = layer_colour();
    vec4 clip = v_current_clip;
    if (clip.w > 0.0 && all(lessThan(abs(clip.xy), vec2(clip.w)))) {
        vec2 t = clip.xy / clip.w * 0.5 + 0.5;                                  // bottom row first, as GL renders
        vec2 uv = u_current_rect.xy + vec2(t.x, 1.0 - t.y) * u_current_rect.zw;   // the atlas: top row first
        vec3 current = atlas_colour(clamp(uv, u_current_uv_rect.xy, u_current_uv_rect.zw));
        vec3 difference = abs(current - color);
        if (max(difference.r, max(difference.g, difference.b)) < CURRENT_AGREEMENT)
            color = mix(color, current, CURRENT_WEIGHT);
    }
    f_color = vec4(color, 1.0);
    f_depth = -v_view_pos.z;
}
