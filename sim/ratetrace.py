"""Bandwidth traces in Mahimahi's format: when a link may deliver, as a list of 1500-byte delivery opportunities.

A Mahimahi trace (``mm-link``) is a text file with one integer per line: a time in milliseconds at which the link
can deliver one packet of up to 1500 bytes. Times never decrease; several lines may share a millisecond (more
than 12 Mbit/s). The trace repeats: when it ends it starts again, shifted by its last timestamp (its period).
So a file holding the single line ``1`` is a 12 Mbit/s link (one 1500-byte packet every millisecond).

:class:`RateTrace` holds one, answers when a byte stream offered at time ``t`` finishes crossing the link
(:meth:`RateTrace.depart`, what :class:`quadcast.sim.link.LinkModel` uses instead of a fixed rate), and gives the
capacity over time for plots (:meth:`RateTrace.rate_mbit`). The link carries a byte *stream*: a message uses the
rest of the opportunity the previous one left partly filled, and an opportunity that passes with nothing queued
is lost, as in Mahimahi.

:func:`trace_from_schedule` makes a trace from a piecewise-constant rate schedule; ``python -m
quadcast.sim.ratetrace`` writes the traces shipped in ``sim/rate_traces/`` (constant, a step down and up, a
sawtooth), which ``builtin:NAME`` names wherever a rate trace is asked for.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["PACKET_BYTES", "RateTrace", "RateTraceError", "trace_from_schedule", "resolve_rate_trace",
           "SHIPPED_TRACES", "SHIPPED_DIR"]

PACKET_BYTES = 1500
"""Bytes one delivery opportunity carries (Mahimahi's MTU)."""

SHIPPED_DIR = Path(__file__).resolve().parent / "rate_traces"


class RateTraceError(ValueError):
    """A rate trace is malformed, unknown or cannot be read."""


@dataclass(frozen=True)
class RateTrace:
    """A Mahimahi trace: ``opportunities_ms`` (sorted, int64) repeating every ``period_ms``."""

    name: str
    opportunities_ms: np.ndarray
    period_ms: int

    def __post_init__(self) -> None:
        ops = np.asarray(self.opportunities_ms)
        if ops.ndim != 1 or ops.size == 0:
            raise RateTraceError(f"{self.name}: a rate trace needs at least one delivery opportunity")
        if np.any(np.diff(ops) < 0) or ops[0] < 0:
            raise RateTraceError(f"{self.name}: timestamps must be >= 0 and never decrease")
        if self.period_ms <= 0 or ops[-1] > self.period_ms:
            raise RateTraceError(f"{self.name}: the period must be > 0 and >= the last timestamp, got "
                                 f"{self.period_ms} ms")
        object.__setattr__(self, "opportunities_ms", ops.astype(np.int64))

    # -- reading and writing

    @classmethod
    def parse(cls, text: str, name: str = "<text>") -> "RateTrace":
        """A trace from Mahimahi text (blank lines and ``#`` comments are skipped); errors name the line."""
        values = []
        for n, line in enumerate(text.splitlines(), 1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            try:
                v = int(s)
            except ValueError:
                raise RateTraceError(f"{name} line {n}: expected an integer time in ms, got {s[:40]!r}") from None
            if v < 0:
                raise RateTraceError(f"{name} line {n}: a time must be >= 0 ms, got {v}")
            if values and v < values[-1]:
                raise RateTraceError(f"{name} line {n}: {v} ms is earlier than the line before ({values[-1]} ms)")
            values.append(v)
        if not values:
            raise RateTraceError(f"{name}: no delivery opportunities (an empty trace would never deliver)")
        if values[-1] <= 0:
            raise RateTraceError(f"{name}: the last timestamp is the trace's period and must be > 0 ms")
        return cls(name, np.asarray(values, np.int64), int(values[-1]))

    @classmethod
    def load(cls, path: str | Path) -> "RateTrace":
        path = Path(path)
        try:
            text = path.read_text()
        except OSError as exc:
            raise RateTraceError(f"rate trace {str(path)!r}: {exc.strerror or exc}") from None
        return cls.parse(text, str(path))

    def to_text(self) -> str:
        return "\n".join(map(str, self.opportunities_ms.tolist())) + "\n"

    # -- the link

    @property
    def mean_mbit(self) -> float:
        """Mean capacity over one period, Mbit/s."""
        return len(self.opportunities_ms) * PACKET_BYTES * 8 / (self.period_ms * 1e3)

    def opportunity_ms(self, k: int | np.ndarray) -> int | np.ndarray:
        """Time (ms) of the k-th opportunity of the repeating trace (k >= 0)."""
        n = len(self.opportunities_ms)
        return self.opportunities_ms[np.asarray(k) % n] + (np.asarray(k) // n) * self.period_ms

    def first_at_or_after(self, t_ms: float) -> int:
        """Index of the first opportunity at or after ``t_ms``."""
        if t_ms <= 0:
            return 0
        n = len(self.opportunities_ms)
        cycle = max(0, int(t_ms // self.period_ms) - 1)     # timestamps lie in [0, period]: start a cycle early
        while True:
            k = int(np.searchsorted(self.opportunities_ms, t_ms - cycle * self.period_ms, side="left"))
            if k < n:
                return cycle * n + k
            cycle += 1

    def depart(self, t: float, size_bytes: int, cursor: tuple[int, int] | None) -> tuple[float, tuple[int, int]]:
        """When ``size_bytes`` offered at time ``t`` (s) have crossed the link, and the new cursor.

        ``cursor`` is ``(next opportunity index, bytes already used of it)`` after the previous message (None: the
        link never carried anything). The stream continues in a partly used opportunity only if that opportunity is
        not in the past of ``t``; otherwise it starts at the first opportunity at or after ``t``. A message of 0
        bytes departs at ``t``."""
        if size_bytes <= 0:
            return t, cursor if cursor is not None else (self.first_at_or_after(t * 1e3), 0)
        k, used = cursor if cursor is not None else (0, 0)
        start = self.first_at_or_after(t * 1e3)
        if start > k:
            k, used = start, 0
        total = used + size_bytes
        last = k + (total - 1) // PACKET_BYTES           # the opportunity that carries the last byte
        rest = total - (last - k) * PACKET_BYTES         # bytes of it used, 1..1500
        depart = float(self.opportunity_ms(last)) / 1e3
        cursor = (last + 1, 0) if rest == PACKET_BYTES else (last, rest)
        return max(depart, t), cursor

    def rate_mbit(self, t0: float, t1: float, step: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
        """Capacity over ``[t0, t1)`` s in windows of ``step`` s: (window centres, Mbit/s)."""
        edges = np.arange(t0, t1 + step * 0.5, step)
        k = np.array([self.first_at_or_after(e * 1e3) for e in edges])
        return (edges[:-1] + edges[1:]) / 2, np.diff(k) * PACKET_BYTES * 8 / (step * 1e6)


def trace_from_schedule(schedule: list[tuple[float, float]], name: str = "schedule") -> RateTrace:
    """A trace from ``[(seconds, Mbit/s), ...]``: each segment at its rate, in order; the period is their total.
    Opportunities are spread evenly at the rate and floored to whole ms, as Mahimahi's own generators do."""
    times: list[np.ndarray] = []
    start = 0.0
    for seconds, mbit in schedule:
        if not (seconds > 0 and mbit > 0 and math.isfinite(seconds) and math.isfinite(mbit)):
            raise RateTraceError(f"{name}: a schedule segment needs seconds > 0 and Mbit/s > 0, got "
                                 f"({seconds}, {mbit})")
        per_ms = mbit * 1e6 / 8 / PACKET_BYTES / 1e3               # opportunities per ms
        count = int(round(seconds * 1e3 * per_ms))
        times.append(start * 1e3 + (np.arange(count) + 1) / per_ms)
        start += seconds
    ops = np.floor(np.concatenate(times) + 1e-6).astype(np.int64)     # + 1e-6: 2999.9999... is 3000
    period = int(round(start * 1e3))
    ops = np.minimum(ops, period)
    ops[-1] = period                 # Mahimahi's period is the last timestamp
    return RateTrace(name, ops, period)


def _ramp(low: float, high: float, seconds: float, steps: int) -> list[tuple[float, float]]:
    return [(seconds / steps, low + (high - low) * (i + 0.5) / steps) for i in range(steps)]


SHIPPED_TRACES: dict[str, list[tuple[float, float]]] = {
    # name: schedule. Short (each file repeats), so the files stay small.
    "const-20": [(0.3, 20.0)],
    "step-100-15-100": [(1.0, 100.0), (1.5, 15.0), (1.5, 100.0)],
    "sawtooth-10-40": _ramp(10.0, 40.0, 3.0, 30),
}
"""The traces ``python -m quadcast.sim.ratetrace`` writes to ``sim/rate_traces/NAME.mahi``."""


def resolve_rate_trace(spec: str) -> RateTrace:
    """``builtin:NAME`` (a shipped trace, see :data:`SHIPPED_TRACES`) or a Mahimahi file."""
    if spec.startswith("builtin:"):
        name = spec.split(":", 1)[1]
        if name not in SHIPPED_TRACES:
            raise RateTraceError(f"rate trace {spec!r}: unknown; built-in rate traces are "
                                 f"{', '.join('builtin:' + n for n in SHIPPED_TRACES)}")
        trace = RateTrace.load(SHIPPED_DIR / f"{name}.mahi")
        return RateTrace(spec, trace.opportunities_ms, trace.period_ms)
    return RateTrace.load(spec)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m quadcast.sim.ratetrace",
                                description="write the shipped Mahimahi rate traces")
    p.add_argument("--out", default=str(SHIPPED_DIR), help="directory (default: the package's sim/rate_traces)")
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for name, schedule in SHIPPED_TRACES.items():
        trace = trace_from_schedule(schedule, name)
        (out / f"{name}.mahi").write_text(trace.to_text())
        print(f"{out / (name + '.mahi')}: {len(trace.opportunities_ms)} opportunities, period {trace.period_ms} ms, "
              f"mean {trace.mean_mbit:.1f} Mbit/s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
