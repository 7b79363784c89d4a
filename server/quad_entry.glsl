// A Quad Map entry: plane.xyz = view-space normal, plane.w = view depth of the plane on the quad's centre ray
// (> 0 valid, 0 empty, -1 "marked": holds unmerged quads at a finer level). off = 16 offsets (see quad.glsl).
struct QuadEntry {
    vec4 plane;
    vec4 off[4];
};
const float EMPTY = 0.0;
const float MARKED = -1.0;

// Normalised depth in [0, 1] between near and far: what the discontinuity threshold delta_max compares.
float normalized_depth(float z) {
    return (z - u_near) / (u_far - u_near);
}
