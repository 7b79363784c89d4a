"""Rate adaptation, sans-I/O: operating points, the measured ladder of them, and the server's rate controller.

An :class:`OperatingPoint` is one setting of every knob the QUASAR server can turn while it streams -- H.264 CRF,
quad merge thresholds (a scale on delta_sim / delta_flatten, coarse passes), view-cell radius, how many hidden
layers are sent, the reference interval, and foveation (merge thresholds and atlas resolution that grow with
eccentricity from the gaze point, after the gaze-driven multi-resolution paper: sensitivity
S(e) = exp(-max(0, e - r0)^2 / 2 sigma^2), and a quad threshold / atlas pixel size scaled by S^-gamma, capped).
Every knob keeps the atlas size, so switching points never changes the video's picture size.

The :class:`Ladder` holds the Pareto fronts of (Mbps, FLIP) over such points, one per frame rate floor
(:func:`ladder_points`), *measured* by ``quadcast bench ladder`` (virtual-time replay on real head traces) and
stored in ``protocol/ladder.json`` with the command that made it.

The :class:`RateController` runs inside the server's session core (:class:`quadcast.protocol.session.ServerSession`),
so the virtual-time replay and the live server drive the same code. Its inputs are the frames the server sent
(id, bytes, when) and the client's receive reports (id, bytes, when the last byte arrived, on the client's clock).
Like WebRTC's delay-based congestion control it looks at one-way delay, not loss:

- **queueing delay**: each frame's one-way delay (client arrival minus server send; the unknown clock offset
  cancels) minus the smallest one seen in the last ``base_window_s``; and its **gradient** over the last
  ``trend_frames`` frames (a least-squares slope of delay against send time: a link sent k times its capacity
  queues k - 1 seconds per second);
- **overuse** when the recent queueing delay (the mean of the last three frames') exceeds ``overuse_delay_s`` (or
  more on a link that jitters more), or the last frame's alone exceeds twice that, or half of it while the
  gradient exceeds ``overuse_trend``;
- **capacity** from the frames that waited behind the one before them at the bottleneck (their arrival spacing is
  the link's serialization; frames the pacing spaced out are not used), or from what the link delivered while
  frames arrived late, whichever is lower (the delay's jitter can shorten a run's span; a late frame may be late
  for its own serialization alone, so the delivered rate errs low).

Decisions ("best" is the lowest measured FLIP): the session starts at the best point of at least ``start_fps``
whose measured rate fits ``start_mbps``, and every ``hold_up_s`` / 4 while nothing queues it moves to the best
point of up to twice its rate (a slow start), until the first overuse. On overuse, at once, the best point whose
predicted rate fits ``backoff`` x capacity (at the first sign of a growing queue, before any frame has queued
behind another: the delivered rate, or half the current rate without one; then again with each frame that did,
never above where the queueing began; a
step up that failed
goes back to where it came from) and whose frames would be fresh:
a frame is, on average, its serialization at the link's capacity plus half its frame interval older than the
latency, and that must stay within ``max_age_s`` (so a slow link gets fewer bits per frame, not fewer frames of
many bits, as long as the ladder allows). After ``hold_up_s`` of no overuse and no queue, up to the best fresh
point that fits the ceiling (``target_mbps``) and a headroom that starts at the last measured capacity (or the
rate of the last point that ran ``hold_up_s`` without overuse, if higher) and grows by ``probe_growth`` per
second (hysteresis: a rate that just failed is not tried again at once). Above the ladder, given ``own`` (the server's
own settings, :func:`own_point`: what it sends without adaptation, finer than any point the ladder measured): after
``own_hold_s`` at the ladder's best point with no change and no overuse, up to them if they fit that limit (their rate,
until seen, ``own_guess`` times the best point's); any overuse there goes back down the ladder as above. A point's rate
is predicted from the bytes per frame observed at it
over its reference cycle (self-contained and residual frames apart: a new CRF restarts the stream, so the first
frame at a point is a large self-contained one) or, until it has been used, from the nearest observed point scaled
by the ladder's measured ratio, times the frame rate. Frames are also *paced*: while the bytes sent and not yet reported exceed what the link holds in one
round trip plus ``queue_target_s`` of queue, no new frame starts (:meth:`RateController.may_start`), so a backlog
drains instead of being fed frames that would be stale when they arrive; and frames held back again and again
(three frames within ``ack_window_s``, each counted once however often it was asked for) while the link queues (half
the overuse threshold) and what was reported over that window is under ``backoff`` x what the point makes at the
session's frame interval mean the point sends more than the link carries even though the pacing keeps the delay
under the threshold: the point then goes down to what was reported. (A server slower than the link makes less than
its point allows, and its reports measure the server, not the link.) Without receive reports
nothing is paced and the point only follows the ceiling.
"""
from __future__ import annotations

import collections
import json
import math
from dataclasses import asdict, dataclass, fields, replace
from importlib import resources
from pathlib import Path

import numpy as np

from quadcast.protocol.methods import method_crf

__all__ = ["OperatingPoint", "Ladder", "LadderError", "pareto_front", "ladder_points", "load_ladder", "resolve_point",
           "RateConfig", "RateController", "RateState", "fovea_scale", "own_point", "session_rate", "LADDER_FILE",
           "OWN_POINT"]

LADDER_FILE = "ladder.json"
"""The measured ladder, beside this module (``quadcast bench ladder --write`` rewrites it)."""


class LadderError(ValueError):
    """An operating point or a ladder is malformed."""


def fovea_scale(ecc_deg, fovea_deg: float, sigma_deg: float, gamma: float, max_scale: float):
    """How much coarser than at the gaze point things may be at eccentricity ``ecc_deg`` (degrees; scalar or
    array): S^-gamma for the sensitivity S(e) = exp(-max(0, e - fovea_deg)^2 / (2 sigma^2)), capped at
    ``max_scale``; 1 everywhere when ``sigma_deg`` is 0 (uniform). The server's shaders compute the same
    (server/fovea.glsl)."""
    e = np.maximum(np.asarray(ecc_deg, np.float64) - fovea_deg, 0.0)
    if sigma_deg <= 0:
        return np.ones_like(e)
    return np.minimum(np.exp(gamma * e * e / (2.0 * sigma_deg * sigma_deg)), max_scale)


@dataclass(frozen=True)
class OperatingPoint:
    """One setting of the server's knobs (see the module docstring) and, for ladder points, what it measured.

    ``quad_scale`` multiplies delta_sim and delta_flatten of every layer (the hidden and wide layers keep their
    10x relaxation on top); ``coarse_passes`` is the visible layer's (hidden/wide: one more); ``hidden_layers``
    of the server's hidden layers are sent (the others' atlas space stays black); ``fovea_sigma_deg`` 0 is
    uniform, otherwise merge thresholds (and, with ``fovea_atlas`` > 1, the atlas pixel size, up to that factor)
    grow with eccentricity beyond ``fovea_deg``."""

    name: str = "default"
    crf: float = 23.0
    quad_scale: float = 1.0
    coarse_passes: int = 3
    viewcell_m: float = 0.5
    hidden_layers: int = 3
    reference_every: int = 5
    fovea_deg: float = 10.0
    fovea_sigma_deg: float = 0.0
    fovea_gamma: float = 1.0
    fovea_max_scale: float = 8.0
    fovea_atlas: float = 1.0
    fps: float = 30.0                  # the most frames per second the server makes at this point
    mbps: float | None = None          # measured by `quadcast bench ladder` (at the ladder's size and fps)
    flip: float | None = None
    flip_fovea: float | None = None

    def __post_init__(self) -> None:
        def bad(name, what):
            raise LadderError(f"operating point {self.name!r}: {name} {what}, got {getattr(self, name)!r}")
        if not isinstance(self.name, str) or not self.name:
            raise LadderError("operating point: name must be a non-empty string")
        for name in ("crf", "quad_scale", "viewcell_m", "fovea_deg", "fovea_sigma_deg", "fovea_gamma",
                     "fovea_max_scale", "fovea_atlas", "fps"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                bad(name, "must be a finite number")
            object.__setattr__(self, name, float(v))
        for name in ("coarse_passes", "hidden_layers", "reference_every"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) != v:
                bad(name, "must be an integer")
            object.__setattr__(self, name, int(v))
        if not 0 <= self.crf <= 51:
            bad("crf", "must be in [0, 51]")
        if self.quad_scale <= 0:
            bad("quad_scale", "must be > 0")
        if not 0 <= self.coarse_passes <= 12:
            bad("coarse_passes", "must be in 0..12")
        if self.viewcell_m < 0:
            bad("viewcell_m", "must be >= 0")
        if self.hidden_layers < 0:
            bad("hidden_layers", "must be >= 0")
        if self.reference_every < 1:
            bad("reference_every", "must be >= 1")
        if self.fovea_deg < 0 or self.fovea_sigma_deg < 0 or self.fovea_gamma < 0:
            bad("fovea_deg" if self.fovea_deg < 0 else "fovea_sigma_deg" if self.fovea_sigma_deg < 0
                else "fovea_gamma", "must be >= 0")
        if self.fovea_max_scale < 1:
            bad("fovea_max_scale", "must be >= 1")
        if not 1 <= self.fovea_atlas <= 8:
            bad("fovea_atlas", "must be in [1, 8]")
        if not 0.5 <= self.fps <= 240:
            bad("fps", "must be in [0.5, 240]")
        for name in ("mbps", "flip", "flip_fovea"):
            v = getattr(self, name)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)
                                  or v < 0):
                bad(name, "must be a finite number >= 0 or null")

    @property
    def foveated(self) -> bool:
        return self.fovea_sigma_deg > 0

    def scale_at(self, ecc_deg):
        """The merge-threshold scale at eccentricity ``ecc_deg`` (see :func:`fovea_scale`)."""
        return fovea_scale(ecc_deg, self.fovea_deg, self.fovea_sigma_deg, self.fovea_gamma, self.fovea_max_scale)

    def knobs(self) -> dict:
        """The settings without the name and the measured figures."""
        return {k: v for k, v in asdict(self).items() if k not in ("name", "mbps", "flip", "flip_fovea")}

    def same_settings(self, other: "OperatingPoint") -> bool:
        return self.knobs() == other.knobs()

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "operating point") -> "OperatingPoint":
        if not isinstance(d, dict):
            raise LadderError(f"{where}: expected an object, got {type(d).__name__}")
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise LadderError(f"{where}: unknown field(s) {', '.join(unknown)}; fields are {', '.join(sorted(known))}")
        return cls(**d)

    _SHORT = {"crf": "crf", "quad": "quad_scale", "coarse": "coarse_passes", "viewcell": "viewcell_m",
              "hidden": "hidden_layers", "every": "reference_every", "fovea": "fovea_deg",
              "sigma": "fovea_sigma_deg", "gamma": "fovea_gamma", "max": "fovea_max_scale", "atlas": "fovea_atlas",
              "fps": "fps"}

    @classmethod
    def parse(cls, spec: str, base: "OperatingPoint | None" = None) -> "OperatingPoint":
        """``key=value,...`` over ``base`` (default: the defaults): keys crf, quad, coarse, viewcell, hidden,
        every, fovea, sigma, gamma, max, atlas, fps (or the field names)."""
        base = base or cls()
        values: dict = {}
        for part in (p.strip() for p in str(spec).split(",")):
            if not part:
                continue
            key, sep, value = part.partition("=")
            name = cls._SHORT.get(key.strip(), key.strip())
            if not sep or name not in {f.name for f in fields(cls)} - {"name", "mbps", "flip", "flip_fovea"}:
                raise LadderError(f"operating point {spec!r}: expected key=value with keys "
                                  f"{', '.join(cls._SHORT)}, got {part!r}")
            try:
                values[name] = int(value) if name in ("coarse_passes", "hidden_layers", "reference_every") \
                    else float(value)
            except ValueError:
                raise LadderError(f"operating point {spec!r}: {key} needs a number, got {value!r}") from None
        return replace(base, name=spec, mbps=None, flip=None, flip_fovea=None, **values)


def pareto_front(points: list[OperatingPoint]) -> list[OperatingPoint]:
    """The points no other point beats on both Mbps and FLIP (lower is better for both), by rising Mbps."""
    measured = sorted((p for p in points if p.mbps is not None and p.flip is not None),
                      key=lambda p: (p.mbps, p.flip))
    front: list[OperatingPoint] = []
    for p in measured:
        if not front or p.flip < front[-1].flip:
            front.append(p)
    return front


def ladder_points(points: list[OperatingPoint]) -> list[OperatingPoint]:
    """The ladder's points: for every frame rate measured, the Pareto front of the points at that rate or
    faster, together, by rising Mbps. (The front of all points alone favours low frame rates, whose FLIP without a
    rate limit hides that on a slow link each of their frames takes long to cross it; the controller weighs that
    itself, see :meth:`RateController.expected_age_s`, and needs the best points of each frame rate to choose
    from.)"""
    chosen: dict[str, OperatingPoint] = {}
    for floor in sorted({p.fps for p in points}):
        for p in pareto_front([q for q in points if q.fps >= floor]):
            chosen[p.name] = p
    out: list[OperatingPoint] = []
    for p in sorted(chosen.values(), key=lambda p: (p.mbps, p.flip)):
        if not out or p.mbps > out[-1].mbps:
            out.append(p)
    return out


@dataclass(frozen=True)
class Ladder:
    """Operating points by rising measured Mbps (lowest first), with where the figures came from."""

    points: tuple[OperatingPoint, ...]
    size: tuple[int, int] = (640, 360)
    fps: float = 30.0
    command: str = ""
    note: str = ""

    def __post_init__(self) -> None:
        pts = tuple(self.points)
        if not pts:
            raise LadderError("ladder: no operating points")
        names = [p.name for p in pts]
        if len(set(names)) != len(names):
            raise LadderError(f"ladder: duplicate point names {sorted({n for n in names if names.count(n) > 1})}")
        if any(p.mbps is None or p.mbps <= 0 for p in pts):
            raise LadderError(f"ladder: every point needs a measured mbps > 0 "
                              f"({', '.join(p.name for p in pts if p.mbps is None or p.mbps <= 0)} has none)")
        if any(b.mbps <= a.mbps for a, b in zip(pts, pts[1:])):
            raise LadderError("ladder: points must be ordered by strictly rising mbps")
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "size", tuple(int(v) for v in self.size))

    def __len__(self) -> int:
        return len(self.points)

    def __getitem__(self, i: int) -> OperatingPoint:
        return self.points[i]

    def index(self, name: str) -> int:
        for i, p in enumerate(self.points):
            if p.name == name:
                return i
        raise LadderError(f"ladder: no point named {name!r}; points are {', '.join(p.name for p in self.points)}")

    def to_json(self) -> str:
        return json.dumps({"command": self.command, "note": self.note, "size": list(self.size), "fps": self.fps,
                           "points": [p.to_dict() for p in self.points]}, indent=1) + "\n"

    @classmethod
    def from_json(cls, text: str, where: str = "ladder") -> "Ladder":
        try:
            d = json.loads(text)
        except json.JSONDecodeError as exc:
            raise LadderError(f"{where}: not JSON ({exc})") from None
        if not isinstance(d, dict) or not isinstance(d.get("points"), list):
            raise LadderError(f"{where}: expected an object with a 'points' list")
        points = tuple(OperatingPoint.from_dict(p, f"{where} point {i}") for i, p in enumerate(d["points"]))
        try:
            return cls(points, tuple(d.get("size", (640, 360))), float(d.get("fps", 30.0)),
                       str(d.get("command", "")), str(d.get("note", "")))
        except (TypeError, ValueError) as exc:
            raise LadderError(f"{where}: {exc}") from None


def load_ladder(path: str | Path | None = None) -> Ladder:
    """The ladder in ``path``, or the measured one shipped beside this module."""
    if path is None:
        text = resources.files("quadcast.protocol").joinpath(LADDER_FILE).read_text()
        return Ladder.from_json(text, f"protocol/{LADDER_FILE}")
    try:
        text = Path(path).read_text()
    except OSError as exc:
        raise LadderError(f"ladder {str(path)!r}: {exc.strerror or exc}") from None
    return Ladder.from_json(text, str(path))


def resolve_point(spec: "str | OperatingPoint", ladder: Ladder | None = None) -> OperatingPoint:
    """An operating point: as given, ``key=value,...`` (:meth:`OperatingPoint.parse`), or a point of ``ladder`` (the
    shipped one if None) by name. ValueError / LadderError name what is wrong."""
    if isinstance(spec, OperatingPoint):
        return spec
    if "=" in spec:
        return OperatingPoint.parse(spec)
    ladder = ladder if ladder is not None else load_ladder()
    return ladder[ladder.index(spec)]


# ------------------------------------------------------------------------------------------------ controller

def _run_start(flags: list[bool], end: int) -> int:
    """The first index of the run of true ``flags`` that ends at ``end`` (``flags[end]`` is true)."""
    start = end
    while start > 0 and flags[start - 1]:
        start -= 1
    return start


@dataclass(frozen=True)
class RateConfig:
    """The controller's ladder, ceiling and constants (see the module docstring)."""

    ladder: Ladder
    target_mbps: float | None = None
    start: int | None = None              # first point (default: the best whose measured rate fits start_mbps)
    start_mbps: float = 6.0               # ... a rate in the ladder's own terms (its size and fps), under the ceiling
    start_fps: float = 15.0               # ... and of at least this frame rate when there is one
    overuse_delay_s: float = 0.045
    overuse_trend: float = 0.3
    trend_frames: int = 6
    backoff: float = 0.85
    hold_up_s: float = 0.5
    probe_growth: float = 1.4
    queue_target_s: float = 0.06
    initial_frames: int = 4               # frames in flight before the first report
    max_age_s: float | None = 0.10         # how much older than the latency frames may be (see expected_age_s)
    ack_window_s: float = 0.5
    base_window_s: float = 10.0
    lost_after_s: float = 2.0
    ema: float = 0.3
    own: OperatingPoint | None = None     # the server's own settings (:func:`own_point`), above the ladder
    own_hold_s: float = 2.0               # ... entered only after this long at the ladder's best point, calm
    own_guess: float = 1.5                # ... its rate, until seen: this times the ladder's best point's

    def __post_init__(self) -> None:
        if not isinstance(self.ladder, Ladder):
            raise ValueError(f"RateConfig.ladder: expected a Ladder, got {type(self.ladder).__name__}")
        if self.target_mbps is not None and not (math.isfinite(self.target_mbps) and self.target_mbps > 0):
            raise ValueError(f"--target-mbps: expected a number > 0, got {self.target_mbps!r}")
        if self.start is not None and not 0 <= self.start < len(self.ladder):
            raise ValueError(f"RateConfig.start: expected 0..{len(self.ladder) - 1}, got {self.start}")
        for name in ("overuse_delay_s", "overuse_trend", "hold_up_s", "queue_target_s", "base_window_s",
                     "lost_after_s", "start_mbps", "own_hold_s", "own_guess"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"RateConfig.{name}: expected a number > 0, got {v!r}")
        if not 0 < self.backoff < 1 or not self.probe_growth >= 1 or not 0 < self.ema <= 1:
            raise ValueError("RateConfig: backoff must be in (0, 1), probe_growth >= 1, ema in (0, 1]")
        if self.max_age_s is not None and not (math.isfinite(self.max_age_s) and self.max_age_s > 0):
            raise ValueError(f"RateConfig.max_age_s: expected a number > 0 or None, got {self.max_age_s!r}")
        if self.initial_frames < 1:
            raise ValueError(f"RateConfig.initial_frames: expected >= 1, got {self.initial_frames}")
        if self.trend_frames < 3:
            raise ValueError(f"RateConfig.trend_frames: expected >= 3, got {self.trend_frames}")
        if self.own is not None and not isinstance(self.own, OperatingPoint):
            raise ValueError(f"RateConfig.own: expected an OperatingPoint or None, got {type(self.own).__name__}")
        if self.own is not None and any(p.name == self.own.name for p in self.ladder.points):
            raise ValueError(f"RateConfig.own: the ladder already has a point named {self.own.name!r}")

    @property
    def points(self) -> tuple[OperatingPoint, ...]:
        """Every point the controller may choose, by index: the ladder's, then the server's own settings if given."""
        return self.ladder.points + ((self.own,) if self.own is not None else ())


OWN_POINT = "own"
"""The name of the server's own settings as an operating point (:func:`own_point`)."""


def own_point(crf: float | None, viewcell_m: float, reference_every: int, fps: float = 30.0) -> OperatingPoint:
    """The QUASAR server's own settings -- what it sends without adaptation (``crf``, None for quasar's default; the
    session's view cell and reference interval; three hidden layers, the merge thresholds and coarse passes as
    configured, uniform) -- as the point :class:`RateController` may go to above its ladder (``RateConfig.own``)."""
    return OperatingPoint(name=OWN_POINT, crf=method_crf("quasar", crf), viewcell_m=viewcell_m,
                          reference_every=reference_every, fps=fps)


def session_rate(ladder: Ladder, target_mbps: float | None, crf: float | None, viewcell_m: float,
                 reference_every: int) -> RateConfig:
    """A session's rate controller settings, live (``quadcast server --adapt``) and replayed (``quadcast eval
    --adapt``) alike: ``ladder`` under the ceiling ``target_mbps``, and above it the server's own settings for the
    session's ``crf`` (None: quasar's default), view cell and reference interval."""
    return RateConfig(ladder, target_mbps, own=own_point(crf, viewcell_m, reference_every, ladder.fps))


@dataclass
class RateState:
    """What the controller believes now (for logs, reports and tests)."""

    index: int
    queue_delay_s: float | None = None
    trend: float | None = None
    capacity_mbps: float | None = None
    overuse: bool = False
    in_flight_bytes: int = 0
    decreases: int = 0
    increases: int = 0
    frames_paced: int = 0


@dataclass
class _Sample:
    t_sent: float
    t_arrive: float           # client clock
    owd: float                # t_arrive - t_sent (clock offset included)
    size: int
    index: int                # the point it was made at


class RateController:
    """See the module docstring. Times: ``now`` and send times on the server's clock, arrivals on the client's."""

    def __init__(self, config: RateConfig) -> None:
        self.config = c = config
        self.ladder = c.ladder
        self.points = c.points    # the ladder's, then the server's own settings (``own``) if given
        n = len(self.ladder)      # how good each point is: its measured FLIP (unmeasured: the later the better)
        self._flip = [p.flip if p.flip is not None else 1.0 - i / n for i, p in enumerate(self.ladder.points)]
        self._best = min(range(n), key=lambda i: (self._flip[i], -i))     # the ladder's best point
        self.own_index = n if c.own is not None else None
        if c.own is not None:
            self._flip.append(-1.0)            # better than any ladder point: what the server sends unadapted
        self.state = RateState(index=c.start if c.start is not None else self._top_by_ladder())
        self._sent: collections.OrderedDict[int, tuple[float, int, int]] = collections.OrderedDict()
        self._samples: collections.deque[_Sample] = collections.deque()
        self._rtts: collections.deque[tuple[float, float]] = collections.deque()   # (now, rtt)
        self._bytes_res: dict[int, float] = {}      # EMA of a residual frame's bytes observed at each point
        self._bytes_ref: dict[int, float] = {}      # ... and of a self-contained frame's
        self._sent_log: collections.deque[tuple[float, int]] = collections.deque()  # (t, bytes) of the last 1 s
        self._reports = 0
        self._first_sent: float | None = None
        self._last_overuse: float | None = None
        self._last_change = -math.inf
        self._calm: collections.deque[float] = collections.deque(maxlen=120)
        self._headroom: tuple[float, float] | None = None     # (Mbit/s, since when): see headroom_mbps
        self._window = 0.0                          # the slow-start window (bytes), before the first overuse
        self._srtt: float | None = None             # smoothed round trip (send -> report), as TCP's
        self._acks: collections.deque[tuple[float, int]] = collections.deque()     # (report time, bytes)
        self._probe: tuple[int, float] | None = None    # (index before, when) of the last step up past the headroom
        self._calm_index: int | None = None         # the point of the newest frame reported without queueing
        self._episode: list | None = None          # while the link queues: [index it began at, last measurement]
        self._paced: collections.deque[float] = collections.deque()     # when frames were held back
        self._holding = False                       # the frame waiting to start was held back (counted in _paced)

    # -- the ladder and predictions

    @property
    def index(self) -> int:
        return self.state.index

    @property
    def point(self) -> OperatingPoint:
        return self.points[self.state.index]

    def _top_by_ladder(self) -> int:
        """The first point: the best whose *measured* rate fits ``start_mbps`` and the ceiling (nothing is
        observed yet; the controller climbs from there)."""
        t = min(self.config.start_mbps, self.config.target_mbps or math.inf)
        fits = [i for i, p in enumerate(self.ladder.points) if p.mbps <= t]
        fast = [i for i in fits if self.ladder[i].fps >= self.config.start_fps]
        return min(fast or fits, key=lambda i: (self._flip[i], -i)) if fits else 0

    def _nominal_bytes(self, i: int) -> float:
        """Bytes per frame of point ``i`` as the ladder measured it (the server's own settings, which it did not
        measure: ``own_guess`` times its best point's)."""
        if i == self.own_index:
            return self.config.own_guess * self._nominal_bytes(self._best)
        p = self.ladder[i]
        return p.mbps * 1e6 / 8 / min(p.fps, self.ladder.fps)

    def _observed_bytes(self, i: int) -> float | None:
        """Bytes per frame observed at point ``i`` over its reference cycle: one self-contained frame and
        ``reference_every - 1`` residual frames; a kind not yet seen there is estimated from the other with the
        residual/reference ratio seen over all points (None before any frame of point ``i``)."""
        ref, res = self._bytes_ref.get(i), self._bytes_res.get(i)
        if ref is None and res is None:
            return None
        ratio = self._residual_ratio()
        if ref is None:
            ref = res / ratio
        if res is None:
            res = ref * ratio
        n = max(1, self.points[i].reference_every)
        return (ref + (n - 1) * res) / n

    def _residual_ratio(self) -> float:
        """Residual over self-contained frame bytes, from the points where both were seen (0.5 before)."""
        both = [self._bytes_res[k] / self._bytes_ref[k] for k in self._bytes_res if k in self._bytes_ref]
        return float(np.clip(np.median(both), 0.05, 1.0)) if both else 0.5

    def bytes_per_frame(self, i: int) -> float:
        """Predicted bytes per frame at point ``i``: as observed there over its reference cycle, or as observed at
        the nearest point used, scaled by the ladder's ratio of the two (the ladder's own figure until any frame was
        sent); the server's own settings, until seen, ``own_guess`` times the ladder's best point's prediction."""
        own = self._observed_bytes(i)
        if own is not None:
            return own
        if i == self.own_index:
            return self.config.own_guess * self.bytes_per_frame(self._best)
        nominal = self._nominal_bytes(i)
        seen = set(self._bytes_res) | set(self._bytes_ref)
        if seen:
            j = min(seen, key=lambda k: abs(math.log(self._nominal_bytes(k) / nominal)))
            return self._observed_bytes(j) * nominal / self._nominal_bytes(j)
        return nominal

    def predicted_mbps(self, i: int, frame_interval_s: float) -> float:
        """Point ``i``'s rate at the session's frame interval (or its own, longer one)."""
        interval = max(frame_interval_s, 1.0 / self.points[i].fps, 1e-3)
        return self.bytes_per_frame(i) * 8 / interval / 1e6

    def expected_age_s(self, i: int, frame_interval_s: float, capacity_mbps: float) -> float:
        """How much older than the link's latency a frame of point ``i`` is, on average, while it is shown: its
        serialization at ``capacity_mbps`` and half its frame interval."""
        interval = max(frame_interval_s, 1.0 / self.points[i].fps)
        return self.bytes_per_frame(i) * 8 / (capacity_mbps * 1e6) + interval / 2

    def _fresh(self, i: int, frame_interval_s: float, capacity_mbps: float | None) -> bool:
        c = self.config
        return capacity_mbps is None or c.max_age_s is None or \
            self.expected_age_s(i, frame_interval_s, capacity_mbps) <= c.max_age_s

    def _best_fitting(self, mbps: float, frame_interval_s: float, capacity_mbps: float | None = None) -> int:
        """The best point (lowest measured FLIP) whose predicted rate fits ``mbps`` and whose frames are fresh
        enough on a link of ``capacity_mbps`` (``max_age_s``); if none is fresh enough, the freshest that fits halfway
        between ``mbps`` and ``capacity_mbps``; if none fits, the lowest."""
        fits = [i for i in range(len(self.ladder)) if self.predicted_mbps(i, frame_interval_s) <= mbps]
        if not fits:
            return 0
        fresh = [i for i in fits if self._fresh(i, frame_interval_s, capacity_mbps)]
        if fresh:
            return min(fresh, key=lambda i: (self._flip[i], -i))
        if capacity_mbps is not None and capacity_mbps > mbps:
            # nothing fresh fits the target: give up half of its margin below the link for freshness (a low frame
            # rate's frames are old however fast the link is)
            limit = (mbps + capacity_mbps) / 2
            fits = [i for i in range(len(self.ladder)) if self.predicted_mbps(i, frame_interval_s) <= limit]
        return min(fits, key=lambda i: self.expected_age_s(i, frame_interval_s, capacity_mbps))

    # -- events

    def frame_sent(self, now: float, frame_id: int, size_bytes: int, index: int | None = None,
                   self_contained: bool = False) -> None:
        """The server handed frame ``frame_id`` (``size_bytes``, made at point ``index``; a self-contained frame if
        ``self_contained``) to the transport."""
        index = self.state.index if index is None else index
        self._sent[int(frame_id)] = (float(now), int(size_bytes), index)
        if self._first_sent is None:
            self._first_sent = float(now)
        while len(self._sent) > 512:
            self._sent.popitem(last=False)
        self._holding = False                       # (also when it started without asking may_start)
        table = self._bytes_ref if self_contained else self._bytes_res
        prev = table.get(index)
        table[index] = size_bytes if prev is None else (1 - self.config.ema) * prev + self.config.ema * size_bytes
        self._sent_log.append((now, size_bytes))
        while self._sent_log and self._sent_log[0][0] < now - 1.0:
            self._sent_log.popleft()

    def report(self, now: float, entries, frame_interval_s: float) -> None:
        """The client's receive report arrived at ``now``: ``(frame_id, bytes, t_arrive)`` entries."""
        c, st = self.config, self.state
        self._reports += 1
        for frame_id, _size, t_arrive in entries:
            sent = self._sent.pop(int(frame_id), None)
            if sent is None:
                continue
            t_sent, size, index = sent
            self._samples.append(_Sample(t_sent, float(t_arrive), float(t_arrive) - t_sent, size, index))
            self._rtts.append((now, now - t_sent))
            self._srtt = now - t_sent if self._srtt is None else 0.875 * self._srtt + 0.125 * (now - t_sent)
            self._acks.append((now, size))
        if not self._samples:
            return
        last = self._samples[-1].t_arrive
        while self._samples and self._samples[0].t_arrive < last - c.base_window_s:
            self._samples.popleft()
        while self._rtts and self._rtts[0][0] < now - c.base_window_s:
            self._rtts.popleft()
        base = self._base_owd()
        recent = list(self._samples)[-c.trend_frames:]
        queue = [s.owd - base for s in recent]
        st.queue_delay_s = float(np.mean(queue[-3:]))
        st.trend = None
        if len(recent) >= 3 and recent[-1].t_sent - recent[0].t_sent > 1e-3:
            st.trend = float(np.polyfit([s.t_sent for s in recent], [s.owd for s in recent], 1)[0])
        capacity, newest = self._capacity_mbps()
        threshold = self.overuse_threshold_s
        queued = queue[-1] > threshold / 2
        if not queued:
            self._calm_index = self._samples[-1].index
        # fewer frames give a noisier gradient: its threshold rises as trend_frames / n
        trend_threshold = c.overuse_trend * c.trend_frames / len(recent)
        st.overuse = (st.queue_delay_s > threshold or queue[-1] > 2 * threshold
                      or (st.trend is not None and st.trend > trend_threshold and st.queue_delay_s > threshold / 2))
        if not st.overuse:
            self._episode = None
            self._calm.append(queue[-1])           # the delay's spread when the link does not queue: its jitter
            if not queued:
                self._window = max(self._window, c.initial_frames * self.bytes_per_frame(st.index)) + recent[-1].size
            return
        interval = frame_interval_s
        if self._episode is None:                  # the link began to queue: where it was, what is known so far
            self._episode = [st.index, None]
        self._last_overuse = now
        if capacity is not None:
            delivered = self._delivery_mbps()        # jitter may shorten a run's span; what was delivered may not
            if delivered is not None:
                capacity = min(capacity, delivered)
            st.capacity_mbps = capacity
            self._headroom = (capacity, now)
            if newest == self._episode[1]:
                return                             # one decision per new frame that queued: its spacing is news
            target = c.backoff * capacity
        elif self._episode[1] is None and st.trend is not None and st.trend > trend_threshold:
            # the first sign, a queue that grows but no spacing to measure yet: what the link delivered while the
            # frames queued, or, without that either, half the rate
            capacity = self._delivery_mbps()
            if capacity is not None:
                target = c.backoff * capacity
                st.capacity_mbps = capacity
            else:
                target = capacity = 0.5 * self.predicted_mbps(st.index, interval)
            self._headroom = (capacity, now)       # (the freshness of what is chosen and the pacing go by it)
        else:
            return
        self._episode[1] = newest if newest is not None else -math.inf   # (-inf: decided on the trend alone)
        if c.target_mbps is not None:
            target = min(target, c.target_mbps)
        new = self._best_fitting(target, interval, capacity)
        if self._probe is not None and now - self._probe[1] < 3 * c.hold_up_s \
                and self._flip[self._probe[0]] < self._flip[new]:
            new = self._probe[0]                    # a probe that failed: back to where it came from
        self._probe = None
        # within an episode a better measurement may also move up again, never above where it began
        if new != st.index and self.predicted_mbps(new, interval) <= self.predicted_mbps(self._episode[0], interval):
            if self.predicted_mbps(new, interval) < self.predicted_mbps(st.index, interval):
                st.decreases += 1
            st.index = new
            self._last_change = now

    def _base_owd(self) -> float:
        """The smallest one-way delay in the window: the clock offset, the propagation and a frame's crossing."""
        return min(s.owd for s in self._samples)

    @property
    def overuse_threshold_s(self) -> float:
        """The queueing delay that means overuse: ``overuse_delay_s``, or more on a link whose delay jitters more
        (the 90th percentile of the delay above the base while the link did not queue, plus 10 ms)."""
        if len(self._calm) < 10:
            return self.config.overuse_delay_s
        return max(self.config.overuse_delay_s, float(np.percentile(self._calm, 90)) + 0.01)

    def _capacity_mbps(self) -> tuple[float | None, float | None]:
        """The link's rate from the newest run of frames that each waited behind the one before at the bottleneck
        (sent before the one before would have arrived had nothing queued: their arrival spacing is the link's
        serialization), within the last ``2 * trend_frames`` frames, and the send time of the run's newest frame
        (which tells a new measurement from the last one: once the run fills the window, its length stays the
        same); (None, None) without a run of at least two such frames.
        Frames the pacing spaced out tell nothing about the link and are not used."""
        recent = list(self._samples)[-2 * self.config.trend_frames:]
        base = self._base_owd()
        margin = self.overuse_threshold_s / 2          # the delay's jitter must not make a pair look queued
        # y waited if it reached the bottleneck before x had left it (x's arrival less the propagation delay); the
        # newest run of frames that each waited for the one before: one span, so that the delay's jitter (which
        # also decides which pairs look queued) counts only at its two ends
        waited = [y.t_sent + base + margin < x.t_arrive for x, y in zip(recent, recent[1:])]
        if not any(waited):
            return None, None
        end = max(i for i, w in enumerate(waited) if w)
        start = _run_start(waited, end)
        run = recent[start:end + 2]
        span = run[-1].t_arrive - run[0].t_arrive
        if len(run) < 3 or span <= 1e-3:          # one pair alone: its two ends' jitter is most of its span
            return None, None
        return sum(y.size for y in run[1:]) * 8 / span / 1e6, run[-1].t_sent

    def _delivery_mbps(self) -> float | None:
        """What the link delivered over the newest run of frames that each arrived late (their one-way delay more
        than half the overuse threshold above the base), within the last ``2 * trend_frames`` frames: their bytes
        over the time from when the first of them could have reached the bottleneck (its send time plus the base
        delay, or the frame before it leaving, whichever is later) to the last one's arrival. A looser measure than
        :meth:`_capacity_mbps` (a large frame arrives late for its own serialization alone) that errs low, where the
        link idled between them: the safe side while the link queues. None without at least two late frames."""
        recent = list(self._samples)[-2 * self.config.trend_frames:]
        base, margin = self._base_owd(), self.overuse_threshold_s / 2
        late = [s.owd - base > margin for s in recent[1:]]
        if len(late) < 2 or not late[-1] or not late[-2]:
            return None
        start = _run_start(late, len(late) - 1)
        before, run = recent[start], recent[start + 1:]
        span = run[-1].t_arrive - max(before.t_arrive, run[0].t_sent + base)
        return sum(s.size for s in run) * 8 / span / 1e6 if span > 1e-3 else None

    # -- decisions

    def in_flight_bytes(self, now: float) -> int:
        """Bytes sent and not yet reported (frames unreported for ``lost_after_s``, or four smoothed round trips if
        that is longer, are taken as lost)."""
        lost_after = max(self.config.lost_after_s, 4 * self._srtt if self._srtt is not None else 0.0)
        while self._sent and next(iter(self._sent.values()))[0] < now - lost_after:
            self._sent.popitem(last=False)
        return sum(size for _, size, _ in self._sent.values())

    def _acked_rate(self, now: float) -> float | None:
        """Bytes per second reported over the last ``ack_window_s`` (None with fewer than three reports)."""
        while self._acks and self._acks[0][0] < now - self.config.ack_window_s:
            self._acks.popleft()
        if len(self._acks) < 3:
            return None
        return sum(b for _, b in self._acks) / self.config.ack_window_s

    def headroom_mbps(self, now: float) -> float | None:
        """The rate the link is believed to carry: the capacity measured at the last overuse (or the rate of the
        last point that ran ``hold_up_s`` without one, if higher), growing by ``probe_growth`` per second since;
        None before any overuse."""
        if self._headroom is None:
            return None
        value, since = self._headroom
        return value * self.config.probe_growth ** max(0.0, now - since)

    def may_start(self, now: float, frame_interval_s: float) -> bool:
        """Whether a new frame may start. Before the first overuse: while the bytes in flight fit a window that
        starts at ``initial_frames`` frames and grows by each frame reported without queueing (slow start), and,
        once reports flow, what was reported in the last ``ack_window_s`` over one smoothed round trip and one
        frame more (so a link that suddenly queues stops new frames within a round trip). After
        one: while they fit what the link carries (the headroom) in the smallest round trip seen plus
        ``queue_target_s``, and one frame more (so where even the lowest point does not fit, frames come less
        often). A client that sends no reports at
        all is not paced (:meth:`_silent`)."""
        c, st = self.config, self.state
        st.in_flight_bytes = inflight = self.in_flight_bytes(now)
        if inflight == 0 or (not self._reports and self._silent(now)):
            self._holding = False
            return True
        frame = self.bytes_per_frame(st.index)
        headroom = self.headroom_mbps(now)
        if headroom is None or not self._rtts:
            allowed = max(self._window, c.initial_frames * frame)
            acked = self._acked_rate(now)
            if acked is not None:      # ack-clocked: what was delivered in one smoothed round trip, and a frame
                allowed = min(allowed, acked * self._srtt + frame)
        else:
            allowed = headroom * 1e6 / 8 * (min(r for _, r in self._rtts) + c.queue_target_s) + frame
        if inflight + frame > allowed:
            st.frames_paced += 1
            if not self._holding:                   # one per frame held back, however often asked
                self._paced.append(now)
                self._holding = True
            return False
        self._holding = False                       # this frame starts: the next one held back is another
        return True

    def _own_due(self, now: float) -> bool:
        """Whether the server's own settings may be tried: at the ladder's best point, which has run
        ``own_hold_s`` since the last change and the last overuse. They cost the most to leave when the link drops
        (their frames are the largest in flight), so they need more calm than a step within the ladder."""
        c = self.config
        since = max(self._last_change, self._first_sent if self._first_sent is not None else now)
        return (self.own_index is not None and self.state.index == self._best and now - since >= c.own_hold_s
                and (self._last_overuse is None or now - self._last_overuse >= c.own_hold_s))

    def _silent(self, now: float) -> bool:
        """No report ever came although a frame was sent ``lost_after_s`` ago: the client does not report. (A
        client that does says so with an empty report when it connects, so a slow first frame is not taken for
        silence.)"""
        return self._first_sent is not None and now - self._first_sent >= self.config.lost_after_s

    def choose(self, now: float, frame_interval_s: float) -> int:
        """The point for a frame starting now: the current one; after ``hold_up_s`` without overuse or queue (and
        once a frame made at the current point was reported through without queueing), the best one that fits the
        ceiling and the headroom (twice the current rate before the first overuse); lower at once if the current one
        no longer fits the ceiling."""
        c, st = self.config, self.state
        if c.target_mbps is not None and self.predicted_mbps(st.index, frame_interval_s) > c.target_mbps:
            st.index = self._best_fitting(c.target_mbps, frame_interval_s, self.headroom_mbps(now))
            self._last_change = now
            return st.index
        # frames held back again and again while the link queues, and what was reported over the last window clearly
        # less than the point makes at the session's frame interval: the point sends more than the link carries,
        # though the pacing keeps the delay below the overuse threshold, and the link's rate is what was reported. (A
        # server slower than the link makes less than the point allows; its frames then wait now and then for the
        # report of the one before, and the reports measure the server, not the link.)
        while self._paced and self._paced[0] < now - c.ack_window_s:
            self._paced.popleft()
        acked = self._acked_rate(now)
        queueing = st.queue_delay_s is not None and st.queue_delay_s > self.overuse_threshold_s / 2
        short = acked is not None and acked * 8 / 1e6 < c.backoff * self.predicted_mbps(st.index, frame_interval_s)
        if len(self._paced) >= 3 and queueing and short and now - self._last_change >= c.hold_up_s:
            capacity = acked * 8 / 1e6
            st.capacity_mbps, self._headroom, self._last_overuse = capacity, (capacity, now), now
            new = self._best_fitting(c.backoff * capacity, frame_interval_s, capacity)
            if self.predicted_mbps(new, frame_interval_s) < self.predicted_mbps(st.index, frame_interval_s):
                st.index, st.decreases, self._last_change = new, st.decreases + 1, now
                self._paced.clear()
            return st.index
        calm = ((self._last_overuse is None or now - self._last_overuse >= c.hold_up_s)
                and st.queue_delay_s is not None and st.queue_delay_s <= self.overuse_threshold_s / 2
                and self._calm_index == st.index)       # a frame of this point went through without queueing
        # before the first overuse the controller climbs four times as fast (its slow start)
        hold = c.hold_up_s if self._headroom is not None else c.hold_up_s / 4
        if now - self._last_change < hold or not calm:
            return st.index
        if self._headroom is not None:       # the point has run hold_up_s without overuse: the link carries it
            value = max(self.headroom_mbps(now), self.predicted_mbps(st.index, frame_interval_s))
            self._headroom = (value, now)
        ceiling = c.target_mbps if c.target_mbps is not None else math.inf
        headroom = self.headroom_mbps(now)
        rate = self.predicted_mbps(st.index, frame_interval_s)
        # up: the best point within the headroom (before the first overuse: within twice the rate now, a slow
        # start that doubles) whose frames are fresh enough on the link as measured
        limit = min(ceiling, headroom if headroom is not None else 2 * rate)
        better = [j for j in range(len(self.ladder)) if self._flip[j] < self._flip[st.index]
                  and self.predicted_mbps(j, frame_interval_s) <= limit
                  and self._fresh(j, frame_interval_s, headroom)]
        up = min(better, key=lambda j: (self._flip[j], -j)) if better else None
        if up is None and self._own_due(now) and self.predicted_mbps(self.own_index, frame_interval_s) <= limit \
                and self._fresh(self.own_index, frame_interval_s, headroom):
            up = self.own_index
        if up is not None:
            if self._headroom is not None:
                self._probe = (st.index, now)        # a step past what the link was seen to carry
            st.index = up
            st.increases += 1
            self._last_change = now
        return st.index
