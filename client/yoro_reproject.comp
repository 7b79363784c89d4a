#version 430
// YORO Algorithm 1 (Reprojector stage 1), one invocation per ImBuffer pixel: lift the dominant eye's depth
// sample at this pixel's uv to a view-space point and move it with one matrix into the other eye's clip space.
// Writes (x where it lands, in ImBuffer pixel-centre units; its depth in the other eye). No random writes here.
layout(local_size_x = 8, local_size_y = 8) in;
#include "stereo_common.glsl"

layout(rg32f, binding = 0) writeonly uniform image2D u_targets;
uniform mat4 u_reproject;   // dominant eye view space -> other eye clip space (M of YORO eq. 5)
uniform vec4 u_extents;     // dominant eye's frustum l, r, b, t at distance 1

void main() {
    ivec2 size = imageSize(u_targets);
    ivec2 i = ivec2(gl_GlobalInvocationID.xy);
    if (any(greaterThanEqual(i, size))) return;
    vec2 uv = (vec2(i) + 0.5) / vec2(size);
    ivec2 src = ivec2(uv * vec2(textureSize(u_depth, 0)));
    float z = source_depth(src);
    vec3 ray = view_ray(u_extents, 1.0, uv);
    vec4 p = z < SKY_DEPTH ? vec4(ray * z, 1.0) : vec4(ray, 0.0);  // sky: a direction (point at infinity)
    vec4 c = u_reproject * p;
    float x = -1e9;  // behind the other eye: lands nowhere
    if (c.w > 0.0) x = (c.x / c.w * 0.5 + 0.5) * float(size.x) - 0.5;
    imageStore(u_targets, i, vec4(x, z < SKY_DEPTH ? c.w : SKY_DEPTH, 0.0, 0.0));
}
