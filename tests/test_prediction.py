"""Tests for server.prediction: kinematic / Savitzky-Golay pose prediction."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from quadcast.protocol.prediction import PosePredictor, prediction_errors

AXIS = np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])


def angle_deg(q_a: np.ndarray, q_b: np.ndarray) -> float:
    return float(np.degrees((Rotation.from_quat(q_a).inv() * Rotation.from_quat(q_b)).magnitude()))


def constant_motion_trace(duration=6.0, hz=60.0, v=(1.0, 0.0, 0.5), w_deg=90.0):
    t = np.arange(0.0, duration, 1.0 / hz)
    pos = np.array([0.1, 1.6, -0.3]) + np.outer(t, v)
    quat = (Rotation.from_rotvec(np.outer(np.radians(w_deg) * t, AXIS)) * Rotation.from_euler("y", 30, degrees=True)).as_quat()
    return t, pos, quat


def smooth_noisy_trace(seed=1, duration=8.0, hz=60.0):
    t = np.arange(0.0, duration, 1.0 / hz)
    pos = np.column_stack([0.3 * np.sin(2 * np.pi * t / 4), 1.6 + 0.1 * np.cos(2 * np.pi * t / 3), 0.05 * t])
    rv = np.column_stack([np.radians(10) * np.sin(2 * np.pi * t / 6), np.radians(40) * np.sin(2 * np.pi * t / 5), 0 * t])
    rng = np.random.default_rng(seed)
    pos = pos + rng.normal(0.0, 0.002, pos.shape)
    quat = (Rotation.from_rotvec(rng.normal(0.0, np.radians(0.2), rv.shape)) * Rotation.from_rotvec(rv)).as_quat()
    return t, pos, quat


# -- PosePredictor --------------------------------------------------------------


def test_predict_before_observe_raises():
    with pytest.raises(RuntimeError, match="before any pose"):
        PosePredictor().predict(0.0)


def test_single_sample_holds_and_two_samples_extrapolate_constant_velocity():
    pred = PosePredictor()
    pred.observe(0.0, [0, 0, 0], [0, 0, 0, 1])
    p, q = pred.predict(1.0)
    assert_allclose(p, [0, 0, 0])
    assert angle_deg(q, [0, 0, 0, 1]) < 1e-9

    q1 = Rotation.from_rotvec([0, 0, np.radians(10)]).as_quat()
    pred.observe(0.1, [0.1, 0, 0], q1)
    p, q = pred.predict(0.3)
    assert_allclose(p, [0.3, 0, 0], atol=1e-12)
    assert_allclose(Rotation.from_quat(q).as_rotvec(), [0, 0, np.radians(30)], atol=1e-9)


def test_out_of_order_and_duplicate_samples_are_ignored():
    pred = PosePredictor()
    assert pred.observe(1.0, [1, 0, 0], [0, 0, 0, 1])
    assert not pred.observe(1.0, [5, 5, 5], [0, 0, 0, 1])
    assert not pred.observe(0.5, [9, 9, 9], [0, 0, 0, 1])
    assert len(pred) == 1
    assert_allclose(pred.predict(2.0)[0], [1, 0, 0])


@pytest.mark.parametrize("smooth", [False, True])
def test_constant_acceleration_is_predicted_almost_exactly(smooth):
    a, v0, p0 = np.array([0.8, -0.5, 2.0]), np.array([0.2, 1.0, -0.4]), np.array([0.0, 1.5, 0.0])
    alpha, w0 = np.radians(120.0), np.radians(-30.0)  # angular accel / velocity about a fixed axis
    r0 = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)

    def pose(t):
        return p0 + v0 * t + 0.5 * a * t * t, (Rotation.from_rotvec(AXIS * (w0 * t + 0.5 * alpha * t * t)) * r0).as_quat()

    pred = PosePredictor(smooth=smooth, window=7, order=2)
    times = np.cumsum([0.0, 0.03, 0.035, 0.031, 0.029, 0.033, 0.034, 0.032, 0.03])  # non-uniform steps
    for t in times:
        pred.observe(t, *pose(t))
    target = times[-1] + 0.1
    p, q = pred.predict(target)
    p_true, q_true = pose(target)
    assert np.linalg.norm(p - p_true) < 1e-9
    assert angle_deg(q, q_true) < 1e-7


def test_savgol_is_exact_for_quadratic_motion_on_uniform_steps():
    pred = PosePredictor(smooth=True, window=9, order=2)
    for t in np.arange(12) / 30.0:
        pred.observe(t, [t * t, 2 * t, 1.0], Rotation.from_rotvec([0, 0.5 * t * t + t, 0]).as_quat())
    t = 11 / 30.0 + 0.1
    p, q = pred.predict(t)
    assert_allclose(p, [t * t, 2 * t, 1.0], atol=1e-9)
    assert_allclose(Rotation.from_quat(q).as_rotvec(), [0, 0.5 * t * t + t, 0], atol=1e-9)


def test_quaternion_sign_flips_do_not_change_prediction():
    t, pos, quat = constant_motion_trace(duration=0.5)
    flipped = quat * np.where(np.arange(len(t)) % 2 == 0, 1.0, -1.0)[:, None]
    for smooth in (False, True):
        a, b = PosePredictor(smooth=smooth), PosePredictor(smooth=smooth)
        for i in range(len(t)):
            a.observe(t[i], pos[i], quat[i])
            b.observe(t[i], pos[i], flipped[i])
        assert angle_deg(a.predict(t[-1] + 0.1)[1], b.predict(t[-1] + 0.1)[1]) < 1e-9


def test_fast_spin_through_many_turns_is_predicted_exactly():
    # 720 deg/s for 3 s: the rotation passes through 180 deg (rotvec wrap) and 360 deg many times.
    w = np.radians(720.0)
    pred = PosePredictor()
    for t in np.arange(0.0, 3.0, 1.0 / 60.0):
        pred.observe(t, [0, 0, 0], Rotation.from_rotvec(AXIS * w * t).as_quat())
        target = t + 0.05
        if len(pred) >= 2:
            q = pred.predict(target)[1]
            assert angle_deg(q, Rotation.from_rotvec(AXIS * w * target).as_quat()) < 1e-6, t


@settings(max_examples=30, deadline=None)
@given(
    v=st.lists(st.floats(-3, 3), min_size=3, max_size=3),
    w=st.lists(st.floats(-4, 4), min_size=3, max_size=3),
    dts=st.lists(st.floats(0.005, 0.05), min_size=2, max_size=6),
    horizon=st.floats(0.0, 0.2),
)
def test_constant_velocity_property(v, w, dts, horizon):
    v, w = np.array(v), np.array(w)
    times = np.concatenate([[0.0], np.cumsum(dts)])
    r0 = Rotation.from_euler("zyx", [40, -10, 5], degrees=True)
    pred = PosePredictor()
    for t in times:
        pred.observe(t, v * t, (Rotation.from_rotvec(w * t) * r0).as_quat())
    target = times[-1] + horizon
    p, q = pred.predict(target)
    assert_allclose(p, v * target, atol=1e-8)
    assert angle_deg(q, (Rotation.from_rotvec(w * target) * r0).as_quat()) < 1e-6


def test_constructor_validation():
    with pytest.raises(ValueError, match="window"):
        PosePredictor(smooth=True, window=6)
    with pytest.raises(ValueError, match="order"):
        PosePredictor(smooth=True, window=5, order=5)
    with pytest.raises(ValueError, match="history"):
        PosePredictor(smooth=True, window=9, history=5)
    with pytest.raises(ValueError, match="quat"):
        PosePredictor().observe(0.0, [0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(ValueError, match="position"):
        PosePredictor().observe(0.0, [0, 0], [0, 0, 0, 1])


# -- prediction_errors -------------------------------------------------------------


def test_prediction_beats_no_prediction_by_5x_on_constant_motion():
    t, pos, quat = constant_motion_trace()
    with_pred = prediction_errors(t, pos, quat, latency_ms=50, jitter_ms=5, predict=True)
    without = prediction_errors(t, pos, quat, latency_ms=50, jitter_ms=5, predict=False)
    assert with_pred["samples"] == without["samples"] > 150
    assert set(with_pred) == {"position_cm", "rotation_deg", "samples"}
    assert set(with_pred["position_cm"]) == {"mean", "std", "max"}
    # Without prediction the pose is ~2 x 50 ms stale: ~1.1 m/s * 0.1 s = 11 cm, 90 deg/s * 0.1 s = 9 deg.
    assert 9.0 < without["position_cm"]["mean"] < 13.0
    assert 7.0 < without["rotation_deg"]["mean"] < 11.0
    assert with_pred["position_cm"]["mean"] * 5 <= without["position_cm"]["mean"]
    assert with_pred["rotation_deg"]["mean"] * 5 <= without["rotation_deg"]["mean"]


def test_zero_jitter_constant_motion_has_no_error_after_warmup():
    t, pos, quat = constant_motion_trace(duration=2.0)
    full = prediction_errors(t, pos, quat, latency_ms=40, jitter_ms=0)
    # Only the very first frame (a single sample: hold) can be wrong.
    assert full["position_cm"]["mean"] * full["samples"] == pytest.approx(full["position_cm"]["max"], rel=1e-6)


def test_smoothing_reduces_error_on_noisy_trace():
    t, pos, quat = smooth_noisy_trace()
    raw = prediction_errors(t, pos, quat, latency_ms=50, jitter_ms=10, smooth=False)
    smoothed = prediction_errors(t, pos, quat, latency_ms=50, jitter_ms=10, smooth=True)
    assert smoothed["position_cm"]["mean"] < 0.5 * raw["position_cm"]["mean"]
    assert smoothed["rotation_deg"]["mean"] < 0.5 * raw["rotation_deg"]["mean"]


def test_seeded_determinism():
    t, pos, quat = smooth_noisy_trace(duration=3.0)
    a = prediction_errors(t, pos, quat, latency_ms=30, jitter_ms=15, seed=7)
    b = prediction_errors(t, pos, quat, latency_ms=30, jitter_ms=15, seed=7)
    c = prediction_errors(t, pos, quat, latency_ms=30, jitter_ms=15, seed=8)
    assert a == b
    assert a != c


def test_trace_too_short_and_bad_shapes_raise():
    t, pos, quat = constant_motion_trace(duration=0.05)
    with pytest.raises(ValueError, match="no frame"):
        prediction_errors(t, pos, quat, latency_ms=200, jitter_ms=0)
    with pytest.raises(ValueError, match="positions"):
        prediction_errors(t, pos[:, :2], quat, latency_ms=20, jitter_ms=0)
    with pytest.raises(ValueError, match="increasing"):
        prediction_errors(t[::-1], pos, quat, latency_ms=20, jitter_ms=0)
