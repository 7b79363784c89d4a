// Layered-mesh rendering: colour from the decoded video atlas (alpha 1 where the mesh covers the pixel); linear
// view depth for depth-based masks and the stereo synthesis (0, the clear value, where nothing was drawn).
// The atlas is sampled inside the layer's own rect, half a texel in from its edges: a quad at the rect's border,
// seen magnified or at a new angle, would otherwise filter in the next layer's pixels (a dark seam along the edge
// of the reference view on the ground, for one).
#include "atlas_colour.glsl"
in vec3 v_uvw;
in vec3 v_view_pos;
uniform vec4 u_uv_rect;   // the layer's atlas rect in uv, half a texel in: (u0, v0, u1, v1)
layout(location = 0) out vec4 f_color;
layout(location = 1) out float f_depth;
// The layer's colour at this fragment; each draw's main writes it to f_color (alpha 1) and -v_view_pos.z to f_depth.
vec3 layer_colour() {
    return atlas_colour(clamp(v_uvw.xy / v_uvw.z, u_uv_rect.xy, u_uv_rect.zw));
}
