#version 430
// Crack fill, first pass (render/quadmesh.py, MeshView): after the mesh's first layer is drawn, a full-screen
// triangle on the far plane, depth-tested, so that it runs only where that layer drew nothing. Such a pixel whose
// two opposite neighbours -- in its row, its column or a diagonal, tried in that order -- the layer drew at depths
// that agree is a crack: it is listed with their mean colour and depth for crack_points.vert.glsl to draw.
layout(early_fragment_tests) in;
uniform sampler2D u_color;        // the first layer's colour
uniform sampler2D u_view_depth;   // its linear view depth, 0 where nothing was drawn
uniform float u_tolerance;        // relative depth: the neighbours agree within it
uniform uint u_capacity;          // cracks the list holds; more are left open (the draw never reads past it)

struct DrawCommand { uint count; uint instances; uint first; uint base_instance; };
layout(std430, binding = 0) buffer Cracks {
    DrawCommand command;          // the points' draw: count = the cracks listed
    uvec4 cracks[];               // x, y, depth (float bits), colour (packUnorm4x8)
};

const ivec2 STEPS[4] = ivec2[4](ivec2(1, 0), ivec2(0, 1), ivec2(1, 1), ivec2(1, -1));

void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    ivec2 last = textureSize(u_view_depth, 0) - 1;
    for (int k = 0; k < 4; ++k) {
        ivec2 a = p - STEPS[k], b = p + STEPS[k];
        if (any(lessThan(min(a, b), ivec2(0))) || any(greaterThan(max(a, b), last))) continue;
        float da = texelFetch(u_view_depth, a, 0).r;
        float db = texelFetch(u_view_depth, b, 0).r;
        float near = min(da, db);
        if (near <= 0.0 || abs(da - db) >= u_tolerance * near) continue;
        vec4 colour = 0.5 * (texelFetch(u_color, a, 0) + texelFetch(u_color, b, 0));
        uint i = atomicAdd(command.count, 1u);
        if (i < u_capacity) cracks[i] = uvec4(uvec2(p), floatBitsToUint(0.5 * (da + db)), packUnorm4x8(colour));
        else atomicAdd(command.count, 0xFFFFFFFFu);     // one too many: the count ends at the capacity
        break;
    }
    discard;
}
