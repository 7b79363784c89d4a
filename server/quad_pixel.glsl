// The G-buffer pixel a quad pass starts from (server/quad_planes.comp, server/quad_create.comp): its view-space
// position and normal, or false where it gets no quad -- masked out, beyond the far-field split, or without
// geometry when the layer has no sky quads (a sky pixel otherwise: a camera-facing plane u_sky_distance away).
uniform sampler2D u_position;   // view-space position, w > 0 where geometry (GL rows: bottom first)
uniform sampler2D u_normal;
uniform usampler2D u_mask;      // optional: only pixels with mask != 0 get quads
uniform bool u_use_mask;
uniform float u_max_angle;      // radians: normals are kept within this angle of the view ray
uniform float u_sky_distance;   // > 0: pixels with no geometry get a camera-facing quad this far away
uniform float u_max_depth;      // geometry farther than this (view depth) gets no quad: the far field shows it

bool load(ivec2 p, out vec3 n, out vec3 pos) {
    if (any(lessThan(p, ivec2(0))) || any(greaterThanEqual(p, u_size))) return false;
    ivec2 g = ivec2(p.x, u_size.y - 1 - p.y);
    if (u_use_mask && texelFetch(u_mask, g, 0).r == 0u) return false;
    vec4 P = texelFetch(u_position, g, 0);
    if (P.w > 0.0 && -P.z > u_max_depth) return false;
    if (P.w <= 0.0) {
        if (u_sky_distance <= 0.0) return false;
        pos = normalize(ray_dir(vec2(p) + 0.5)) * u_sky_distance;
        n = -normalize(pos);
        return true;
    }
    pos = P.xyz;
    n = normalize(texelFetch(u_normal, g, 0).xyz);
    return true;
}
