// Foveation of the quad thresholds (after the gaze-driven multi-resolution paper): sensitivity
// S(e) = exp(-max(0, e - r0)^2 / (2 sigma^2)) at eccentricity e from the gaze direction, and a threshold scale
// S^-gamma, capped -- quadcast.protocol.rate.fovea_scale computes the same on the CPU. Needs quad.glsl's ray_dir.
uniform vec4 u_fovea;   // fovea radius r0 (rad), sigma (rad; 0: uniform), gamma, largest scale
uniform vec3 u_gaze;    // unit gaze direction in the layer camera's view space

float fovea_scale(vec2 p) {
    if (u_fovea.y <= 0.0) return 1.0;
    float e = acos(clamp(dot(normalize(ray_dir(p)), u_gaze), -1.0, 1.0));
    float x = max(e - u_fovea.x, 0.0);
    return min(exp(u_fovea.z * x * x / (2.0 * u_fovea.y * u_fovea.y)), u_fovea.w);
}
