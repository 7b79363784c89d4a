#version 430
// One hidden layer of the one-pass peel from the per-pixel lists peel_list.frag.glsl stored, as a layer-by-layer
// pass (peel.frag.glsl) would peel it: the nearest stored fragment (by window depth) behind the previous layer by
// more than the connectivity gap. Of fragments at exactly the same depth it keeps the earliest stored: llvmpipe
// shades a pixel's fragments in the order they are drawn, so that is the one a "<" depth test keeps; a GPU may
// store them in another order. Writes the G-buffer's outputs and its depth; discards where the layer is empty.
#include "camera.glsl"
#include "peel_list_buffers.glsl"

uniform sampler2D u_prev_position;     // the previous layer's view positions (the visible layer's for the first)
uniform float u_connectivity;

layout(location = 0) out vec4 f_albedo;
layout(location = 1) out vec4 f_normal;
layout(location = 2) out vec4 f_position;
layout(location = 3) out int f_object_id;

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    vec4 prev = texelFetch(u_prev_position, px, 0);
    if (is_sky(prev)) discard;                               // nothing in front: nothing hidden here
    float behind = -prev.z * (1.0 + u_connectivity);
    uint best = END;
    float best_depth = 2.0;
    for (uint k = heads[u_list_width * px.y + px.x]; k != END; k = fragments[k - 1u].next) {   // newest first
        if (-fragments[k - 1u].position.z > behind && fragments[k - 1u].depth <= best_depth) {  // "<=": the earliest
            best = k;
            best_depth = fragments[k - 1u].depth;
        }
    }
    if (best == END) discard;
    PeelFragment f = fragments[best - 1u];
    f_albedo = f.albedo;
    f_normal = f.normal;
    f_position = f.position;
    f_object_id = f.object_id;
    gl_FragDepth = f.depth;
}
