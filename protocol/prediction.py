"""Head-pose prediction for the server, and an offline evaluation of it.

A pose is ``(t, position, quat)``: time in seconds, position ``(3,)`` float64
metres, orientation quaternion ``(4,)`` in scipy's ``xyzw`` order.  All
rotation maths goes through :class:`scipy.spatial.transform.Rotation`, so a
quaternion and its negation are the same pose.

:class:`PosePredictor` extrapolates the latest observed pose kinematically,
with translational velocity/acceleration and angular velocity/acceleration.
Rotations are handled as rotation vectors of the history *relative to the
latest rotation* (``rotvec_i = (R_i * R_latest^-1).as_rotvec()``), which are
small and continuous around the latest sample, so there are no Euler or
360-degree wrap problems as long as consecutive samples differ by less than
180 degrees.  Derivatives come either from a quadratic through the last three
samples (exact finite differences over non-uniform steps) or, with
``smooth=True``, from a Savitzky-Golay fit (:func:`scipy.signal.savgol_filter`).

:func:`prediction_errors` replays a recorded head trace through a simulated
uplink/downlink to measure how far the pose a server renders for is from
the pose the user actually has when the frame is displayed.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import savgol_filter
from scipy.spatial.transform import Rotation, Slerp

__all__ = ["PoseSample", "PosePredictor", "prediction_errors", "MIN_STEP_S", "MAX_SPEED", "MAX_ACCELERATION",
           "MAX_ANGULAR_SPEED", "MAX_ANGULAR_ACCELERATION"]

MIN_STEP_S = 1e-3
"""Samples closer than this to the latest one are ignored like duplicates: finite differences over tiny steps are
noise (and over 1e-300 s they overflow)."""

MAX_SPEED = 50.0                   # m/s
MAX_ACCELERATION = 1000.0          # m/s^2
MAX_ANGULAR_SPEED = 8 * np.pi      # rad/s (1440 deg/s)
MAX_ANGULAR_ACCELERATION = 1000.0  # rad/s^2
"""Caps on the estimated derivatives (far above any head's, which stays under ~5 m/s and ~15 rad/s): whatever
poses a client sends, the extrapolation stays finite and bounded."""


def _clamp_norm(v: np.ndarray, limit: float) -> np.ndarray:
    """``v`` scaled down to norm ``limit`` if longer (NaN -> zero)."""
    v = np.nan_to_num(v, nan=0.0, posinf=limit, neginf=-limit)
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit else v


@dataclass(frozen=True)
class PoseSample:
    """One observed pose: time (s), position (3,) metres, unit quaternion (4,) xyzw."""

    t: float
    position: np.ndarray
    quat: np.ndarray


def _as_position(position: np.ndarray) -> np.ndarray:
    p = np.asarray(position, dtype=np.float64)
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise ValueError(f"position must be a finite array of shape (3,), got shape {p.shape}: {p!r}")
    return p.copy()


def _as_quat(quat: np.ndarray) -> np.ndarray:
    q = np.asarray(quat, dtype=np.float64)
    if q.shape != (4,) or not np.all(np.isfinite(q)):
        raise ValueError(f"quat must be a finite xyzw array of shape (4,), got shape {q.shape}: {q!r}")
    norm = np.linalg.norm(q)
    if not 1e-12 <= norm < np.inf:
        raise ValueError(f"quat must have a non-zero, finite norm, got {q!r}")
    return q / norm


def _three_point_derivatives(t: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and second derivative at ``t[2]`` of the quadratic through three
    samples ``(t[i], y[i])`` with non-uniform spacing (``y`` has shape (3, k))."""
    h1 = t[1] - t[0]
    h2 = t[2] - t[1]
    s = h1 + h2
    d1 = np.array([h2 / (h1 * s), -s / (h1 * h2), (h1 + 2.0 * h2) / (h2 * s)])
    d2 = 2.0 * np.array([1.0 / (h1 * s), -1.0 / (h1 * h2), 1.0 / (h2 * s)])
    return d1 @ y, d2 @ y


class PosePredictor:
    """Kinematic pose extrapolator over a short history of observed poses.

    Parameters
    ----------
    history:
        How many of the most recent samples to keep (>= 3, and >= ``window``
        when smoothing).
    smooth:
        If ``True``, estimate pose, velocity and acceleration with a
        Savitzky-Golay filter over the last ``window`` samples (resampled to
        a uniform grid over their time span with a cubic spline); otherwise use the quadratic
        through the last three samples.
    window, order:
        Savitzky-Golay window length (odd, > ``order``) and polynomial order
        (>= 1; with order 1 the acceleration is zero).

    With fewer samples than a method needs, prediction degrades gracefully:
    one sample -> hold; two -> constant velocity; fewer than ``window`` with
    ``smooth=True`` -> the three-sample finite differences.

    Whatever the samples, the prediction is finite: samples less than
    :data:`MIN_STEP_S` after the latest are ignored, and the estimated
    velocities and accelerations are capped (:data:`MAX_SPEED` and friends).
    """

    def __init__(self, history: int = 16, smooth: bool = False, window: int = 7, order: int = 2) -> None:
        window, order, history = int(window), int(order), int(history)
        if window < 3 or window % 2 == 0:
            raise ValueError(f"window must be an odd integer >= 3, got {window}")
        if not (1 <= order < window):
            raise ValueError(f"order must satisfy 1 <= order < window ({window}), got {order}")
        needed = max(3, window) if smooth else 3
        if history < needed:
            raise ValueError(f"history must be >= {needed} for smooth={smooth}, window={window}; got {history}")
        self.history = history
        self.smooth = bool(smooth)
        self.window = window
        self.order = order
        self._samples: deque[PoseSample] = deque(maxlen=history)

    def __len__(self) -> int:
        return len(self._samples)

    @property
    def latest(self) -> PoseSample | None:
        """The most recent accepted sample, or ``None`` before any."""
        return self._samples[-1] if self._samples else None

    def reset(self) -> None:
        """Forget all observed samples."""
        self._samples.clear()

    def observe(self, t: float, position: np.ndarray, quat: np.ndarray) -> bool:
        """Add a pose sample; returns ``False`` (and ignores it) if ``t`` is not
        at least :data:`MIN_STEP_S` later than the latest accepted sample
        (out-of-order, duplicate or too close)."""
        t = float(t)
        if not np.isfinite(t):
            raise ValueError(f"pose time t must be finite, got {t!r}")
        p, q = _as_position(position), _as_quat(quat)
        if self._samples and not t >= self._samples[-1].t + MIN_STEP_S:
            return False
        self._samples.append(PoseSample(t, p, q))
        return True

    # -- estimation ----------------------------------------------------------

    def _state(self) -> tuple[float, np.ndarray, Rotation, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Return (t0, position, rotation, velocity, acceleration, angular
        velocity, angular acceleration) at the latest sample time t0."""
        samples = list(self._samples)
        last = samples[-1]
        r_last = Rotation.from_quat(last.quat)
        zero = np.zeros(3)
        if len(samples) == 1:
            return last.t, last.position, r_last, zero, zero, zero, zero

        use_savgol = self.smooth and len(samples) >= self.window
        recent = samples[-self.window :] if use_savgol else samples[-3:]
        t = np.array([s.t for s in recent])
        pos = np.array([s.position for s in recent])
        # Rotation vectors relative to the latest rotation (world frame): R_i = exp(r_i) * R_last.
        rel = (Rotation.from_quat(np.array([s.quat for s in recent])) * r_last.inv()).as_rotvec()

        if len(recent) == 2:
            dt = t[1] - t[0]
            return last.t, last.position, r_last, (pos[1] - pos[0]) / dt, zero, (rel[1] - rel[0]) / dt, zero

        if not use_savgol:
            v, a = _three_point_derivatives(t, pos)
            w, alpha = _three_point_derivatives(t, rel)
            return last.t, last.position, r_last, v, a, w, alpha

        # Savitzky-Golay assumes uniform spacing: resample the window onto a uniform grid with a
        # (not-a-knot) cubic spline, which reproduces polynomial motion up to degree 3 exactly.
        grid = np.linspace(t[0], t[-1], len(t))
        delta = grid[1] - grid[0]
        y = CubicSpline(t, np.column_stack([pos, rel]), axis=0)(grid)

        def fit(deriv: int) -> np.ndarray:
            if deriv > self.order:
                return np.zeros(y.shape[1])
            return savgol_filter(y, self.window, self.order, deriv=deriv, delta=delta, axis=0, mode="interp")[-1]

        y0, y1, y2 = fit(0), fit(1), fit(2)
        r0 = Rotation.from_rotvec(y0[3:]) * r_last
        return last.t, y0[:3], r0, y1[:3], y2[:3], y1[3:], y2[3:]

    def predict(self, t_target: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted ``(position (3,), quat (4,) xyzw)`` at time ``t_target``."""
        if not self._samples:
            raise RuntimeError("PosePredictor.predict called before any pose was observed")
        t0, p0, r0, v, a, w, alpha = self._state()
        v, a = _clamp_norm(v, MAX_SPEED), _clamp_norm(a, MAX_ACCELERATION)
        w, alpha = _clamp_norm(w, MAX_ANGULAR_SPEED), _clamp_norm(alpha, MAX_ANGULAR_ACCELERATION)
        dt = float(t_target) - t0
        position = p0 + v * dt + 0.5 * a * dt * dt
        rotation = Rotation.from_rotvec(w * dt + 0.5 * alpha * dt * dt) * r0
        return position, rotation.as_quat()


# -- offline evaluation --------------------------------------------------------


def _validate_trace(times: np.ndarray, positions: np.ndarray, quats: np.ndarray) -> tuple[np.ndarray, np.ndarray, Rotation]:
    times = np.asarray(times, dtype=np.float64)
    positions = np.asarray(positions, dtype=np.float64)
    quats = np.asarray(quats, dtype=np.float64)
    n = times.shape[0] if times.ndim == 1 else -1
    if n < 2:
        raise ValueError(f"times must be a 1-D array with at least 2 samples, got shape {times.shape}")
    if positions.shape != (n, 3):
        raise ValueError(f"positions must have shape ({n}, 3) to match times, got {positions.shape}")
    if quats.shape != (n, 4):
        raise ValueError(f"quats must have shape ({n}, 4) to match times, got {quats.shape}")
    if not np.all(np.diff(times) > 0):
        raise ValueError("times must be strictly increasing")
    return times, positions, Rotation.from_quat(quats)


def _summary(values: np.ndarray) -> dict[str, float]:
    return {"mean": float(np.mean(values)), "std": float(np.std(values)), "max": float(np.max(values))}


def prediction_errors(
    times: np.ndarray,
    positions: np.ndarray,
    quats: np.ndarray,
    latency_ms: float,
    jitter_ms: float,
    predict: bool = True,
    smooth: bool = False,
    seed: int = 0,
    client_hz: float = 60.0,
    server_hz: float = 30.0,
) -> dict:
    """Replay a head trace through a simulated round trip and measure pose error.

    The simulation (after QUASAR section 4.1.4), on one shared clock:

    * the client tracks the trace at ``client_hz`` (the trace is interpolated
      at ``times[0] + i / client_hz``) and, every ``1 / server_hz`` seconds,
      sends its latest tracked pose with that pose's timestamp;
    * each pose reaches the server after ``latency_ms`` plus uniform jitter in
      ``+-jitter_ms`` (seeded; late poses that arrive after newer ones are
      ignored by the predictor);
    * on every received pose the server renders a frame for the pose it
      predicts at ``receive time + latency`` (its estimate of the downlink);
      with ``predict=False`` it renders the last received pose as-is;
    * the frame is displayed at ``receive time + latency + downlink jitter``
      (uniform in ``+-jitter_ms``, never before the receive time).

    Error is the distance (cm) and angle (degrees) between the rendered pose
    and the true trace pose at display time (linear interpolation for
    position, slerp for rotation).  Frames displayed outside the trace's time
    span are skipped.

    Returns ``{"position_cm": {"mean", "std", "max"}, "rotation_deg": {...},
    "samples": n}``.
    """
    times, positions, rotations = _validate_trace(times, positions, quats)
    latency_s = float(latency_ms) * 1e-3
    jitter_s = float(jitter_ms) * 1e-3
    if not np.isfinite(latency_s) or latency_s < 0:
        raise ValueError(f"latency_ms must be finite and >= 0, got {latency_ms!r}")
    if not np.isfinite(jitter_s) or jitter_s < 0:
        raise ValueError(f"jitter_ms must be finite and >= 0, got {jitter_ms!r}")
    if not client_hz > 0 or not server_hz > 0:
        raise ValueError(f"client_hz and server_hz must be > 0, got {client_hz!r} and {server_hz!r}")

    slerp = Slerp(times, rotations)

    def trace_position(t: np.ndarray) -> np.ndarray:
        return np.column_stack([np.interp(t, times, positions[:, k]) for k in range(3)])

    # Client tracking ticks and the pose it sends at each server tick.
    span = times[-1] - times[0]
    tick_times = times[0] + np.arange(int(np.floor(span * client_hz + 1e-9)) + 1) / client_hz
    send_times = times[0] + np.arange(int(np.floor(span * server_hz + 1e-9)) + 1) / server_hz
    tick_index = np.searchsorted(tick_times, send_times + 1e-9, side="right") - 1
    pose_times = tick_times[tick_index]
    pose_positions = trace_position(pose_times)
    pose_quats = slerp(pose_times).as_quat()

    rng = np.random.default_rng(seed)
    up_jitter = rng.uniform(-jitter_s, jitter_s, size=len(send_times))
    down_jitter = rng.uniform(-jitter_s, jitter_s, size=len(send_times))
    receive_times = send_times + np.maximum(0.0, latency_s + up_jitter)

    predictor = PosePredictor(smooth=smooth)
    rendered_pos, rendered_quat, display_times = [], [], []
    for k in np.argsort(receive_times, kind="stable"):
        predictor.observe(pose_times[k], pose_positions[k], pose_quats[k])
        t_display = receive_times[k] + max(0.0, latency_s + down_jitter[k])
        if not (times[0] <= t_display <= times[-1]):
            continue
        if predict:
            p, q = predictor.predict(receive_times[k] + latency_s)
        else:
            p, q = predictor.latest.position, predictor.latest.quat
        rendered_pos.append(p)
        rendered_quat.append(q)
        display_times.append(t_display)

    if not display_times:
        raise ValueError(
            f"no frame was displayed within the trace (span {span:.3f} s) at latency {latency_ms} ms; use a longer trace"
        )
    display_times = np.array(display_times)
    pos_err_cm = 100.0 * np.linalg.norm(np.array(rendered_pos) - trace_position(display_times), axis=1)
    rot_err_deg = np.degrees((Rotation.from_quat(np.array(rendered_quat)).inv() * slerp(display_times)).magnitude())
    return {
        "position_cm": _summary(pos_err_cm),
        "rotation_deg": _summary(rot_err_deg),
        "samples": int(len(display_times)),
    }
