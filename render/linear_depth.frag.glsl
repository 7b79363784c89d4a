#version 430
// A G-buffer's linear view depth for read-back (GBuffer.read_depth): -z of the view position, +inf where nothing
// was drawn -- a quarter of the bytes of the position texture.
#include "camera.glsl"
uniform sampler2D u_position;
layout(location = 0) out float f_depth;
void main() {
    vec4 p = texelFetch(u_position, ivec2(gl_FragCoord.xy), 0);
    f_depth = is_sky(p) ? uintBitsToFloat(0x7f800000u) : -p.z;
}
