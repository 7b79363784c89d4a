#version 430
// The workgroup count of the Patcher's hole pass (yoro_patch.comp, HOLES 1: 64 holes a group), for its indirect
// dispatch: the hole list's length is known only on the GPU.
layout(local_size_x = 1) in;
layout(std430, binding = 3) readonly buffer Holes { uint hole_count; };
layout(std430, binding = 4) writeonly buffer Groups { uint groups[3]; };
void main() {
    groups[0] = (hole_count + 63u) / 64u;
    groups[1] = 1u;
    groups[2] = 1u;
}
