// Poses, matrices and traces in the page, with render/camera.py's and render/traces.py's conventions: world +Y
// up, a camera looks down its local -Z, quaternions are xyzw. Matrices are column-major Float64Array(16) (as
// WebGL and WebXR take them); uploads convert to Float32Array.

export function quatMul(a, b) {
  const [ax, ay, az, aw] = a, [bx, by, bz, bw] = b;
  return [aw * bx + ax * bw + ay * bz - az * by, aw * by - ax * bz + ay * bw + az * bx,
          aw * bz + ax * by - ay * bx + az * bw, aw * bw - ax * bx - ay * by - az * bz];
}

export function quatNormalize(q) {
  const n = Math.hypot(...q);
  return q.map((v) => v / n);
}

export function axisAngle(axis, deg) {
  const h = (deg * Math.PI) / 360, s = Math.sin(h);
  return [axis[0] * s, axis[1] * s, axis[2] * s, Math.cos(h)];
}

export function rotate(q, v) {
  const [x, y, z, w] = q;
  const tx = 2 * (y * v[2] - z * v[1]), ty = 2 * (z * v[0] - x * v[2]), tz = 2 * (x * v[1] - y * v[0]);
  return [v[0] + w * tx + y * tz - z * ty, v[1] + w * ty + z * tx - x * tz, v[2] + w * tz + x * ty - y * tx];
}

// Pose.from_euler: yaw about world Y, then pitch about the camera X, then roll (intrinsic YXZ), degrees.
export function quatFromYawPitch(yawDeg, pitchDeg, rollDeg = 0) {
  return quatMul(quatMul(axisAngle([0, 1, 0], yawDeg), axisAngle([1, 0, 0], pitchDeg)), axisAngle([0, 0, 1], rollDeg));
}

// QUASAR trace angles (render/traces.py): R = Rz(roll) Ry(yaw) Rx(pitch) about world axes.
export function quatFromTraceEuler(pitchDeg, yawDeg, rollDeg) {
  return quatMul(quatMul(axisAngle([0, 0, 1], rollDeg), axisAngle([0, 1, 0], yawDeg)), axisAngle([1, 0, 0], pitchDeg));
}

export function cameraToWorld(position, quat) {
  const [x, y, z, w] = quatNormalize(quat);
  const m = new Float64Array(16);
  m[0] = 1 - 2 * (y * y + z * z); m[1] = 2 * (x * y + z * w); m[2] = 2 * (x * z - y * w);
  m[4] = 2 * (x * y - z * w); m[5] = 1 - 2 * (x * x + z * z); m[6] = 2 * (y * z + x * w);
  m[8] = 2 * (x * z + y * w); m[9] = 2 * (y * z - x * w); m[10] = 1 - 2 * (x * x + y * y);
  m[12] = position[0]; m[13] = position[1]; m[14] = position[2]; m[15] = 1;
  return m;
}

// World -> view of a rigid pose (the inverse of cameraToWorld).
export function viewMatrix(position, quat) {
  const c = cameraToWorld(position, quat);
  const m = new Float64Array(16);
  for (let i = 0; i < 3; i++) for (let j = 0; j < 3; j++) m[j * 4 + i] = c[i * 4 + j];
  for (let i = 0; i < 3; i++) m[12 + i] = -(m[i] * c[12] + m[4 + i] * c[13] + m[8 + i] * c[14]);
  m[15] = 1;
  return m;
}

export function mul(a, b) {
  const m = new Float64Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0;
    for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
    m[c * 4 + r] = s;
  }
  return m;
}

// The gaze (quadcast.protocol.pose.gaze_direction's angles: degrees to the right and up from the view axis) of a point
// `dx`, `dy` pixels right of and above the centre of a view `heightPx` high with a vertical field of view `fovyDeg`,
// each angle capped at `maxDeg`.
export function gazeAt(dx, dy, heightPx, fovyDeg, maxDeg = 88) {
  const f = heightPx / 2 / Math.tan((fovyDeg * Math.PI) / 360);
  const deg = (v) => Math.max(-maxDeg, Math.min(maxDeg, (Math.atan(v / f) * 180) / Math.PI));
  return [deg(dx), deg(dy)];
}

// Frustum.symmetric and Frustum.projection_matrix (OpenGL clip space).
export function symmetricFrustum(fovyDeg, aspect, near = 0.1, far = 100.0) {
  const t = near * Math.tan((fovyDeg * Math.PI) / 360);
  return { left: -t * aspect, right: t * aspect, bottom: -t, top: t, near, far };
}

export function projection({ left: l, right: r, bottom: b, top: t, near: n, far: f }) {
  const m = new Float64Array(16);
  m[0] = (2 * n) / (r - l); m[5] = (2 * n) / (t - b);
  m[8] = (r + l) / (r - l); m[9] = (t + b) / (t - b); m[10] = -(f + n) / (f - n); m[11] = -1;
  m[14] = (-2 * f * n) / (f - n);
  return m;
}

export function slerp(q0, q1, u) {
  let dot = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3];
  const b = dot < 0 ? q1.map((v) => -v) : q1;            // the shorter arc, as scipy's Slerp
  dot = Math.abs(dot);
  if (dot > 0.9995) return quatNormalize(q0.map((v, i) => v + (b[i] - v) * u));
  const theta = Math.acos(Math.min(dot, 1)), s = Math.sin(theta);
  const w0 = Math.sin((1 - u) * theta) / s, w1 = Math.sin(u * theta) / s;
  return q0.map((v, i) => w0 * v + w1 * b[i]);
}

// A trace {times (s), positions, quats}: positions linear, rotations slerped, clamped at the ends (Trace.pose_at).
export function tracePoseAt(trace, t) {
  const { times, positions, quats } = trace;
  const n = times.length;
  if (t <= times[0] || n === 1) return { position: positions[0].slice(), quat: quats[0].slice() };
  if (t >= times[n - 1]) return { position: positions[n - 1].slice(), quat: quats[n - 1].slice() };
  let lo = 0, hi = n - 1;
  while (hi - lo > 1) {
    const mid = (lo + hi) >> 1;
    if (times[mid] <= t) lo = mid; else hi = mid;
  }
  const u = (t - times[lo]) / (times[hi] - times[lo]);
  return { position: positions[lo].map((v, k) => v + (positions[hi][k] - v) * u), quat: slerp(quats[lo], quats[hi], u) };
}

export class TraceError extends Error {}

// QUASAR trace text (x y z pitch yaw roll t_ms per line; blank and # lines skipped), as render/traces.py parses it.
export function parseQuasarTrace(text, name = "<upload>") {
  const times = [], positions = [], quats = [];
  const fields = ["x", "y", "z", "pitch", "yaw", "roll", "t_ms"];
  text.split(/\r?\n/).forEach((line, i) => {
    const s = line.trim();
    if (!s || s.startsWith("#")) return;
    const tokens = s.split(/\s+/);
    if (tokens.length !== 7) throw new TraceError(`${name}:${i + 1}: expected 7 fields (x y z pitch yaw roll t_ms), got ${tokens.length}`);
    const v = tokens.map((tok, k) => {
      const x = Number(tok);
      if (tok === "" || !Number.isFinite(x)) throw new TraceError(`${name}:${i + 1}: ${fields[k]} is not a finite number: ${JSON.stringify(tok)}`);
      return x;
    });
    if (times.length && v[6] / 1000 <= times[times.length - 1]) {
      throw new TraceError(`${name}:${i + 1}: time ${v[6]} ms is not after the previous line's; times must strictly increase`);
    }
    times.push(v[6] / 1000);
    positions.push(v.slice(0, 3));
    quats.push(quatFromTraceEuler(v[3], v[4], v[5]));
  });
  if (!times.length) throw new TraceError(`${name}: trace has no poses (only blank or comment lines)`);
  return { name, times, positions, quats };
}
