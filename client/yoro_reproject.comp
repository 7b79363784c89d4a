#version 430
// YORO Algorithm 1 (Reprojector stage 1), one invocation per ImBuffer pixel: where the dominant eye's sample at
// this pixel lands in the other eye (`landing`, stereo_common.glsl). Writes (x where it lands, in ImBuffer
// pixel-centre units; its depth in the other eye). No random writes here.
layout(local_size_x = 8, local_size_y = 8) in;
#include "stereo_common.glsl"

layout(rg32f, binding = 0) writeonly uniform image2D u_targets;

void main() {
    ivec2 size = imageSize(u_targets);
    ivec2 i = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(i, size))) return;
    imageStore(u_targets, i, vec4(landing(i, size), 0.0, 0.0));
}
