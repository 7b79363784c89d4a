"""Offline evaluation of head-pose prediction (`quadcast predict`, QUASAR Table 1): how far the pose a server
renders for is from the pose the user has when the frame is shown, with and without prediction, and whether any
single prediction overshoots what the head's motion allows.

The overshoot bound: a frame predicted ``H`` seconds ahead of the latest pose the server had (``H`` = the time it
predicted for minus that pose's time) may be off by at most

    (the error of not predicting: the true motion from that pose to the display time)
    + (the head's peak speed between the trace samples from ``PEAK_LOOKBACK_S`` before that pose to the display
       time) * H,

i.e. a prediction may move the pose at most as fast as the head truly moved around that time. The clamped
:class:`quadcast.protocol.prediction.PosePredictor` meets it by construction; an unclamped acceleration model
overshoots it after sharp reversals. ``bound`` in the result counts the frames that break it.
"""
from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from quadcast.protocol.prediction import PEAK_LOOKBACK_S, PosePredictor, PredictorSettings

__all__ = ["prediction_errors"]

BOUND_SLACK = 1e-6
"""Numerical slack of the overshoot bound (cm and degrees)."""


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
    predictor: PredictorSettings | None = None,
    seed: int = 0,
    client_hz: float = 60.0,
    server_hz: float = 30.0,
) -> dict:
    """Replay a head trace through a simulated round trip and measure pose error.

    The simulation (after QUASAR section 4.1.4), on one shared clock:

    * the client tracks the trace at ``client_hz`` (the trace is interpolated at ``times[0] + i / client_hz``)
      and, every ``1 / server_hz`` seconds, sends its latest tracked pose with that pose's timestamp;
    * each pose reaches the server after ``latency_ms`` plus uniform jitter in ``+-jitter_ms`` (seeded; late poses
      that arrive after newer ones are ignored by the predictor);
    * on every received pose the server renders a frame for the pose it predicts (``predictor``, default
      :data:`quadcast.protocol.prediction.DEFAULT_PREDICTOR`) at ``receive time + latency`` (its estimate of the
      downlink); with ``predict=False`` it renders the last received pose as is;
    * the frame is displayed at ``receive time + latency + downlink jitter`` (uniform in ``+-jitter_ms``, never
      before the receive time).

    Error is the distance (cm) and angle (degrees) between the rendered pose and the true trace pose at display
    time (linear interpolation for position, slerp for rotation). Frames displayed outside the trace's time span
    are skipped.

    Returns ``{"position_cm": {"mean", "std", "max"}, "rotation_deg": {...}, "samples": n, "horizon_ms":
    {...}, "bound": {"violations", "max_excess_cm", "max_excess_deg"}}`` -- ``bound`` as in the module docstring
    (excess: the largest amount by which a frame's error went past its bound, <= 0 when none did).
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

    # Peak speeds of the trace's own segments (the truth the bound allows).
    seg_dt = np.diff(times)
    seg_speed_m = np.linalg.norm(np.diff(positions, axis=0), axis=1) / seg_dt
    seg_speed_deg = np.degrees((rotations[1:] * rotations[:-1].inv()).magnitude()) / seg_dt

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

    model = PosePredictor(predictor)
    rendered_pos, rendered_quat, display_times, known = [], [], [], []
    for k in np.argsort(receive_times, kind="stable"):
        model.observe(pose_times[k], pose_positions[k], pose_quats[k])
        t_display = receive_times[k] + max(0.0, latency_s + down_jitter[k])
        if not (times[0] <= t_display <= times[-1]):
            continue
        target = receive_times[k] + latency_s
        latest = model.latest
        if predict:
            p, q = model.predict(target)
        else:
            p, q = latest.position, latest.quat
        rendered_pos.append(p)
        rendered_quat.append(q)
        display_times.append(t_display)
        known.append((latest.t, latest.position, latest.quat, max(target - latest.t, 0.0)))

    if not display_times:
        raise ValueError(
            f"no frame was displayed within the trace (span {span:.3f} s) at latency {latency_ms} ms; use a longer trace"
        )
    display_times = np.array(display_times)
    true_pos, true_rot = trace_position(display_times), slerp(display_times)
    pos_err_cm = 100.0 * np.linalg.norm(np.array(rendered_pos) - true_pos, axis=1)
    rot_err_deg = np.degrees((Rotation.from_quat(np.array(rendered_quat)).inv() * true_rot).magnitude())

    # The overshoot bound per frame.
    t_known = np.array([k[0] for k in known])
    horizon = np.array([k[3] for k in known])
    hold_cm = 100.0 * np.linalg.norm(np.array([k[1] for k in known]) - true_pos, axis=1)
    hold_deg = np.degrees((Rotation.from_quat(np.array([k[2] for k in known])).inv() * true_rot).magnitude())
    first = np.searchsorted(times, t_known - PEAK_LOOKBACK_S, side="right") - 1
    last = np.searchsorted(times, display_times, side="left")
    peak_m = np.array([seg_speed_m[max(a, 0):max(b, a + 1)].max() for a, b in zip(first, last)])
    peak_deg = np.array([seg_speed_deg[max(a, 0):max(b, a + 1)].max() for a, b in zip(first, last)])
    excess_cm = pos_err_cm - (hold_cm + 100.0 * peak_m * horizon)
    excess_deg = rot_err_deg - (hold_deg + peak_deg * horizon)
    violations = int(np.count_nonzero((excess_cm > BOUND_SLACK) | (excess_deg > BOUND_SLACK)))
    return {
        "position_cm": _summary(pos_err_cm),
        "rotation_deg": _summary(rot_err_deg),
        "samples": int(len(display_times)),
        "horizon_ms": _summary(1e3 * horizon),
        "bound": {"violations": violations, "max_excess_cm": float(excess_cm.max()),
                  "max_excess_deg": float(excess_deg.max())},
    }
