// A Quad Map is two arrays (structure of arrays, so the passes that only test validity read 16 bytes, not 80):
// plane[i].xyz = view-space normal, plane[i].w = view depth of the plane on the quad's centre ray (> 0 valid,
// 0 empty, -1 "marked": holds unmerged quads at a finer level); off[4 * i + s] = the 16 offsets (see quad.glsl),
// meaningful only where the plane is valid.
const float EMPTY = 0.0;
const float MARKED = -1.0;

// Normalised depth in [0, 1] between near and far: what the discontinuity threshold delta_max compares.
float normalized_depth(float z) {
    return (z - u_near) / (u_far - u_near);
}
