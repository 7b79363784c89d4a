"""Gaze traces: where the viewer looks, relative to the head, over time (for foveation: `quadcast eval --gaze`, whose
replayed client sends it with its poses, and `quadcast client --gaze`).

One sample per line, whitespace-separated: ``t_ms x_deg y_deg`` -- the time since the start of the head trace it
goes with, and the gaze's angles from the view axis in degrees (x to the right, y up). Blank lines and ``#``
comments are skipped; times must increase. Between samples the angles are interpolated linearly; before the first
and after the last they hold. Without a gaze trace the gaze is the view centre. Angles are bounded as the wire's are
(:func:`quadcast.protocol.pose.check_gaze`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from quadcast.protocol.pose import MAX_GAZE_DEG, gaze_direction

__all__ = ["GazeTrace", "GazeTraceError"]


class GazeTraceError(ValueError):
    """A gaze trace is malformed or cannot be read."""


@dataclass(frozen=True)
class GazeTrace:
    name: str
    times: np.ndarray          # (N,) seconds since the head trace's start
    angles_deg: np.ndarray     # (N, 2) x right, y up

    @classmethod
    def parse(cls, text: str, name: str = "<text>") -> "GazeTrace":
        rows = []
        for n, line in enumerate(text.splitlines(), 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            try:
                values = [float(v) for v in parts]
            except ValueError:
                raise GazeTraceError(f"{name} line {n}: expected numbers 't_ms x_deg y_deg', got {s[:60]!r}") from None
            if len(values) != 3 or not np.all(np.isfinite(values)):
                raise GazeTraceError(f"{name} line {n}: expected three finite numbers 't_ms x_deg y_deg', got {s[:60]!r}")
            if not all(-MAX_GAZE_DEG < v < MAX_GAZE_DEG for v in values[1:]):
                raise GazeTraceError(f"{name} line {n}: gaze angles must be within +-{MAX_GAZE_DEG:g} degrees, "
                                     f"got {values[1:]}")
            if rows and values[0] <= rows[-1][0]:
                raise GazeTraceError(f"{name} line {n}: time {values[0]:g} ms does not follow {rows[-1][0]:g} ms")
            rows.append(values)
        if not rows:
            raise GazeTraceError(f"{name}: no gaze samples")
        a = np.asarray(rows, np.float64)
        return cls(name, a[:, 0] / 1e3, a[:, 1:])

    @classmethod
    def load(cls, path: str | Path) -> "GazeTrace":
        try:
            text = Path(path).read_text()
        except OSError as exc:
            raise GazeTraceError(f"gaze trace {str(path)!r}: {exc.strerror or exc}") from None
        return cls.parse(text, str(path))

    def angles_at(self, t: float) -> np.ndarray:
        return np.array([np.interp(t, self.times, self.angles_deg[:, k]) for k in range(2)])

    def direction_at(self, t: float) -> np.ndarray:
        """The unit view-space direction (camera looking down -Z) of the gaze at ``t`` s."""
        return gaze_direction(self.angles_at(t))
