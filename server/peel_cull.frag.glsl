#version 430
// Depth-only steps around a peel pass (server/layers.py). Before it (u_restore false): depth 0 where the previous
// layer holds nothing, so the depth test rejects every fragment there before the peel shader runs -- it would
// discard them all (nothing in front: nothing hidden) but, with a discard in it, llvmpipe shades them first.
// After it (u_restore true, u_position = the peeled layer): depth 1 again wherever that layer holds nothing, as
// a plain pass leaves it (the depth-tested lighting relies on it).
#include "camera.glsl"
uniform sampler2D u_position;
uniform bool u_restore;
void main() {
    bool empty = is_sky(texelFetch(u_position, ivec2(gl_FragCoord.xy), 0));
    if (u_restore) {
        if (!empty) discard;
        gl_FragDepth = 1.0;
    } else {
        gl_FragDepth = empty ? 0.0 : 1.0;
    }
}
