#version 430
// Effective Depth Peeling in one pass: every fragment behind the visible layer that could become visible from
// inside the view sphere (peel_visibility.glsl) is stored in its pixel's list; peel_resolve.frag.glsl then takes
// the hidden layers from the lists as the layer-by-layer passes (peel.frag.glsl) would peel them. The scene is
// rasterized once instead of once a layer.
layout(early_fragment_tests) in;     // the cull step's depth 0 (nothing visible there) rejects before the shader
#include "material.glsl"
#include "camera.glsl"
#include "peel_visibility.glsl"
#include "peel_list_buffers.glsl"

uniform uint u_capacity;             // fragments the buffer holds

void main() {
    ivec2 px = ivec2(gl_FragCoord.xy);
    float z = -v_view_pos.z;
    if (z <= visible_depth(px) * (1.0 + u_connectivity)) discard;   // the visible surface, or in front of it
    if (!potentially_visible(px, z)) discard;
    write_gbuffer();                 // no colour attachments: only to read the outputs back
    uint i = atomicAdd(fragment_count, 1u);
    if (i >= u_capacity) return;     // counted, not stored: the caller makes room and runs the pass again
    uint next = atomicExchange(heads[u_list_width * px.y + px.x], i + 1u);
    fragments[i] = PeelFragment(f_albedo, f_normal, f_position, gl_FragCoord.z, f_object_id, next, 0u);
}
