"""Camera traces: timed sequences of head poses, in QUASAR's text format.

A *pose* is a world-space position (metres, +Y up) and a rotation
(:class:`scipy.spatial.transform.Rotation`, quaternions stored ``xyzw``).
The camera looks down its local -Z with +Y up (OpenGL convention).

QUASAR's trace format has one pose per line::

    x y z pitch yaw roll t_ms

(metres, degrees, milliseconds; usually 60 Hz). Blank lines and lines
starting with ``#`` are ignored. Angles are those QUASAR writes with
``glm::eulerAngles``: ``R = Rz(roll) * Ry(yaw) * Rx(pitch)`` about world
axes, i.e. ``Rotation.from_euler("xyz", [pitch, yaw, roll], degrees=True)``.
yaw is the middle angle, so at yaw = +-90° pitch and roll may flip by 180°
together between two lines (gimbal lock) -- same orientation, no jump. With
roll = 0 this is yaw about world Y after pitch about X: yaw = pitch = 0 looks
down -Z, positive yaw turns left (towards -X) and positive pitch looks up.

Besides files, a few traces are built in code (:data:`BUILTIN_TRACES`) and
can be named as ``"builtin:NAME"`` in :func:`resolve_trace`.

A trace recorded in one scene can be replayed in another: :meth:`Trace.anchored`
keeps its motion relative to one of its poses and moves that pose to an
:class:`Anchor` (a position and optionally a heading), :func:`parse_anchor`
reads ``x,y,z[,yaw_deg]`` (or ``spawn``, a scene's own spawn point, see
:func:`quadcast.render.scene.place_trace`); :meth:`Trace.window` cuts a part of a
long trace and :meth:`Trace.fastest_window` finds its part with the most motion.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.integrate import cumulative_trapezoid
from scipy.spatial.transform import Rotation, Slerp

__all__ = [
    "Anchor",
    "BUILTIN_TRACES",
    "SPAWN",
    "Trace",
    "TraceError",
    "TraceSpeed",
    "builtin_trace",
    "euler_to_rotation",
    "heading_deg",
    "load_trace",
    "look_at_euler",
    "parse_anchor",
    "parse_trace",
    "resolve_trace",
]

#: Sample rate of QUASAR traces and of the built-in traces (Hz).
TRACE_HZ = 60.0
#: Euler sequence of the trace format: extrinsic x (pitch), y (yaw), z (roll), as glm::eulerAngles.
EULER_SEQ = "xyz"
#: Number of whitespace-separated fields on a trace line.
FIELDS_PER_LINE = 7
#: The anchor that names a scene's own spawn point (``--anchor spawn``).
SPAWN = "spawn"
#: Depth (m) at which :meth:`Trace.fastest_window` weighs translation against rotation: moving 1 m sideways shifts
#: what is this far away as much as turning by 1/APPARENT_DEPTH_M radians.
APPARENT_DEPTH_M = 3.0


class TraceError(ValueError):
    """A camera trace is malformed, unknown or cannot be read."""


def euler_to_rotation(euler_deg: np.ndarray) -> Rotation:
    """Rotation(s) for trace angles given as ``(pitch, yaw, roll)`` degrees, shape (3,) or (N, 3)."""
    euler = np.asarray(euler_deg, dtype=np.float64)
    return Rotation.from_euler(EULER_SEQ, euler, degrees=True)


def rotation_to_euler(rotation: Rotation) -> np.ndarray:
    """Trace angles ``(pitch, yaw, roll)`` in degrees for a rotation (yaw in [-90, 90], the others (-180, 180]).
    At yaw = ±90° (gimbal lock) only pitch ∓ roll is defined; scipy then picks roll = 0 (without its warning)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Gimbal lock detected")
        return rotation.as_euler(EULER_SEQ, degrees=True)


def unwrap_degrees(angles_deg: np.ndarray) -> np.ndarray:
    """Remove 360° jumps between consecutive rows of an angle array (degrees, along axis 0)."""
    return np.unwrap(np.asarray(angles_deg, dtype=np.float64), period=360.0, axis=0)


def heading_deg(rotation: Rotation) -> np.ndarray | float:
    """The compass heading (degrees, as trace yaw: 0 looks down -Z, positive turns left) of where each camera looks:
    its forward direction projected on the ground plane; 0 for a camera looking straight up or down."""
    forward = np.atleast_2d(rotation.apply([0.0, 0.0, -1.0]))
    vertical = np.hypot(forward[:, 0], forward[:, 2]) < 1e-9
    heading = np.where(vertical, 0.0, np.degrees(np.arctan2(-forward[:, 0], -forward[:, 2])))
    return float(heading[0]) if rotation.single else heading


def _euler_near(quats: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Trace angles of the rotations ``quats`` (M, 4) on the 360° branch and the one of their two angle triples
    nearest ``reference`` (M, 3) degrees -- both triples are the same rotation, so this only keeps angles
    continuous."""
    raw = rotation_to_euler(Rotation.from_quat(quats))
    # Every rotation has two angle triples: (p, y, r) and (p + 180, 180 - y, r + 180).
    candidates = []
    for angles in (raw, raw * [1.0, -1.0, 1.0] + [180.0, 180.0, 180.0]):
        angles = angles + 360.0 * np.round((reference - angles) / 360.0)
        candidates.append(angles)
    far = np.abs(candidates[0] - reference).sum(1) > np.abs(candidates[1] - reference).sum(1)
    euler = np.where(far[:, None], candidates[1], candidates[0])
    # Within 0.001° of gimbal lock (yaw ±90°) pitch and roll trade off: keep the reference roll and solve pitch and
    # yaw for it (off by at most about as much).
    # With R = Rz(roll) Ry(yaw) Rx(pitch), M = Rz(-roll) R = Ry(yaw) Rx(pitch) has row 1 = (0, cos p, -sin p).
    locked = np.abs(np.abs(raw[:, 1]) - 90.0) < 1e-3
    if np.any(locked):
        roll = reference[locked, 2]
        m = (Rotation.from_euler("z", -roll[:, None], degrees=True) * Rotation.from_quat(quats[locked])).as_matrix()
        pitch = np.degrees(np.arctan2(-m[:, 1, 2], m[:, 1, 1]))
        ry = m @ Rotation.from_euler("x", -pitch[:, None], degrees=True).as_matrix()
        yaw = np.degrees(np.arctan2(ry[:, 0, 2], ry[:, 0, 0]))
        fixed = np.stack([pitch, yaw, roll], axis=1)
        euler[locked] = fixed + 360.0 * np.round((reference[locked] - fixed) / 360.0)
    return euler


@dataclass(frozen=True)
class Anchor:
    """Where a re-anchored trace starts: its reference pose goes to ``position`` (metres) and turns (about +Y) to
    heading ``yaw_deg`` (degrees, as trace yaw; None keeps the trace's own heading: a pure translation)."""

    position: tuple[float, float, float]
    yaw_deg: float | None = None

    def __post_init__(self) -> None:
        p = np.asarray(self.position, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise TraceError(f"anchor position must be 3 finite numbers, got {self.position!r}")
        if self.yaw_deg is not None and not np.isfinite(self.yaw_deg):
            raise TraceError(f"anchor yaw must be a finite number of degrees, got {self.yaw_deg!r}")
        object.__setattr__(self, "position", tuple(float(v) for v in p))

    def __str__(self) -> str:
        text = ",".join(f"{v:g}" for v in self.position)
        return text if self.yaw_deg is None else f"{text},{self.yaw_deg:g}"


def parse_anchor(text: str) -> Anchor | str:
    """``"x,y,z"`` or ``"x,y,z,yaw_deg"`` -> :class:`Anchor`; ``"spawn"`` -> :data:`SPAWN` (resolved against a
    scene by :func:`quadcast.render.scene.place_trace`). Anything else raises :class:`TraceError` naming it."""
    if not isinstance(text, str) or not text.strip():
        raise TraceError(f"anchor must be 'spawn' or 'x,y,z[,yaw_deg]', got {text!r}")
    text = text.strip()
    if text == SPAWN:
        return SPAWN
    fields = [f.strip() for f in text.split(",")]
    if len(fields) not in (3, 4):
        raise TraceError(f"anchor {text!r}: expected 'spawn' or 'x,y,z[,yaw_deg]' (3 or 4 numbers), "
                         f"got {len(fields)} fields")
    values = [_finite(token, f"anchor {text!r}: {label}") for label, token in zip(("x", "y", "z", "yaw_deg"), fields)]
    return Anchor(tuple(values[:3]), values[3] if len(values) == 4 else None)


def look_at_euler(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """``(pitch, yaw, roll)`` degrees (roll = 0) of cameras at ``eye`` (N,3) looking at ``target``.

    Yaw is unwrapped along the rows, so a camera circling the target has a
    continuous yaw.
    """
    eye = np.atleast_2d(np.asarray(eye, dtype=np.float64))
    forward = np.asarray(target, dtype=np.float64) - eye
    horizontal = np.hypot(forward[:, 0], forward[:, 2])
    if np.any(np.hypot(horizontal, forward[:, 1]) == 0.0):
        raise TraceError("look_at_euler: eye coincides with target")
    yaw = np.degrees(np.arctan2(-forward[:, 0], -forward[:, 2]))
    pitch = np.degrees(np.arctan2(forward[:, 1], horizontal))
    euler = np.stack([pitch, yaw, np.zeros_like(yaw)], axis=1)
    return unwrap_degrees(euler)


@dataclass(frozen=True)
class TraceSpeed:
    """Linear speed statistics of a trace (m/s), from per-sample segment speeds."""

    mean: float
    """Path length divided by duration."""
    median: float
    p95: float
    max: float
    path_length: float
    """Total distance travelled (m)."""


@dataclass(eq=False)
class Trace:
    """A camera trace: poses sampled at strictly increasing times.

    ``times`` (N,) are seconds, ``positions`` (N, 3) metres in world space and
    ``euler_deg`` (N, 3) the QUASAR angles ``(pitch, yaw, roll)`` in degrees,
    unwrapped (no 360° jumps between samples). Times keep whatever origin the
    source had; built-in traces start at 0.
    """

    name: str
    times: np.ndarray
    positions: np.ndarray
    euler_deg: np.ndarray
    _slerp: Slerp | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.times = np.asarray(self.times, dtype=np.float64)
        self.positions = np.asarray(self.positions, dtype=np.float64)
        self.euler_deg = np.asarray(self.euler_deg, dtype=np.float64)
        n = self.times.shape[0] if self.times.ndim == 1 else -1
        if n < 1:
            raise TraceError(f"trace {self.name!r}: times must be a non-empty 1-D array, got shape {self.times.shape}")
        for label, array in (("positions", self.positions), ("euler_deg", self.euler_deg)):
            if array.shape != (n, 3):
                raise TraceError(f"trace {self.name!r}: {label} must have shape ({n}, 3), got {array.shape}")
        for label, array in (("times", self.times), ("positions", self.positions), ("euler_deg", self.euler_deg)):
            if not np.all(np.isfinite(array)):
                raise TraceError(f"trace {self.name!r}: {label} contains NaN or infinity")
        steps = np.diff(self.times)
        if np.any(steps <= 0.0):
            bad = int(np.argmax(steps <= 0.0)) + 1
            raise TraceError(
                f"trace {self.name!r}: times must be strictly increasing, "
                f"sample {bad} has t={self.times[bad]!r} after t={self.times[bad - 1]!r}"
            )
        self.euler_deg = unwrap_degrees(self.euler_deg)

    # ------------------------------------------------------------------ basics
    def __len__(self) -> int:
        return int(self.times.shape[0])

    @property
    def duration(self) -> float:
        """Seconds from the first to the last sample."""
        return float(self.times[-1] - self.times[0])

    @property
    def rotations(self) -> Rotation:
        """The N camera rotations (camera-to-world)."""
        return euler_to_rotation(self.euler_deg)

    @property
    def quats(self) -> np.ndarray:
        """The N camera rotations as quaternions, (N, 4) ``xyzw``."""
        return self.rotations.as_quat()

    def forward(self) -> np.ndarray:
        """Unit viewing directions (the camera's -Z in world space), (N, 3)."""
        return self.rotations.apply([0.0, 0.0, -1.0])

    # ----------------------------------------------------------- interpolation
    def _rotation_interpolator(self) -> Callable[[np.ndarray], Rotation]:
        if len(self) == 1:
            only = self.rotations[0]
            return lambda t: Rotation.from_quat(np.repeat(only.as_quat()[None], np.size(t), axis=0))
        if self._slerp is None:
            self._slerp = Slerp(self.times, self.rotations)
        return self._slerp

    def poses_at(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated poses at ``times`` (M,) seconds: positions (M, 3) and quaternions (M, 4) ``xyzw``.

        Positions are interpolated linearly and rotations by slerp; times
        outside the trace are clamped to its first/last pose.
        """
        query = np.asarray(times, dtype=np.float64).reshape(-1)
        if not np.all(np.isfinite(query)):
            raise TraceError(f"trace {self.name!r}: query times must be finite")
        query = np.clip(query, self.times[0], self.times[-1])
        positions = np.stack([np.interp(query, self.times, self.positions[:, k]) for k in range(3)], axis=1)
        quats = self._rotation_interpolator()(query).as_quat()
        return positions, quats

    def pose_at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Interpolated pose at time ``t`` seconds: position (3,) and quaternion (4,) ``xyzw`` (clamped at the ends)."""
        positions, quats = self.poses_at(np.array([t], dtype=np.float64))
        return positions[0], quats[0]

    def _euler_at(self, query: np.ndarray, quats: np.ndarray) -> np.ndarray:
        """Unwrapped ``(pitch, yaw, roll)`` of interpolated rotations, kept on the same 360° branch as the source
        (the angle triple nearer the linearly interpolated source angles)."""
        reference = np.stack([np.interp(query, self.times, self.euler_deg[:, k]) for k in range(3)], axis=1)
        return _euler_near(quats, reference)

    def resample(self, hz: float) -> Trace:
        """The trace sampled uniformly at ``hz`` from its first time (the last sample lands at or before the end)."""
        if not np.isfinite(hz) or hz <= 0.0:
            raise TraceError(f"trace {self.name!r}: resample rate must be a positive number of Hz, got {hz!r}")
        count = int(np.floor(self.duration * hz + 1e-9)) + 1
        query = self.times[0] + np.arange(count, dtype=np.float64) / hz
        positions, quats = self.poses_at(query)
        return Trace(self.name, query, positions, self._euler_at(query, quats))

    def slice(self, t0: float, t1: float) -> Trace:
        """The part of the trace between ``t0`` and ``t1`` seconds (clamped to the trace).

        Samples inside the interval are kept as they are; interpolated poses
        are added at ``t0``/``t1`` when no sample falls exactly there. Times are
        not shifted.
        """
        if not (np.isfinite(t0) and np.isfinite(t1)) or t1 < t0:
            raise TraceError(f"trace {self.name!r}: slice needs finite t0 <= t1, got t0={t0!r}, t1={t1!r}")
        lo = max(float(t0), float(self.times[0]))
        hi = min(float(t1), float(self.times[-1]))
        if hi < lo:
            raise TraceError(
                f"trace {self.name!r}: slice [{t0}, {t1}] does not overlap the trace "
                f"[{self.times[0]}, {self.times[-1]}]"
            )
        inside = (self.times >= lo) & (self.times <= hi)
        query = np.unique(np.concatenate([[lo], self.times[inside], [hi]]))
        positions, quats = self.poses_at(query)
        euler = self._euler_at(query, quats)
        # Keep original samples bit-exact.
        kept = np.isin(query, self.times[inside])
        positions[kept] = self.positions[inside]
        euler[kept] = self.euler_deg[inside]
        return Trace(self.name, query, positions, euler)

    def window(self, start_s: float = 0.0, duration_s: float | None = None) -> Trace:
        """The part of the trace from ``start_s`` seconds after its first sample, lasting ``duration_s`` (default:
        to the end); times are not shifted (see :meth:`slice`). Raises :class:`TraceError` when the window does not
        fit in the trace."""
        if not np.isfinite(start_s) or start_s < 0:
            raise TraceError(f"trace {self.name!r}: start must be a finite number of seconds >= 0, got {start_s!r}")
        if duration_s is not None and (not np.isfinite(duration_s) or duration_s <= 0):
            raise TraceError(f"trace {self.name!r}: duration must be > 0 s, got {duration_s!r}")
        end = self.duration if duration_s is None else start_s + duration_s
        if end > self.duration + 1e-9 or start_s >= self.duration:
            raise TraceError(f"trace {self.name!r} lasts {self.duration:.2f} s; a window from {start_s:g} s"
                             + (f" lasting {duration_s:g} s" if duration_s is not None else "") + " does not fit")
        t0 = float(self.times[0])
        return self.slice(t0 + start_s, t0 + min(end, self.duration))

    def anchored(self, position, yaw_deg: float | None = None, at_s: float = 0.0) -> Trace:
        """The trace moved rigidly into another scene: its motion relative to its pose ``at_s`` seconds after its
        first sample is kept, and that pose goes to ``position`` (3,) facing heading ``yaw_deg`` (degrees, as trace
        yaw; the whole trace turns about +Y by the difference to that pose's heading). ``yaw_deg=None`` keeps the
        headings: a pure translation."""
        anchor = Anchor(tuple(np.asarray(position, dtype=np.float64).reshape(-1)), yaw_deg)
        if not np.isfinite(at_s) or not 0 <= at_s <= self.duration + 1e-9:
            raise TraceError(f"trace {self.name!r}: anchor time {at_s!r} s is outside its {self.duration:.2f} s")
        p_ref, q_ref = self.pose_at(float(self.times[0]) + at_s)
        turn_deg = 0.0 if anchor.yaw_deg is None else anchor.yaw_deg - heading_deg(Rotation.from_quat(q_ref))
        turn = Rotation.from_euler("y", turn_deg, degrees=True)
        positions = np.asarray(anchor.position) + turn.apply(self.positions - p_ref)
        quats = (turn * self.rotations).as_quat()
        euler = _euler_near(quats, self.euler_deg + [0.0, turn_deg, 0.0])
        return Trace(f"{self.name}@{anchor}", self.times.copy(), positions, euler)

    def fastest_window(self, duration_s: float) -> float:
        """Start (seconds after the first sample) of the ``duration_s`` window with the most apparent motion: the
        sum over its samples of the turn (radians) plus the move (metres) / :data:`APPARENT_DEPTH_M`. The window
        starts at a sample; a trace exactly ``duration_s`` long gives 0, a shorter one is a :class:`TraceError`."""
        if not np.isfinite(duration_s) or duration_s <= 0:
            raise TraceError(f"trace {self.name!r}: window duration must be > 0 s, got {duration_s!r}")
        if duration_s >= self.duration - 1e-9:
            if duration_s > self.duration + 1e-9:
                raise TraceError(f"trace {self.name!r} lasts {self.duration:.2f} s, shorter than a "
                                 f"{duration_s:g} s window")
            return 0.0
        rotations = self.rotations
        turn = (rotations[1:] * rotations[:-1].inv()).magnitude()
        move = np.linalg.norm(np.diff(self.positions, axis=0), axis=1)
        motion = np.concatenate([[0.0], np.cumsum(turn + move / APPARENT_DEPTH_M)])
        starts = self.times[self.times + duration_s <= self.times[-1] + 1e-9]
        ends = np.searchsorted(self.times, starts + duration_s - 1e-9)
        amount = motion[ends] - motion[: len(starts)]
        return float(starts[int(np.argmax(amount))] - self.times[0])

    # ------------------------------------------------------------------ stats
    def speed(self) -> TraceSpeed:
        """Statistics of the camera's linear speed (m/s); all zero for a single-sample trace."""
        if len(self) < 2:
            return TraceSpeed(0.0, 0.0, 0.0, 0.0, 0.0)
        segment_lengths = np.linalg.norm(np.diff(self.positions, axis=0), axis=1)
        segment_speeds = segment_lengths / np.diff(self.times)
        path_length = float(segment_lengths.sum())
        return TraceSpeed(
            mean=path_length / self.duration,
            median=float(np.median(segment_speeds)),
            p95=float(np.percentile(segment_speeds, 95)),
            max=float(segment_speeds.max()),
            path_length=path_length,
        )

    # --------------------------------------------------------------------- io
    def to_text(self, time_decimals: int = 3, header: bool = True) -> str:
        """The trace in QUASAR's format (``x y z pitch yaw roll t_ms`` per line).

        ``time_decimals=0`` writes integer milliseconds, which is what QUASAR's
        own loader reads; the default keeps sub-millisecond times so 60 Hz
        traces round-trip. With ``header`` a ``#`` comment line names the trace.
        """
        if time_decimals < 0:
            raise TraceError(f"time_decimals must be >= 0, got {time_decimals}")
        t_ms = self.times * 1000.0
        if time_decimals == 0:
            t_ms = np.round(t_ms)
        lines = [f"# quadcast trace {self.name}: x y z pitch yaw roll t_ms"] if header else []
        for (x, y, z), (pitch, yaw, roll), t in zip(self.positions, self.euler_deg, t_ms):
            lines.append(
                f"{x:.6f} {y:.6f} {z:.6f} {pitch:.6f} {yaw:.6f} {roll:.6f} {t:.{time_decimals}f}"
            )
        return "\n".join(lines) + "\n"

    def save(self, path: str | Path, time_decimals: int = 3) -> None:
        """Write :meth:`to_text` to ``path``."""
        Path(path).write_text(self.to_text(time_decimals=time_decimals))


# ---------------------------------------------------------------------- parsing
def _finite(token: str, what: str) -> float:
    """``token`` as a finite float; otherwise a :class:`TraceError` saying ``what`` is not a (finite) number."""
    try:
        value = float(token)
    except ValueError:
        raise TraceError(f"{what} is not a number: {token!r}") from None
    if not np.isfinite(value):
        raise TraceError(f"{what} is not finite: {token!r}")
    return value


def parse_trace(text: str, name: str = "<text>") -> Trace:
    """Parse QUASAR trace text (``x y z pitch yaw roll t_ms`` per line) into a :class:`Trace`.

    Blank lines and lines starting with ``#`` are skipped. Any bad line raises
    :class:`TraceError` naming ``name``, the 1-based line number and the problem.
    """
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    for line_number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        fields = stripped.split()
        if len(fields) != FIELDS_PER_LINE:
            raise TraceError(
                f"{name}:{line_number}: expected {FIELDS_PER_LINE} fields "
                f"(x y z pitch yaw roll t_ms), got {len(fields)}: {stripped!r}"
            )
        values = [_finite(token, f"{name}:{line_number}: {column}")
                  for column, token in zip(("x", "y", "z", "pitch", "yaw", "roll", "t_ms"), fields)]
        if rows and values[6] <= rows[-1][6]:
            raise TraceError(
                f"{name}:{line_number}: time {values[6]:g} ms is not after the previous "
                f"line's {rows[-1][6]:g} ms (line {line_numbers[-1]}); times must strictly increase"
            )
        rows.append(values)
        line_numbers.append(line_number)
    if not rows:
        raise TraceError(f"{name}: trace has no poses (only blank or comment lines)")
    data = np.asarray(rows, dtype=np.float64)
    return Trace(name=name, times=data[:, 6] / 1000.0, positions=data[:, :3], euler_deg=data[:, 3:6])


def load_trace(path: str | Path) -> Trace:
    """Read a QUASAR trace file; the trace is named after the path."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise TraceError(f"trace file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TraceError(f"cannot read trace file {path}: {exc}") from exc
    return parse_trace(text, name=str(path))


# --------------------------------------------------------------------- built-ins
def _uniform_times(duration_s: float, hz: float = TRACE_HZ) -> np.ndarray:
    count = int(round(duration_s * hz)) + 1
    return np.arange(count, dtype=np.float64) / hz


def _superellipse(phi: np.ndarray, half_x: float, half_z: float, exponent: float) -> np.ndarray:
    """Points (M, 2) as (x, z) on ``|x/a|^n + |z/b|^n = 1``; phi = 0 is (0, b), increasing towards +X."""
    s, c = np.sin(phi), np.cos(phi)
    x = half_x * np.sign(s) * np.abs(s) ** (2.0 / exponent)
    z = half_z * np.sign(c) * np.abs(c) ** (2.0 / exponent)
    return np.stack([x, z], axis=1)


def _walk() -> Trace:
    """A person walking once around the courtyard fountain, looking about.

    Path: superellipse (|x/5|^3.5 + |z/6|^3.5 = 1) so it stays within
    |x| <= 5, |z| <= 6 and at least 5 m from the fountain at the origin; it
    starts at (0, 1.6, 6) heading +X with the head turned left towards the
    fountain (-Z-ish). Speed varies smoothly around 1.4 m/s; eye height bobs
    with the steps; the head yaws within -40..+60° around the walking direction and
    pitches about -10..+6°.
    """
    # Dense arclength table of the loop.
    phi = np.linspace(0.0, 2.0 * np.pi, 20001)
    loop = _superellipse(phi, 5.0, 6.0, 3.5)
    arclength = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(loop, axis=0), axis=1))])
    perimeter = float(arclength[-1])

    # Speed profile: mean 1.4 m/s with slow surges; scaled so one loop fits exactly.
    base_speed = 1.4
    duration = round(perimeter / base_speed * TRACE_HZ) / TRACE_HZ
    times = _uniform_times(duration)
    speed = 1.0 + 0.12 * np.sin(2.0 * np.pi * times / 9.0) + 0.05 * np.sin(2.0 * np.pi * times / 3.7 + 1.0)
    distance = cumulative_trapezoid(speed, times, initial=0.0)
    distance *= perimeter / distance[-1]
    ground = np.stack([np.interp(distance, arclength, loop[:, k]) for k in range(2)], axis=1)

    step_hz = 1.9  # steps per second; the eye bobs once per step
    eye_height = 1.6 + 0.02 * np.sin(2.0 * np.pi * step_hz * times)
    positions = np.stack([ground[:, 0], eye_height, ground[:, 1]], axis=1)

    # Walking direction from the path tangent.
    tangent = np.gradient(ground, times, axis=0)
    walk_yaw = np.unwrap(np.arctan2(-tangent[:, 0], -tangent[:, 1]), period=2.0 * np.pi)
    # Starts at +57° (turned left, towards the fountain); stays within -40..+60°.
    head_yaw = 10.0 + 47.0 * np.cos(2.0 * np.pi * times / 7.0) + 3.0 * np.sin(2.0 * np.pi * times / 2.3)
    yaw = np.degrees(walk_yaw) + head_yaw
    pitch = -2.0 + 8.0 * np.sin(2.0 * np.pi * times / 5.3 + 0.3)
    roll = 1.0 * np.sin(np.pi * step_hz * times)  # slight sway, once per stride
    return Trace("builtin:walk", times, positions, np.stack([pitch, yaw, roll], axis=1))


def _orbit() -> Trace:
    """One revolution in 10 s on a circle of radius 5.5 m at 1.8 m height, looking at (0, 1, 0)."""
    times = _uniform_times(10.0)
    angle = 2.0 * np.pi * times / 10.0
    positions = np.stack([5.5 * np.sin(angle), np.full_like(angle, 1.8), 5.5 * np.cos(angle)], axis=1)
    return Trace("builtin:orbit", times, positions, look_at_euler(positions, [0.0, 1.0, 0.0]))


def _static() -> Trace:
    """3 s standing still at (0, 1.6, 6) looking down -Z."""
    times = _uniform_times(3.0)
    positions = np.tile([0.0, 1.6, 6.0], (times.size, 1))
    return Trace("builtin:static", times, positions, np.zeros((times.size, 3)))


def _strafe() -> Trace:
    """4 s moving sideways along +X at 1 m/s from (-2, 1.6, 6), looking down -Z."""
    times = _uniform_times(4.0)
    positions = np.stack([-2.0 + times, np.full_like(times, 1.6), np.full_like(times, 6.0)], axis=1)
    return Trace("builtin:strafe", times, positions, np.zeros((times.size, 3)))


def scene_tour(bounds: np.ndarray, duration_s: float = 10.0, speed_mps: float = 1.0, eye_height: float = 1.6,
               name: str = "tour", centre: tuple[float, float] | None = None, radius: float | None = None) -> Trace:
    """A walk for any scene: a circle at `speed_mps` around `centre` (x, z; default the centre of `bounds`, a
    (2, 3) box, y up) of `radius` (default a quarter of the smaller horizontal side), at `eye_height` above the
    bounds' floor, looking ahead along the circle -- so the view sweeps across the scene. For benchmarks on scenes
    without a trace of their own."""
    bounds = np.asarray(bounds, dtype=np.float64)
    if bounds.shape != (2, 3) or not np.all(np.isfinite(bounds)) or np.any(bounds[1] < bounds[0]):
        raise TraceError(f"scene_tour: bounds must be a finite (2, 3) [min, max] box, got {bounds!r}")
    lo, hi = bounds
    mid = (lo + hi) / 2
    centre = np.array([mid[0], mid[1], mid[2]] if centre is None else [centre[0], mid[1], centre[1]], np.float64)
    radius = max(0.25 * min(hi[0] - lo[0], hi[2] - lo[2]), 0.5) if radius is None else float(radius)
    if radius <= 0:
        raise TraceError(f"scene_tour: radius must be > 0, got {radius}")
    times = _uniform_times(duration_s)
    angle = speed_mps * times / radius
    y = lo[1] + eye_height
    positions = np.stack([centre[0] + radius * np.sin(angle), np.full_like(angle, y),
                          centre[2] + radius * np.cos(angle)], axis=1)
    # Look tangentially-inward: at a point ahead on the circle, so the camera faces along its path.
    ahead = np.stack([centre[0] + radius * np.sin(angle + 1.2), np.full_like(angle, y - 0.2),
                      centre[2] + radius * np.cos(angle + 1.2)], axis=1)
    return Trace(name, times, positions, look_at_euler(positions, ahead))


_BUILTIN_MAKERS: dict[str, Callable[[], Trace]] = {
    "walk": _walk,
    "orbit": _orbit,
    "static": _static,
    "strafe": _strafe,
}

#: Names of the built-in traces (use as ``"builtin:NAME"``).
BUILTIN_TRACES: list[str] = list(_BUILTIN_MAKERS)


def builtin_trace(name: str) -> Trace:
    """The built-in trace ``name`` (one of :data:`BUILTIN_TRACES`), freshly generated."""
    try:
        maker = _BUILTIN_MAKERS[name]
    except KeyError:
        raise TraceError(
            f"unknown built-in trace {name!r}; valid names: "
            + ", ".join(f"builtin:{n}" for n in BUILTIN_TRACES)
        ) from None
    return maker()


def resolve_trace(spec: str) -> Trace:
    """A trace from ``"builtin:NAME"`` or a path to a QUASAR trace file."""
    if not isinstance(spec, (str, Path)) or not str(spec).strip():
        raise TraceError(f"trace spec must be 'builtin:NAME' or a file path, got {spec!r}")
    spec = str(spec)
    if spec.startswith("builtin:"):
        return builtin_trace(spec[len("builtin:"):])
    return load_trace(spec)
