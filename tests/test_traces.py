"""Tests for sim.traces: QUASAR trace parsing, interpolation and the built-in traces."""

from __future__ import annotations

import re

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose
from scipy.spatial.transform import Rotation

from quadcast.render.traces import (
    BUILTIN_TRACES,
    SPAWN,
    Anchor,
    Trace,
    TraceError,
    builtin_trace,
    heading_deg,
    load_trace,
    parse_anchor,
    parse_trace,
    resolve_trace,
)

FORWARD = np.array([0.0, 0.0, -1.0])


def forward_of(quat: np.ndarray) -> np.ndarray:
    return Rotation.from_quat(quat).apply(FORWARD)


# ----------------------------------------------------------------- parsing
def test_parse_known_lines_and_conventions() -> None:
    text = """# x y z pitch yaw roll t_ms

1 2 3 0 0 0 0
1 2 3 0 90 0 16.5
1 2 3 0 -90 0 33
1 2 3 30 0 0 50
"""
    trace = parse_trace(text, name="known")
    assert len(trace) == 4
    np.testing.assert_allclose(trace.times, [0.0, 0.0165, 0.033, 0.050])
    np.testing.assert_allclose(trace.positions, np.tile([1.0, 2.0, 3.0], (4, 1)))
    forward = trace.rotations.apply(FORWARD)
    np.testing.assert_allclose(forward[0], [0, 0, -1], atol=1e-12)  # yaw 0 looks down -Z
    np.testing.assert_allclose(forward[1], [-1, 0, 0], atol=1e-12)  # yaw 90 looks down -X (left)
    np.testing.assert_allclose(forward[2], [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(forward[3], [0, 0.5, -np.sqrt(3) / 2], atol=1e-12)  # positive pitch looks up
    assert trace.quats.shape == (4, 4)
    np.testing.assert_allclose(trace.quats[1], Rotation.from_euler("y", 90, degrees=True).as_quat(), atol=1e-12)


def test_yaw_then_pitch_order() -> None:
    # yaw 90 then pitch 30 about the camera's own X: look left and up.
    trace = parse_trace("0 0 0 30 90 0 0\n")
    np.testing.assert_allclose(trace.rotations.apply(FORWARD)[0], [-np.sqrt(3) / 2, 0.5, 0.0], atol=1e-12)
    # Roll keeps the view direction but tilts the up vector.
    rolled = parse_trace("0 0 0 0 0 90 0\n")
    np.testing.assert_allclose(rolled.rotations.apply(FORWARD)[0], [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(rolled.rotations.apply([0, 1, 0])[0], [-1, 0, 0], atol=1e-12)


def test_yaw_wrap_interpolates_through_180() -> None:
    trace = parse_trace("0 0 0 0 179 0 0\n0 0 0 0 -179 0 100\n")
    np.testing.assert_allclose(trace.euler_deg[:, 1], [179.0, 181.0])  # unwrapped
    _, quat = trace.pose_at(0.05)
    np.testing.assert_allclose(forward_of(quat), [0, 0, 1], atol=1e-9)  # yaw 180: looking down +Z
    # A quarter of the way: yaw 179.5.
    _, quat = trace.pose_at(0.025)
    expected = Rotation.from_euler("y", 179.5, degrees=True).apply(FORWARD)
    np.testing.assert_allclose(forward_of(quat), expected, atol=1e-9)
    # Resampling keeps the unwrapped branch (no 358° swing).
    resampled = trace.resample(1000.0)
    assert np.all(np.abs(np.diff(resampled.euler_deg[:, 1])) < 1.0)
    np.testing.assert_allclose(resampled.euler_deg[[0, -1], 1], [179.0, 181.0], atol=1e-6)


def test_pitch_and_roll_unwrapped_too() -> None:
    trace = parse_trace("0 0 0 0 350 -170 0\n0 0 0 0 10 170 100\n0 0 0 0 30 150 200\n")
    np.testing.assert_allclose(trace.euler_deg[:, 1], [350.0, 370.0, 390.0])
    np.testing.assert_allclose(trace.euler_deg[:, 2], [-170.0, -190.0, -210.0])


@pytest.mark.parametrize(
    ("text", "line", "fragment"),
    [
        ("0 0 0 0 0 0 0\n0 0 0 0 0 16\n", 2, "expected 7 fields"),
        ("# header\n\n0 0 0 0 0 0 0\n0 0 zero 0 0 0 16\n", 4, "z is not a number"),
        ("0 0 0 0 0 0 0\n0 0 0 0 0 0 16\n0 0 0 0 0 0 16\n", 3, "times must strictly increase"),
        ("0 0 0 0 0 0 10\n0 0 0 0 0 0 5\n", 2, "not after"),
        ("0 0 0 nan 0 0 0\n", 1, "pitch is not finite"),
        ("0 0 0 0 0 0 0 0\n", 1, "got 8"),
    ],
)
def test_bad_lines_name_source_and_line_number(text: str, line: int, fragment: str) -> None:
    with pytest.raises(TraceError) as info:
        parse_trace(text, name="cam.txt")
    message = str(info.value)
    assert f"cam.txt:{line}:" in message
    assert fragment in message


def test_empty_trace_is_an_error() -> None:
    with pytest.raises(TraceError, match="no poses"):
        parse_trace("# only a comment\n\n   \n", name="empty.txt")


def test_trace_validates_arrays() -> None:
    with pytest.raises(TraceError, match="strictly increasing"):
        Trace("t", np.array([0.0, 0.0]), np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(TraceError, match="positions must have shape"):
        Trace("t", np.array([0.0, 1.0]), np.zeros((3, 3)), np.zeros((2, 3)))


def test_load_trace_file_and_missing_file(tmp_path) -> None:
    path = tmp_path / "path.txt"
    path.write_text("0 1.6 6 0 0 0 0\n0.5 1.6 6 0 10 0 500\n")
    trace = load_trace(path)
    assert trace.name == str(path)
    assert resolve_trace(str(path)).duration == pytest.approx(0.5)
    path.write_text("0 1.6 6 0 0 0 0\n0.5 1.6 6 0 x 0 500\n")
    with pytest.raises(TraceError, match=r"path\.txt:2: yaw is not a number"):
        load_trace(path)
    with pytest.raises(TraceError, match="not found"):
        resolve_trace(str(tmp_path / "missing.txt"))


# -------------------------------------------------------------- round trip
def test_round_trip_builtin_walk() -> None:
    walk = resolve_trace("builtin:walk")
    again = parse_trace(walk.to_text(), name="again")
    assert len(again) == len(walk)
    np.testing.assert_allclose(again.times, walk.times, atol=1e-6)
    np.testing.assert_allclose(again.positions, walk.positions, atol=1e-6)
    np.testing.assert_allclose(again.euler_deg, walk.euler_deg, atol=1e-6)
    # Integer milliseconds (what QUASAR's loader reads) still parse, times within half a ms.
    integer = parse_trace(walk.to_text(time_decimals=0))
    np.testing.assert_allclose(integer.times, walk.times, atol=5e-4)


@settings(max_examples=40, deadline=None)
@given(
    st.lists(
        st.tuples(
            st.floats(-50, 50),
            st.floats(-50, 50),
            st.floats(-50, 50),
            st.floats(-80, 80),
            st.floats(-180, 180),
            st.floats(-180, 180),
            st.floats(0.01, 100),
        ),
        min_size=1,
        max_size=12,
    )
)
def test_round_trip_property(rows) -> None:
    data = np.array(rows)
    times = np.cumsum(data[:, 6]) / 1000.0
    trace = Trace("prop", times, data[:, :3], data[:, 3:6])
    again = parse_trace(trace.to_text())
    np.testing.assert_allclose(again.times, trace.times, atol=1e-6)
    np.testing.assert_allclose(again.positions, trace.positions, atol=1e-5)
    np.testing.assert_allclose(again.euler_deg, trace.euler_deg, atol=1e-5)
    # Same poses, not just same numbers.
    np.testing.assert_allclose(
        (again.rotations * trace.rotations.inv()).magnitude(), 0.0, atol=1e-6
    )


# ------------------------------------------------------------ interpolation
def test_pose_at_midpoints_and_clamping() -> None:
    trace = parse_trace("0 0 0 0 0 0 0\n2 4 -6 0 90 0 1000\n")
    position, quat = trace.pose_at(0.5)
    np.testing.assert_allclose(position, [1, 2, -3])
    np.testing.assert_allclose(forward_of(quat), [-np.sqrt(0.5), 0, -np.sqrt(0.5)], atol=1e-12)
    position, quat = trace.pose_at(-3.0)
    np.testing.assert_allclose(position, [0, 0, 0])
    np.testing.assert_allclose(forward_of(quat), [0, 0, -1], atol=1e-12)
    position, quat = trace.pose_at(9.0)
    np.testing.assert_allclose(position, [2, 4, -6])
    np.testing.assert_allclose(forward_of(quat), [-1, 0, 0], atol=1e-12)


def test_poses_at_vectorised_matches_samples() -> None:
    walk = resolve_trace("builtin:walk")
    positions, quats = walk.poses_at(walk.times)
    np.testing.assert_allclose(positions, walk.positions, atol=1e-12)
    np.testing.assert_allclose((Rotation.from_quat(quats) * walk.rotations.inv()).magnitude(), 0, atol=1e-9)
    mid = (walk.times[:-1] + walk.times[1:]) / 2
    positions, quats = walk.poses_at(mid)
    np.testing.assert_allclose(positions, (walk.positions[:-1] + walk.positions[1:]) / 2, atol=1e-12)
    expected = [walk.pose_at(t)[1] for t in mid[:5]]
    np.testing.assert_allclose(np.abs(np.sum(quats[:5] * expected, axis=1)), 1.0, atol=1e-12)


def test_single_pose_trace() -> None:
    trace = parse_trace("1 2 3 0 45 0 100\n")
    assert trace.duration == 0.0
    position, quat = trace.pose_at(7.0)
    np.testing.assert_allclose(position, [1, 2, 3])
    np.testing.assert_allclose(quat, trace.quats[0])
    assert trace.speed().mean == 0.0


def test_resample_and_slice() -> None:
    strafe = resolve_trace("builtin:strafe")
    coarse = strafe.resample(10.0)
    assert len(coarse) == 41
    np.testing.assert_allclose(np.diff(coarse.times), 0.1)
    np.testing.assert_allclose(coarse.positions[:, 0], -2.0 + coarse.times, atol=1e-12)
    part = strafe.slice(1.005, 2.0)
    assert part.times[0] == pytest.approx(1.005) and part.times[-1] == pytest.approx(2.0)
    np.testing.assert_allclose(part.positions[0], [-2.0 + 1.005, 1.6, 6.0])
    assert np.all(np.diff(part.times) > 0)
    clamped = strafe.slice(-5.0, 0.5)
    assert clamped.times[0] == 0.0 and clamped.times[-1] == pytest.approx(0.5)
    with pytest.raises(TraceError, match="does not overlap"):
        strafe.slice(10.0, 11.0)
    with pytest.raises(TraceError, match="positive"):
        strafe.resample(0.0)


# ----------------------------------------------------------------- built-ins
def test_builtin_names_and_unknown() -> None:
    assert set(BUILTIN_TRACES) == {"walk", "orbit", "static", "strafe"}
    with pytest.raises(TraceError) as info:
        resolve_trace("builtin:nope")
    for name in BUILTIN_TRACES:
        assert f"builtin:{name}" in str(info.value)


@pytest.mark.parametrize("name", ["walk", "orbit", "static", "strafe"])
def test_builtins_are_60hz_and_deterministic(name: str) -> None:
    first, second = resolve_trace(f"builtin:{name}"), resolve_trace(f"builtin:{name}")
    assert first.name == f"builtin:{name}"
    np.testing.assert_allclose(np.diff(first.times), 1 / 60, atol=1e-12)
    assert first.times[0] == 0.0
    np.testing.assert_array_equal(first.positions, second.positions)
    np.testing.assert_array_equal(first.euler_deg, second.euler_deg)


def test_walk_stays_in_courtyard_and_walks_like_a_person() -> None:
    walk = resolve_trace("builtin:walk")
    p = walk.positions
    assert walk.duration >= 12.0
    assert np.abs(p[:, [0, 2]]).max() <= 6.5
    assert np.hypot(p[:, 0], p[:, 2]).min() >= 3.2
    assert 1.5 <= p[:, 1].min() and p[:, 1].max() <= 1.7
    assert np.ptp(p[:, 1]) > 0.01  # some bob
    speed = walk.speed()
    assert 1.0 <= speed.mean <= 2.0
    assert speed.max <= 2.2
    horizontal = np.linalg.norm(np.diff(p[:, [0, 2]], axis=0), axis=1) * 60
    assert horizontal.min() >= 0.8  # never stops dead
    # Starts at about (0, 1.6, 6) looking -Z-ish (towards the fountain).
    np.testing.assert_allclose(p[0], [0, 1.6, 6], atol=0.05)
    forward = walk.forward()
    assert forward[0, 2] < -0.7
    # Head turns relative to the walking direction, and some pitch.
    tangent = np.gradient(p[:, [0, 2]], walk.times, axis=0)
    walk_yaw = np.degrees(np.unwrap(np.arctan2(-tangent[:, 0], -tangent[:, 1])))
    head_yaw = walk.euler_deg[:, 1] - walk_yaw
    assert np.ptp(head_yaw) >= 40.0
    assert np.abs(head_yaw).max() <= 65.0
    assert np.ptp(walk.euler_deg[:, 1]) >= 40.0
    pitch = walk.euler_deg[:, 0]
    assert pitch.max() >= 3.0 and pitch.min() <= -5.0 and np.abs(pitch).max() <= 12.0
    # Smooth: no jumps in pose between frames.
    assert np.abs(np.diff(walk.euler_deg, axis=0)).max() < 2.0
    # Closed-ish loop.
    assert np.linalg.norm(p[-1] - p[0]) < 0.5


def test_orbit_looks_at_centre() -> None:
    orbit = resolve_trace("builtin:orbit")
    assert orbit.duration == pytest.approx(10.0)
    p = orbit.positions
    np.testing.assert_allclose(np.hypot(p[:, 0], p[:, 2]), 5.5, atol=1e-9)
    np.testing.assert_allclose(p[:, 1], 1.8)
    to_target = np.array([0.0, 1.0, 0.0]) - p
    to_target /= np.linalg.norm(to_target, axis=1, keepdims=True)
    np.testing.assert_allclose(orbit.forward(), to_target, atol=1e-9)
    # Also between samples.
    position, quat = orbit.pose_at(3.3 + 1 / 120)
    direction = np.array([0.0, 1.0, 0.0]) - position
    np.testing.assert_allclose(forward_of(quat), direction / np.linalg.norm(direction), atol=1e-4)
    # Level horizon (no roll): camera right vector stays horizontal.
    np.testing.assert_allclose(orbit.rotations.apply([1.0, 0.0, 0.0])[:, 1], 0.0, atol=1e-9)


def test_static_and_strafe() -> None:
    static = resolve_trace("builtin:static")
    assert static.duration == pytest.approx(3.0)
    np.testing.assert_allclose(static.positions, np.tile([0, 1.6, 6], (len(static), 1)))
    np.testing.assert_allclose(static.forward(), np.tile([0, 0, -1], (len(static), 1)), atol=1e-12)
    assert static.speed().max == 0.0
    strafe = resolve_trace("builtin:strafe")
    assert strafe.duration == pytest.approx(4.0)
    np.testing.assert_allclose(strafe.positions[0], [-2, 1.6, 6])
    np.testing.assert_allclose(strafe.positions[-1], [2, 1.6, 6])
    assert strafe.speed().mean == pytest.approx(1.0)
    np.testing.assert_allclose(strafe.forward(), np.tile([0, 0, -1], (len(strafe), 1)), atol=1e-12)


def test_scene_tour_walks_a_circle_inside_the_bounds_at_eye_height():
    from quadcast.render.traces import scene_tour
    bounds = np.array([[-10.0, 0.0, -6.0], [10.0, 8.0, 6.0]])
    tour = scene_tour(bounds, duration_s=4.0, speed_mps=1.2, eye_height=1.7)
    assert np.allclose(tour.positions[:, 1], 1.7)
    radius = np.hypot(tour.positions[:, 0], tour.positions[:, 2])
    assert np.allclose(radius, 3.0)                       # a quarter of the smaller horizontal side
    assert abs(tour.speed().mean - 1.2) < 0.05
    with pytest.raises(TraceError, match="bounds"):
        scene_tour(np.zeros(3))
    with pytest.raises(TraceError, match="radius"):
        scene_tour(bounds, radius=-1.0)


def test_glm_gimbal_flip_at_yaw_90_is_not_a_turn() -> None:
    # QUASAR writes glm::eulerAngles: near yaw -90° pitch and roll flip by 180° together between lines.
    trace = parse_trace("0 0 0 -179.6499 -88.3998 180.0 0\n"
                        "0 0 0 -0.9576 -90.0 0.0 16.7\n"
                        "0 0 0 -1.0984 -89.7555 0.0013 33.3\n")
    steps = (trace.rotations[1:] * trace.rotations[:-1].inv()).magnitude()
    assert np.degrees(steps).max() < 5.0          # a head turn, not a 180° flip
    # yaw -90: a quarter turn to the right of -Z, i.e. looking down +X, nearly level.
    np.testing.assert_allclose(trace.rotations[1].apply(FORWARD), [1.0, 0.0, 0.0], atol=0.03)


# ------------------------------------------------------------------------------- anchoring and windows

def _relative_motion(trace: Trace) -> tuple[np.ndarray, np.ndarray]:
    """What re-anchoring must keep: distances from the first position and turns from the first rotation."""
    r = trace.rotations
    return (np.linalg.norm(trace.positions - trace.positions[0], axis=1),
            np.degrees((r * r[0].inv()).magnitude()))


@pytest.mark.parametrize("yaw", [None, 0.0, -90.0, 90.0, 37.5, 180.0])
def test_anchored_moves_the_first_pose_and_keeps_the_motion(yaw) -> None:
    walk = builtin_trace("walk")
    moved = walk.anchored([3.0, 2.0, -1.0], yaw)
    assert_allclose(moved.positions[0], [3.0, 2.0, -1.0], atol=1e-12)
    heading = heading_deg(moved.rotations[0])
    expected = heading_deg(walk.rotations[0]) if yaw is None else yaw
    assert abs((heading - expected + 180.0) % 360.0 - 180.0) < 1e-3
    for a, b in zip(_relative_motion(walk), _relative_motion(moved)):
        assert_allclose(a, b, atol=1e-6)
    # The turn is about +Y only: heights move by the same offset, pitch (look up/down) stays.
    assert_allclose(moved.positions[:, 1] - walk.positions[:, 1], 2.0 - walk.positions[0, 1], atol=1e-12)
    up = lambda t: t.forward()[:, 1]  # noqa: E731
    assert_allclose(up(moved), up(walk), atol=1e-9)
    assert_allclose(moved.times, walk.times)


def test_anchored_at_a_later_pose_and_at_gimbal_lock() -> None:
    # Exactly at the lock, with no roll, the angles keep the reference's roll: no jump, no warning.
    still = Trace("still", np.array([0.0, 1.0]), np.zeros((2, 3)), np.array([[5.0, 10.0, 0.0], [6.0, 12.0, 0.0]]))
    locked = still.anchored([0, 0, 0], 90.0)
    assert_allclose(locked.euler_deg, [[5.0, 90.0, 0.0], [6.0, 92.0, 0.0]], atol=1e-3)
    walk = builtin_trace("walk")
    moved = walk.anchored([0.0, 1.0, 0.0], -90.0, at_s=2.0)
    p, q = moved.pose_at(walk.times[0] + 2.0)
    assert_allclose(p, [0.0, 1.0, 0.0], atol=1e-9)
    assert abs(heading_deg(Rotation.from_quat(q)) + 90.0) < 1e-3
    # Headings near ±90° are the trace format's gimbal lock (pitch and roll then jump, as glm writes them); the
    # rotations stay exact.
    expected = Rotation.from_euler("y", -90.0 - heading_deg(Rotation.from_quat(walk.pose_at(walk.times[0] + 2)[1])),
                                   degrees=True) * walk.rotations
    assert np.degrees((moved.rotations * expected.inv()).magnitude()).max() < 1e-3
    # Round trip through the text format keeps it.
    again = parse_trace(moved.to_text())
    assert np.degrees((again.rotations * moved.rotations.inv()).magnitude()).max() < 1e-3
    with pytest.raises(TraceError, match="anchor time"):
        walk.anchored([0, 0, 0], at_s=walk.duration + 1)


@pytest.mark.parametrize("text, expected", [
    ("spawn", SPAWN), (" 1, 2.5,-3 ", Anchor((1.0, 2.5, -3.0))), ("0,1.6,0,-90", Anchor((0.0, 1.6, 0.0), -90.0))])
def test_parse_anchor(text, expected) -> None:
    assert parse_anchor(text) == expected


@pytest.mark.parametrize("text, fragment", [
    ("", "spawn"), ("1,2", "3 or 4 numbers"), ("1,2,3,4,5", "3 or 4 numbers"), ("1,b,3", "y is not a number"),
    ("1,2,3,nan", "yaw_deg is not finite"), ("home", "3 or 4 numbers")])
def test_bad_anchor_is_named(text, fragment) -> None:
    with pytest.raises(TraceError, match=fragment):
        parse_anchor(text)


def test_window_cuts_and_checks() -> None:
    walk = builtin_trace("walk")
    w = walk.window(2.0, 1.5)
    assert w.times[0] == pytest.approx(walk.times[0] + 2.0) and w.duration == pytest.approx(1.5)
    assert walk.window(3.0).times[-1] == walk.times[-1]
    for start, duration in ((walk.duration, None), (-1.0, 1.0), (walk.duration - 1.0, 2.0), (1.0, 0.0)):
        with pytest.raises(TraceError, match=rf"{re.escape(walk.name)}"):
            walk.window(start, duration)


def test_fastest_window_finds_the_fast_part() -> None:
    # 10 s: still, then 2 s of a fast head turn from t = 6, then still again.
    t = np.arange(601) / 60.0
    yaw = np.degrees(np.clip(t - 6.0, 0.0, 2.0)) * 1.5
    slow = Trace("turn", t, np.tile([0.0, 1.6, 0.0], (len(t), 1)), np.stack([0 * t, yaw, 0 * t], axis=1))
    assert slow.fastest_window(2.0) == pytest.approx(6.0, abs=1 / 60)
    # Moving counts too: a sideways walk at 3 m/s from t = 1 to 3 outweighs a 30 deg/s turn elsewhere.
    x = 3.0 * np.clip(t - 1.0, 0.0, 2.0)
    both = Trace("both", t, np.stack([x, 1.6 + 0 * t, 0 * t], axis=1),
                 np.stack([0 * t, 30.0 * np.clip(t - 6.0, 0.0, 2.0), 0 * t], axis=1))
    assert both.fastest_window(2.0) == pytest.approx(1.0, abs=1 / 60)
    assert both.fastest_window(both.duration) == 0.0
    with pytest.raises(TraceError, match="shorter"):
        both.fastest_window(20.0)
