"""Head-pose prediction for the server: extrapolate the client's recent poses to the time a frame will be shown.

A pose is ``(t, position, quat)``: time in seconds, position ``(3,)`` float64 metres, orientation quaternion
``(4,)`` in scipy's ``xyzw`` order. All rotation maths goes through :class:`scipy.spatial.transform.Rotation`, so a
quaternion and its negation are the same pose.

:class:`PosePredictor` keeps the latest observed poses and extrapolates position and rotation each with its own
:class:`MotionModel`:

- a polynomial of degree ``order`` (0 hold, 1 constant velocity, 2 constant acceleration) fitted by least squares
  (:func:`numpy.polynomial.polynomial.polyfit`, non-uniform times are fine) to the last ``window`` samples -- more
  samples than ``order + 1`` smooth -- and extrapolated from the *latest sample itself* (the fit only gives the
  motion since, so smoothing never moves the pose the user was last seen at);
- *damping*: the extrapolation runs on a time ``tau * (1 - exp(-dt / tau))`` instead of ``dt``, so a long horizon
  asks less of a model that is right only for a moment;
- *clamping*: the predicted pose is never farther from the latest one than the fastest the head moved between
  the samples of the last :data:`PEAK_LOOKBACK_S` seconds (times the horizon), nor than ``max_speed`` allows.

Rotations are handled as rotation vectors of the history *relative to the latest rotation*
(``rotvec_i = (R_i * R_latest^-1).as_rotvec()``), small and continuous around the latest sample, so there are no
Euler or 360-degree wrap problems while consecutive samples differ by less than 180 degrees.

The clamp makes a guarantee that holds whatever the motion: a prediction is off by at most the error of not
predicting plus the head's recent peak speed times the horizon (:func:`quadcast.sim.prediction.prediction_errors`
checks it as ``bound``). The defaults (:data:`DEFAULT_PREDICTOR`) were chosen by measuring the real head traces
with ``quadcast predict`` (see the README).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial import polynomial
from scipy.spatial.transform import Rotation

__all__ = ["DEFAULT_PREDICTOR", "UNCLAMPED_ACCELERATION", "MIN_STEP_S", "MotionModel", "PEAK_LOOKBACK_S", "PoseSample", "PosePredictor",
           "PredictorSettings"]

MIN_STEP_S = 1e-3
"""Samples closer than this to the latest one are ignored like duplicates: speeds over tiny steps are noise (and
over 1e-300 s they overflow), whatever poses a client sends."""

PEAK_LOOKBACK_S = 0.2
"""How far back (s) from the latest sample the clamp looks for the head's peak speed."""


@dataclass(frozen=True)
class PoseSample:
    """One observed pose: time (s), position (3,) metres, unit quaternion (4,) xyzw."""

    t: float
    position: np.ndarray
    quat: np.ndarray


@dataclass(frozen=True)
class MotionModel:
    """How one part of the pose (position or rotation) is extrapolated.

    ``order``: degree of the fitted polynomial (0 hold, 1 velocity, 2 acceleration); ``window``: samples fitted
    (>= ``order + 1``; more smooth); ``damping_s``: time constant of the damped horizon (None: none);
    ``clamp``: never extrapolate faster than the peak speed between the samples of the last
    :data:`PEAK_LOOKBACK_S`; ``max_speed``: an absolute cap (m/s for position, degrees/s for rotation; None: none).
    """

    order: int = 1
    window: int = 2
    damping_s: float | None = None
    clamp: bool = True
    max_speed: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.order, (int, np.integer)) or not 0 <= self.order <= 3:
            raise ValueError(f"MotionModel.order must be 0, 1, 2 or 3, got {self.order!r}")
        if not isinstance(self.window, (int, np.integer)) or self.window < max(self.order + 1, 1):
            raise ValueError(f"MotionModel.window must be an integer >= order + 1 ({self.order + 1}), "
                             f"got {self.window!r}")
        if self.damping_s is not None and not (np.isfinite(self.damping_s) and self.damping_s > 0):
            raise ValueError(f"MotionModel.damping_s must be > 0 s or None, got {self.damping_s!r}")
        if self.max_speed is not None and not (np.isfinite(self.max_speed) and self.max_speed > 0):
            raise ValueError(f"MotionModel.max_speed must be > 0 or None, got {self.max_speed!r}")

    def horizon(self, dt: float) -> float:
        """The (damped) time the polynomial is extrapolated over for a real horizon ``dt``."""
        if self.damping_s is None or dt <= 0:
            return dt
        return self.damping_s * -math.expm1(-dt / self.damping_s)

    def __str__(self) -> str:
        parts = [f"order {self.order}", f"window {self.window}"]
        if self.damping_s is not None:
            parts.append(f"damping {self.damping_s * 1e3:g} ms")
        parts.append("clamped" if self.clamp else "unclamped")
        if self.max_speed is not None:
            parts.append(f"max {self.max_speed:g}/s")
        return ", ".join(parts)


@dataclass(frozen=True)
class PredictorSettings:
    """A :class:`MotionModel` for position and one for rotation."""

    position: MotionModel = field(default_factory=MotionModel)
    rotation: MotionModel = field(default_factory=MotionModel)

    @property
    def history(self) -> int:
        """Samples a predictor must keep."""
        return max(self.position.window, self.rotation.window, 2)

    def __str__(self) -> str:
        return f"position: {self.position}; rotation: {self.rotation}"


DEFAULT_PREDICTOR = PredictorSettings(
    position=MotionModel(order=1, window=3, damping_s=None, clamp=True),
    rotation=MotionModel(order=1, window=2, damping_s=0.3, clamp=True),
)
"""The predictor the session core uses, chosen by measurement on the two real head traces (``quadcast predict``,
4 seeds; README): of polynomial orders 1-3, windows 2-7, damping none/20-600 ms, with and without the clamp and
absolute speed caps, constant velocity was best for both -- position fitted over 3 samples, undamped (0.20-0.22x
the error of not predicting at 40-100 ms horizons, 0.28-0.30x at 500 ms), rotation from the last 2 with its horizon
damped at 300 ms (0.48-0.58x at 40-100 ms, 0.69-0.74x at 500 ms, the live demo's horizon on a slow machine): within
2.1% of the best time constant at every horizon from 40 to 500 ms, where 150 ms was best at 40 ms by that much and
12.5% worse at 500 ms. Acceleration terms lose (rotation 0.82-0.86x clamped at 50±20 ms, above 1x unclamped, where
they overshoot the bound after reversals) and so do caps at human walking speeds (these traces move up to 5.8 m/s)."""


UNCLAMPED_ACCELERATION = PredictorSettings(
    position=MotionModel(order=2, window=3, clamp=False), rotation=MotionModel(order=2, window=3, clamp=False))
"""A predictor with no clamp and acceleration terms (the old kind): for tests that the session core stays sane
whatever the predictor extrapolates."""


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
    if norm < 1e-12:
        raise ValueError(f"quat must have non-zero norm, got {q!r}")
    return q / norm


def _extrapolate(model: MotionModel, t: np.ndarray, y: np.ndarray, steps: np.ndarray, dt: float,
                 unit: float = 1.0) -> np.ndarray:
    """The displacement (k,) from the latest sample after `dt`: `y` (n, k) are the samples at times `t` (n,)
    (newest last), `steps` (n-1,) the distance between consecutive samples (for the peak speed); `unit` converts
    ``model.max_speed`` to the units of `y`."""
    n = min(model.window, len(t))
    degree = min(model.order, n - 1)
    if degree == 0 or dt == 0:
        return np.zeros(y.shape[1])
    x = t[-n:] - t[-1]
    coef = polynomial.polyfit(x, y[-n:], degree)          # (degree + 1, k), lowest power first
    h = model.horizon(dt)
    move = sum(coef[j] * h ** j for j in range(1, degree + 1))
    limit = math.inf
    if model.clamp:
        recent = t[:-1] >= t[-1] - PEAK_LOOKBACK_S - 1e-9   # steps that start within the lookback
        recent[-1] = True                                    # and at least the newest one
        limit = float(np.max(steps[recent] / np.diff(t)[recent])) * abs(dt)
    if model.max_speed is not None:
        limit = min(limit, model.max_speed * unit * abs(dt))
    size = float(np.linalg.norm(move))
    return move * (limit / size) if size > limit else move


class PosePredictor:
    """Pose extrapolation over a short history of observed poses (see the module docstring).

    With fewer samples than a model's window it fits what there is: one sample holds the pose, two give a
    constant velocity.
    """

    def __init__(self, settings: PredictorSettings | None = None) -> None:
        self.settings = settings or DEFAULT_PREDICTOR
        if not isinstance(self.settings, PredictorSettings):
            raise ValueError(f"PosePredictor: settings must be PredictorSettings, got {type(self.settings).__name__}")
        self._samples: deque[PoseSample] = deque(maxlen=self.settings.history)

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
        """Add a pose sample; returns ``False`` (and ignores it) if ``t`` is not at least :data:`MIN_STEP_S` later
        than the latest accepted sample (out-of-order, duplicate or too close)."""
        t = float(t)
        if not np.isfinite(t):
            raise ValueError(f"pose time t must be finite, got {t!r}")
        p, q = _as_position(position), _as_quat(quat)
        if self._samples and t < self._samples[-1].t + MIN_STEP_S:
            return False
        self._samples.append(PoseSample(t, p, q))
        return True

    def predict(self, t_target: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted ``(position (3,), quat (4,) xyzw)`` at time ``t_target``."""
        if not self._samples:
            raise RuntimeError("PosePredictor.predict called before any pose was observed")
        last = self._samples[-1]
        if len(self._samples) == 1:
            return last.position.copy(), last.quat.copy()
        samples = list(self._samples)
        t = np.array([s.t for s in samples])
        dt = float(t_target) - last.t
        s = self.settings
        pos = np.array([s_.position for s_ in samples])
        position = last.position + _extrapolate(s.position, t, pos, np.linalg.norm(np.diff(pos, axis=0), axis=1),
                                                dt)
        rotations = Rotation.from_quat(np.array([s_.quat for s_ in samples]))
        r_last = rotations[-1]
        # Rotation vectors relative to the latest rotation (world frame): R_i = exp(r_i) * R_last; steps are the
        # geodesic angles between consecutive samples.
        rel = (rotations * r_last.inv()).as_rotvec()
        steps = (rotations[1:] * rotations[:-1].inv()).magnitude()
        turn = _extrapolate(s.rotation, t, rel, steps, dt, unit=math.pi / 180.0)
        return position, (Rotation.from_rotvec(turn) * r_last).as_quat()
