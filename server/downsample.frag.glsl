#version 430
// The visible layer's view positions at the hidden layers' size, for depth peeling (server/layers.py): of the
// full-size pixels under each small pixel the nearest sample, so a surface seen there is the one peeling
// starts behind.
uniform sampler2D u_position;   // full-size view positions (w > 0 where geometry), GL rows bottom first
uniform ivec2 u_small_size;
layout(location = 0) out vec4 f_position;
void main() {
    ivec2 size = textureSize(u_position, 0);
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 lo = p * size / u_small_size;
    ivec2 hi = max((p + 1) * size / u_small_size, lo + 1);
    vec4 best = vec4(0.0);
    for (int y = lo.y; y < hi.y; ++y) for (int x = lo.x; x < hi.x; ++x) {
        vec4 q = texelFetch(u_position, ivec2(x, y), 0);
        if (q.w > 0.0 && (best.w <= 0.0 || q.z > best.z)) best = q;     // nearer: larger (less negative) z
    }
    f_position = best;
}
