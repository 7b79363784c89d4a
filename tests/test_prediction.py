"""Pose prediction (protocol.prediction) and its offline evaluation with the overshoot bound (sim.prediction)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from quadcast.protocol.prediction import (DEFAULT_PREDICTOR, PEAK_LOOKBACK_S, MotionModel, PosePredictor,
                                          PredictorSettings)
from quadcast.sim.prediction import prediction_errors

AXIS = np.array([0.3, 1.0, -0.2]) / np.linalg.norm([0.3, 1.0, -0.2])
UNDAMPED = PredictorSettings(MotionModel(1, 3), MotionModel(1, 2))
ACCELERATION = PredictorSettings(MotionModel(2, 3), MotionModel(2, 3))


def angle_deg(q_a: np.ndarray, q_b: np.ndarray) -> float:
    return float(np.degrees((Rotation.from_quat(q_a).inv() * Rotation.from_quat(q_b)).magnitude()))


def constant_motion_trace(duration=6.0, hz=60.0, v=(1.0, 0.0, 0.5), w_deg=90.0):
    t = np.arange(0.0, duration, 1.0 / hz)
    pos = np.array([0.1, 1.6, -0.3]) + np.outer(t, v)
    quat = (Rotation.from_rotvec(np.outer(np.radians(w_deg) * t, AXIS)) * Rotation.from_euler("y", 30, degrees=True)).as_quat()
    return t, pos, quat


def reversal_trace(duration=6.0, hz=60.0):
    """Head turns that reverse sharply: yaw is a triangle wave (±120 deg/s, turning back every 0.5 s), and the
    body walks back and forth (±1.5 m/s every 0.7 s) -- what made acceleration models overshoot."""
    t = np.arange(0.0, duration, 1.0 / hz)
    tri = lambda x: 2 * np.abs(x - np.floor(x + 0.5))  # noqa: E731  (0..1..0 triangle, period 1)
    yaw = 60.0 * tri(t / 1.0)
    x = 1.05 * tri(t / 1.4)
    pos = np.column_stack([x, np.full_like(t, 1.6), np.zeros_like(t)])
    quat = Rotation.from_euler("y", yaw[:, None], degrees=True).as_quat()
    return t, pos, quat


# -- PosePredictor --------------------------------------------------------------


def test_predict_before_observe_raises():
    with pytest.raises(RuntimeError, match="before any pose"):
        PosePredictor().predict(0.0)


def test_single_sample_holds_and_two_samples_extrapolate_constant_velocity():
    pred = PosePredictor(UNDAMPED)
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
    assert len(pred) == 1 and pred.latest.t == 1.0
    assert_allclose(pred.predict(2.0)[0], [1, 0, 0])


def test_constant_acceleration_is_predicted_exactly_by_an_unclamped_second_order_model():
    a, v0, p0 = np.array([0.8, -0.5, 2.0]), np.array([0.2, 1.0, -0.4]), np.array([0.0, 1.5, 0.0])
    alpha, w0 = np.radians(120.0), np.radians(-30.0)  # angular accel / velocity about a fixed axis
    r0 = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)

    def pose(t):
        return p0 + v0 * t + 0.5 * a * t * t, (Rotation.from_rotvec(AXIS * (w0 * t + 0.5 * alpha * t * t)) * r0).as_quat()

    model = MotionModel(order=2, window=7, clamp=False)   # least squares over 7 samples, exact for a quadratic
    pred = PosePredictor(PredictorSettings(model, model))
    times = np.cumsum([0.0, 0.03, 0.035, 0.031, 0.029, 0.033, 0.034, 0.032, 0.03])  # non-uniform steps
    for t in times:
        pred.observe(t, *pose(t))
    target = times[-1] + 0.1
    p, q = pred.predict(target)
    p_true, q_true = pose(target)
    assert np.linalg.norm(p - p_true) < 1e-9
    assert angle_deg(q, q_true) < 1e-7


def test_quaternion_sign_flips_do_not_change_prediction():
    t, pos, quat = constant_motion_trace(duration=0.5)
    flipped = quat * np.where(np.arange(len(t)) % 2 == 0, 1.0, -1.0)[:, None]
    for settings_ in (DEFAULT_PREDICTOR, ACCELERATION):
        a, b = PosePredictor(settings_), PosePredictor(settings_)
        for i in range(len(t)):
            a.observe(t[i], pos[i], quat[i])
            b.observe(t[i], pos[i], flipped[i])
        assert angle_deg(a.predict(t[-1] + 0.1)[1], b.predict(t[-1] + 0.1)[1]) < 1e-9


def test_fast_spin_through_many_turns_is_predicted_exactly():
    # 720 deg/s for 3 s: the rotation passes through 180 deg (rotvec wrap) and 360 deg many times.
    w = np.radians(720.0)
    pred = PosePredictor(UNDAMPED)
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
    pred = PosePredictor(UNDAMPED)
    for t in times:
        pred.observe(t, v * t, (Rotation.from_rotvec(w * t) * r0).as_quat())
    target = times[-1] + horizon
    p, q = pred.predict(target)
    assert_allclose(p, v * target, atol=1e-8)
    assert angle_deg(q, (Rotation.from_rotvec(w * target) * r0).as_quat()) < 1e-6


def test_damping_shortens_the_horizon_and_the_clamp_caps_the_step():
    model = MotionModel(1, 2, damping_s=0.1)
    assert model.horizon(0.1) == pytest.approx(0.1 * (1 - np.exp(-1)))
    assert model.horizon(-0.01) == -0.01 and MotionModel(1, 2).horizon(0.3) == 0.3
    # Constant 90 deg/s turn: damped, the prediction falls short by exactly the shorter horizon.
    pred = PosePredictor(PredictorSettings(MotionModel(1, 2), model))
    for t in (0.0, 0.1):
        pred.observe(t, [0, 0, 0], Rotation.from_euler("y", 90 * t, degrees=True).as_quat())
    q = pred.predict(0.2)[1]
    assert angle_deg(q, Rotation.from_euler("y", 18, degrees=True).as_quat()) == pytest.approx(
        9 * (1 - model.horizon(0.1) / 0.1), abs=1e-9)
    # A quadratic through a sharp reversal would run off; the clamp holds it to the peak speed seen recently.
    for clamp, expect_over in ((False, True), (True, False)):
        m = MotionModel(2, 3, clamp=clamp)
        pred = PosePredictor(PredictorSettings(m, m))
        for t, x in ((0.0, 0.0), (0.05, 0.1), (0.1, 0.1)):       # 2 m/s, then stopped
            pred.observe(t, [x, 0, 0], [0, 0, 0, 1])
        step = abs(pred.predict(0.2)[0][0] - 0.1)
        assert (step > 2.0 * 0.1 + 1e-9) == expect_over, (clamp, step)
    # max_speed (m/s; degrees/s for rotation) caps it absolutely.
    capped = PosePredictor(PredictorSettings(MotionModel(1, 2, max_speed=0.5), MotionModel(1, 2, max_speed=10.0)))
    for t in (0.0, 0.1):
        capped.observe(t, [t * 3, 0, 0], Rotation.from_euler("y", 90 * t, degrees=True).as_quat())
    p, q = capped.predict(0.2)
    assert p[0] == pytest.approx(0.3 + 0.05) and angle_deg(q, Rotation.from_euler("y", 9, degrees=True).as_quat()) \
        == pytest.approx(1.0)


def test_clamp_looks_back_a_limited_time():
    # Fast long ago, slow lately: only the steps of the last PEAK_LOOKBACK_S count.
    m = MotionModel(2, 8)
    pred = PosePredictor(PredictorSettings(m, m))
    times = np.arange(8) * 0.1
    xs = np.where(times < 0.3, times * 5.0, 1.5 + (times - 0.3) * 0.1)
    for t, x in zip(times, xs):
        pred.observe(t, [x, 0, 0], [0, 0, 0, 1])
    assert PEAK_LOOKBACK_S < 0.4
    assert abs(pred.predict(times[-1] + 0.1)[0][0] - xs[-1]) <= 0.1 * 0.1 + 1e-9


def test_settings_validation():
    for kwargs, message in (({"order": 4}, "order"), ({"order": 2, "window": 2}, "window"),
                            ({"damping_s": 0.0}, "damping_s"), ({"max_speed": -1.0}, "max_speed")):
        with pytest.raises(ValueError, match=message):
            MotionModel(**kwargs)
    with pytest.raises(ValueError, match="settings"):
        PosePredictor({"order": 1})
    with pytest.raises(ValueError, match="quat"):
        PosePredictor().observe(0.0, [0, 0, 0], [0, 0, 0, 0])
    with pytest.raises(ValueError, match="position"):
        PosePredictor().observe(0.0, [0, 0], [0, 0, 0, 1])
    assert "damping 300 ms" in str(DEFAULT_PREDICTOR)


# -- prediction_errors -------------------------------------------------------------


def test_prediction_beats_no_prediction_by_5x_on_constant_motion():
    t, pos, quat = constant_motion_trace()
    with_pred = prediction_errors(t, pos, quat, latency_ms=50, jitter_ms=5, predict=True, predictor=UNDAMPED)
    without = prediction_errors(t, pos, quat, latency_ms=50, jitter_ms=5, predict=False)
    assert with_pred["samples"] == without["samples"] > 150
    assert set(with_pred) == {"position_cm", "rotation_deg", "samples", "horizon_ms", "bound"}
    assert set(with_pred["position_cm"]) == {"mean", "std", "max"}
    # Without prediction the pose is ~2 x 50 ms stale: ~1.1 m/s * 0.1 s = 11 cm, 90 deg/s * 0.1 s = 9 deg.
    assert 9.0 < without["position_cm"]["mean"] < 13.0
    assert 7.0 < without["rotation_deg"]["mean"] < 11.0
    assert 90 < with_pred["horizon_ms"]["mean"] < 120
    assert with_pred["position_cm"]["mean"] * 5 <= without["position_cm"]["mean"]
    assert with_pred["rotation_deg"]["mean"] * 5 <= without["rotation_deg"]["mean"]
    # The default damps rotation: still well ahead of not predicting.
    default = prediction_errors(t, pos, quat, latency_ms=50, jitter_ms=5)
    assert default["rotation_deg"]["mean"] * 2 <= without["rotation_deg"]["mean"]


def test_zero_jitter_constant_motion_has_no_error_after_warmup():
    t, pos, quat = constant_motion_trace(duration=2.0)
    full = prediction_errors(t, pos, quat, latency_ms=40, jitter_ms=0, predictor=UNDAMPED)
    # Only the very first frame (a single sample: hold) can be wrong.
    assert full["position_cm"]["mean"] * full["samples"] == pytest.approx(full["position_cm"]["max"], rel=1e-6)


@pytest.mark.parametrize("latency, jitter", [(20, 10), (50, 20)])
def test_no_prediction_overshoots_the_bound_after_sharp_reversals(latency, jitter):
    t, pos, quat = reversal_trace()
    hold = prediction_errors(t, pos, quat, latency, jitter, predict=False)
    assert hold["bound"]["violations"] == 0          # not predicting is the bound's own baseline
    for seed in range(3):
        r = prediction_errors(t, pos, quat, latency, jitter, seed=seed)
        assert r["bound"]["violations"] == 0 and r["bound"]["max_excess_deg"] <= 1e-6, r["bound"]
    # An unclamped acceleration model does overshoot it: the bound can fail.
    wild = PredictorSettings(MotionModel(2, 3, clamp=False), MotionModel(2, 3, clamp=False))
    r = prediction_errors(t, pos, quat, latency, jitter, predictor=wild)
    assert r["bound"]["violations"] > 0 and r["rotation_deg"]["max"] > hold["rotation_deg"]["max"]


def test_seeded_determinism():
    t, pos, quat = reversal_trace(duration=3.0)
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
