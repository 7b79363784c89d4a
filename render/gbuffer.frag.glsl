#version 430
// Geometry pass: write albedo, view-space normal, view-space position and object id.
#include "material.glsl"

void main() {
    write_gbuffer();
}
