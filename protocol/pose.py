"""What a pose on the wire may be (sans-I/O): the bounds every decoder checks, so that any pose a decoder accepts
can be predicted from and rendered, and an absurd one is refused where it is read, with the field named.

A pose is a position (metres), a quaternion (x, y, z, w; sent as given, normalized by whoever uses it) and a time
(seconds on the sender's clock). Finite is not enough: a position of 1e300 m or a quaternion with components of
1e200 (whose norm overflows) are finite and still useless, so each part has a range:

- position: every coordinate within +-:data:`MAX_POSITION_M`;
- quaternion: finite, with a norm in [:data:`MIN_QUAT_NORM`, :data:`MAX_QUAT_NORM`] (normalizing it neither
  divides by ~0 nor overflows);
- time: within +-:data:`MAX_TIME_S`.

A pose may carry where the viewer looks, its gaze: two angles from the view axis in degrees (x to the right, y up),
each within +-:data:`MAX_GAZE_DEG` (a direction in front of the eye; :func:`gaze_direction` turns them into one).

The checks raise ValueError naming the field; the decoders turn that into a ProtocolError.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["MAX_POSITION_M", "MIN_QUAT_NORM", "MAX_QUAT_NORM", "MAX_TIME_S", "MAX_GAZE_DEG", "check_position",
           "check_quat", "check_time", "check_gaze", "gaze_direction"]

MAX_POSITION_M = 1e5
"""Largest absolute coordinate of a position, metres (100 km: any scene, far beyond any renderer's far plane)."""

MIN_QUAT_NORM = 1e-3
MAX_QUAT_NORM = 1e3
"""The norms a quaternion may have (unit quaternions are sent; this leaves room for sloppy senders)."""

MAX_TIME_S = 1e10
"""Largest absolute pose time, seconds (covers a Unix-epoch clock; float64 still resolves microseconds there)."""

MAX_GAZE_DEG = 89.0
"""Largest absolute gaze angle from the view axis, degrees (either axis; beyond it the direction leaves the front)."""


def _vector(name: str, value, n: int) -> np.ndarray:
    try:
        arr = np.array(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError):
        raise ValueError(f"{name}: expected {n} real numbers, got {value!r}") from None
    if arr.shape != (n,):
        raise ValueError(f"{name}: expected {n} numbers, got {arr.size}")
    if not all(map(math.isfinite, arr.tolist())):
        raise ValueError(f"{name}: expected finite numbers, got {arr.tolist()}")
    return arr


def check_position(name: str, value) -> np.ndarray:
    """A read-only float64 (3,) position within +-MAX_POSITION_M, or ValueError naming ``name``."""
    p = _vector(name, value, 3)
    if float(np.abs(p).max()) > MAX_POSITION_M:
        raise ValueError(f"{name}: expected coordinates within +-{MAX_POSITION_M:g} m, got {p.tolist()}")
    p.flags.writeable = False
    return p


def check_quat(name: str, value) -> np.ndarray:
    """A read-only float64 (4,) quaternion, as given, whose norm lies in [MIN_QUAT_NORM, MAX_QUAT_NORM]."""
    q = _vector(name, value, 4)
    scale = float(np.abs(q).max())
    # the norm without overflow: scale it down first (components up to ~1.8e308 are finite)
    norm = scale * math.sqrt(float(((q / scale) ** 2).sum())) if scale > 0 else 0.0
    if norm < MIN_QUAT_NORM:
        raise ValueError(f"{name}: expected a non-zero quaternion (norm >= {MIN_QUAT_NORM:g}), got {q.tolist()}")
    if norm > MAX_QUAT_NORM:
        raise ValueError(f"{name}: expected a quaternion of norm <= {MAX_QUAT_NORM:g}, got norm {norm:g}")
    q.flags.writeable = False
    return q


def check_time(name: str, value) -> float:
    """A finite time within +-MAX_TIME_S seconds."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}: expected a real number, got {value!r}")
    try:
        t = float(value)
    except OverflowError:
        raise ValueError(f"{name}: expected a time within +-{MAX_TIME_S:g} s, got {value!r}") from None
    if not math.isfinite(t):
        raise ValueError(f"{name}: expected a finite number, got {t!r}")
    if abs(t) > MAX_TIME_S:
        raise ValueError(f"{name}: expected a time within +-{MAX_TIME_S:g} s, got {t!r}")
    return t


def check_gaze(name: str, value) -> tuple[float, float]:
    """A gaze ``(x_deg, y_deg)`` (to the right and up from the view axis) as two floats, each within
    +-MAX_GAZE_DEG, or ValueError naming ``name``."""
    g = _vector(name, value, 2)
    if float(np.abs(g).max()) >= MAX_GAZE_DEG:
        raise ValueError(f"{name}: expected angles within +-{MAX_GAZE_DEG:g} degrees of the view axis, got {g.tolist()}")
    return float(g[0]), float(g[1])


def gaze_direction(angles_deg) -> np.ndarray:
    """The unit view-space direction (the camera looks down -Z) of a gaze ``(x_deg, y_deg)`` (see :func:`check_gaze`)."""
    x, y = np.tan(np.radians(np.asarray(angles_deg, np.float64)))
    d = np.array([x, y, -1.0])
    return d / np.linalg.norm(d)
