// Quad proxies in a layer camera's view space, shared by the server's quad stages and the mesh builder.
// A layer image is u_size pixels; image points are (x, y) pixels from the top-left corner. A quad is a plane
// (unit normal n facing the camera, view depth of the plane on the ray through its centre) plus 16 depth offsets:
// sub-quad s (0 TL, 1 TR, 2 BL, 3 BR) corner c (same order) = off[s][c], signed distances along the corner's ray.

#include "camera.glsl"

uniform vec4 u_frustum;   // left, right, bottom, top on the near plane
uniform float u_near;
uniform float u_far;
uniform ivec2 u_size;     // layer image size in pixels

// The (unnormalised) view-space ray through image point p (pixels from the top-left corner), with z = -near.
vec3 ray_dir(vec2 p) {
    return view_ray(u_frustum.xywz, u_near, p, vec2(u_size));
}

// Distance along the unit ray r where it meets the plane dot(n, X) = d (n faces the camera, so dot(n, r) < 0).
float ray_plane_t(vec3 r, vec3 n, float d) {
    return d / min(dot(n, r), -1e-3);
}

// The plane offset d of a plane with normal n whose depth on the ray through image point p is `depth`.
float plane_d(vec3 n, vec2 p, float depth) {
    return dot(n, ray_dir(p) * (depth / u_near));
}

// View depth (-z) of the point at distance t along the ray through p.
float depth_along(vec2 p, float t) {
    vec3 dir = ray_dir(p);
    return t * u_near / length(dir);
}

// Image point (pixels) of corner c of sub-quad s (both 0 TL, 1 TR, 2 BL, 3 BR) of the quad whose block starts at
// `origin` and is `size` pixels wide.
vec2 quad_corner_point(vec2 origin, float size, int s, int c) {
    return origin + 0.5 * size * vec2(float((s & 1) + (c & 1)), float((s >> 1) + (c >> 1)));
}

// View-space position of the mesh vertex at image point p: where its ray meets the quad's plane (normal n, offset
// d = plane_d(...)), moved `offset` along the ray, never nearer than the near plane.
vec3 quad_corner_position(vec2 p, vec3 n, float d, float offset) {
    vec3 r = normalize(ray_dir(p));
    return r * max(ray_plane_t(r, n, d) + offset, u_near);
}

// Keep a normal within max_angle of the direction back to the camera (avoids near-grazing quads).
vec3 limit_grazing(vec3 n, vec3 to_camera, float max_angle) {
    float c = dot(n, to_camera);
    float cmax = cos(max_angle);
    if (c >= cmax) return n;
    vec3 side = n - c * to_camera;
    float ls = length(side);
    if (ls < 1e-6) return to_camera;
    return normalize(side / ls * sin(max_angle) + to_camera * cmax);
}
