#version 430
// The layered-mesh draw without colour (a depth-only MeshView): the linear view depth alone, as
// quad_mesh_fragment.glsl writes it beside the colour.
in vec3 v_view_pos;
layout(location = 0) out float f_depth;
void main() {
    f_depth = -v_view_pos.z;
}
