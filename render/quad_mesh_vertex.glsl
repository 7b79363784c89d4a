// Layered-mesh rendering: a layer's vertices are in its camera's view space; u_layer_to_view takes them to the
// current eye's view space. The atlas uv is affine in the layer camera's image, so it is interpolated
// projectively: (uv * w, w) with w the vertex's depth in the layer camera, divided per fragment. At the layer's
// own pose this samples every pixel exactly where it was rendered, however deep a large quad is.
in vec3 in_position;
in vec2 in_uv;
uniform mat4 u_layer_to_view;
uniform mat4 u_proj;
uniform float u_depth_scale;  // > 1 pushes a fill-in layer (hidden, wide FOV, far field) behind the main one
uniform float u_max_depth;    // just inside the eye's far plane: nothing pushed back is clipped away
out vec3 v_uvw;
out vec3 v_view_pos;
// The vertex in the eye's view space (setting v_uvw and v_view_pos); each draw's main projects it with u_proj.
vec4 layer_vertex() {
    vec4 p = u_layer_to_view * vec4(in_position, 1.0);
    p.xyz *= u_depth_scale;   // along the eye ray: same pixel, slightly farther
    if (-p.z > u_max_depth) p.xyz *= u_max_depth / -p.z;
    float w = -in_position.z;
    v_view_pos = p.xyz;
    v_uvw = vec3(in_uv * w, w);
    return p;
}
