"""One direction of a network link, modelled like Linux ``netem`` in virtual time.

A :class:`LinkModel` turns ``send(t, message, size_bytes)`` calls into
:class:`Delivery` records with an arrival time, and hands them back through
``poll(now)`` once virtual time has reached their arrival.  Nothing here
touches sockets or the wall clock: times are plain float seconds chosen by
the caller (a simulator's event loop).

The model, per message:

1. **Loss** -- dropped with probability ``loss`` (drawn from a seeded numpy
   ``Generator``).  Like netem, loss is applied on enqueue, so a dropped
   message does not occupy the link.
2. **Serialization** -- with ``rate_mbit`` set, the message queues behind
   earlier ones and leaves at
   ``depart = max(t, link_free_at) + size_bytes * 8 / (rate_mbit * 1e6)``.
   With a ``rate_trace`` (:class:`quadcast.sim.ratetrace.RateTrace`, Mahimahi's
   format) instead, it leaves when the trace's delivery opportunities from
   ``max(t, link_free_at)`` on have carried its bytes (trace time 0 is
   ``trace_start``). Without either, ``depart = t``.
3. **Propagation** -- ``arrive = depart + delay + jitter`` where jitter is
   uniform in ``[-J, +J]`` or normal with sigma ``J``, clipped so that
   ``arrive >= depart``.
4. **Ordering** -- unless ``reorder=True``, a message never arrives before
   one sent earlier (``arrive = max(arrive, previous arrive)``).

With ``reliable=True`` the direction carries one TCP stream instead of datagrams: nothing is dropped, ``loss`` is
the probability that each segment of ``mss_bytes`` is lost, and the sender's window behaves like Reno's (with SACK).
A message's segments leave at most a window per round trip (``rtt_ms``, twice ``delay_ms`` unless given): the window
starts at ``initial_window`` segments, doubles each round trip that used it all (slow start), grows by one segment
a round trip past ``ssthresh`` and halves after a round trip with a loss. A lost segment goes again one round trip
after it went, so the message (and every later one: in-order delivery) waits for it. With a rate and
``queue_bytes``, segments that find the drop-tail queue before the rate full are lost too, so the window stops
growing where the queue overflows, as Reno's does over a real bottleneck. A round's acknowledgements come a round
trip after its first segment left the queue (so a window sent into a queue is not sent again before the queue has
carried it), and the window does not restart after idle (Linux's ``tcp_slow_start_after_idle=0``).

Loss and jitter use two independent random streams derived from ``seed``, so
the set of dropped messages depends only on ``seed`` and ``loss`` (not on the
jitter settings), and the same seed always reproduces the same behaviour.

Example::

    >>> link = LinkModel(delay_ms=20, rate_mbit=100)
    >>> d = link.send(0.0, b"frame", size_bytes=125_000)   # 10 ms to serialize
    >>> round(d.t_arrive, 6)
    0.03
    >>> [x.message for x in link.poll(0.05)]
    [b'frame']
"""

from __future__ import annotations

import collections
import heapq
import math
import re
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from quadcast.sim.ratetrace import RateTrace

__all__ = [
    "Delivery",
    "LinkStats",
    "LinkModel",
    "RenoWindow",
    "parse_duration_ms",
    "parse_rate_mbit",
    "parse_loss",
    "parse_bytes",
]

JitterDistribution = Literal["uniform", "normal"]

MAX_RELIABLE_LOSS = 0.5
"""A reliable link's highest segment loss: a 64 MiB message takes its model about 0.2 s there (10 s at 99%)."""


@dataclass(frozen=True)
class Delivery:
    """One message in flight (or delivered) on a :class:`LinkModel`.

    Times are virtual seconds: ``t_sent`` when ``send`` was called,
    ``t_depart`` when its last bit left the sender (after queueing and
    serialization), ``t_arrive`` when it reaches the receiver.  ``seq`` is the
    0-based index of the ``send`` call on this link (dropped ones included).
    """

    message: Any
    size_bytes: int
    t_sent: float
    t_depart: float
    t_arrive: float
    seq: int = 0

    @property
    def latency(self) -> float:
        """Seconds from ``send`` to arrival (queueing + serialization + delay)."""
        return self.t_arrive - self.t_sent


@dataclass
class LinkStats:
    """Running counters of a :class:`LinkModel` (``sent`` counts every ``send``)."""

    sent: int = 0
    dropped: int = 0
    delivered: int = 0
    bytes_sent: int = 0
    bytes_dropped: int = 0
    bytes_delivered: int = 0
    segments_sent: int = 0        # reliable links: TCP segments put on the wire, those sent again included
    segments_lost: int = 0        # reliable links: segments lost (and sent again), overflowed ones included
    segments_overflowed: int = 0  # reliable links: segments the bottleneck's full queue dropped


@dataclass
class RenoWindow:
    """A TCP sender's congestion window, in segments, advanced one round trip at a time (Reno with SACK: at most
    one halving per round trip). ``used`` and ``lost`` count the current round's segments."""

    cwnd: float = 10.0
    ssthresh: float = math.inf
    round_start: float = -math.inf
    used: int = 0
    lost: int = 0

    def room(self) -> int:
        """Segments the window still lets out in this round."""
        return max(0, int(self.cwnd) - self.used)

    def next_round(self, t: float) -> None:
        """Start a round at ``t``: the acknowledgements of the last one have come back and set the window."""
        if self.lost:
            self.ssthresh = max(self.cwnd / 2.0, 2.0)
            self.cwnd = self.ssthresh
        elif self.used >= int(self.cwnd):   # only a window that limited the sender grows (RFC 7661)
            if self.cwnd < self.ssthresh:
                self.cwnd = min(self.cwnd + self.used, max(self.ssthresh, self.cwnd + 1.0))
            else:
                self.cwnd += self.used / self.cwnd
        self.round_start, self.used, self.lost = t, 0, 0


def _require_finite_nonneg(name: str, value: float) -> float:
    value = float(value)
    if not math.isfinite(value) or value < 0.0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return value


class LinkModel:
    """One direction of a netem-like link in virtual time.

    Parameters
    ----------
    delay_ms:
        Fixed one-way propagation delay in milliseconds (>= 0).
    jitter_ms:
        Jitter amplitude J in milliseconds (>= 0): half-width of the uniform
        distribution, or the standard deviation of the normal one.
    jitter:
        ``"uniform"`` (in ``[-J, +J]``) or ``"normal"`` (sigma ``J``).
    rate_mbit:
        Link rate in Mbit/s (> 0), or ``None`` for no serialization cost.
    loss:
        Drop probability per message, a fraction in ``[0, 1)``.
    reorder:
        If ``False`` (default) messages arrive in send order, as with netem
        when jitter is combined with a rate; if ``True`` jitter may let a
        later message overtake an earlier one.
    seed:
        Seed for the loss and jitter random streams.
    rate_trace:
        A Mahimahi bandwidth trace instead of a fixed ``rate_mbit`` (not both).
    trace_start:
        The link time (s) at which the trace's time 0 falls.
    reliable:
        Carry one TCP stream (see the module's docstring): segments are lost and sent again, messages never.
    rtt_ms:
        The round trip a reliable link's sender sees (``None``: ``2 * delay_ms``).
    mss_bytes:
        A reliable link's segment size.
    initial_window:
        A reliable link's first window, in segments (Linux: 10).
    queue_bytes:
        A reliable link's drop-tail queue before the rate (``None``: it takes everything): a segment that finds it
        full is lost, and sent again as any other.
    """

    def __init__(
        self,
        delay_ms: float = 0.0,
        jitter_ms: float = 0.0,
        jitter: JitterDistribution = "uniform",
        rate_mbit: float | None = None,
        loss: float = 0.0,
        reorder: bool = False,
        seed: int = 0,
        rate_trace: RateTrace | None = None,
        trace_start: float = 0.0,
        reliable: bool = False,
        rtt_ms: float | None = None,
        mss_bytes: int = 1448,
        initial_window: int = 10,
        queue_bytes: int | None = None,
    ) -> None:
        self.delay_ms = _require_finite_nonneg("delay_ms", delay_ms)
        self.jitter_ms = _require_finite_nonneg("jitter_ms", jitter_ms)
        if jitter not in ("uniform", "normal"):
            raise ValueError(f"jitter must be 'uniform' or 'normal', got {jitter!r}")
        self.jitter: JitterDistribution = jitter
        if rate_mbit is not None:
            rate_mbit = float(rate_mbit)
            if not math.isfinite(rate_mbit) or rate_mbit <= 0.0:
                raise ValueError(f"rate_mbit must be a finite number > 0 or None, got {rate_mbit!r}")
        self.rate_mbit: float | None = rate_mbit
        if rate_trace is not None and rate_mbit is not None:
            raise ValueError("a link takes a fixed rate_mbit or a rate_trace, not both")
        if rate_trace is not None and not isinstance(rate_trace, RateTrace):
            raise ValueError(f"rate_trace must be a RateTrace, got {type(rate_trace).__name__}")
        self.rate_trace: RateTrace | None = rate_trace
        self.trace_start = float(trace_start)
        if not math.isfinite(self.trace_start):
            raise ValueError(f"trace_start must be finite, got {trace_start!r}")
        self._trace_cursor: tuple[int, int] | None = None
        loss = float(loss)
        if not (0.0 <= loss < 1.0):
            raise ValueError(f"loss must be a fraction in [0, 1), got {loss!r}")
        self.loss = loss
        self.reorder = bool(reorder)
        self.seed = int(seed)
        self.reliable = bool(reliable)
        if self.reliable and self.reorder:
            raise ValueError("a reliable link delivers in order: reorder must be False")
        if self.reliable and self.loss > MAX_RELIABLE_LOSS:
            raise ValueError(f"a reliable (TCP) link's loss must be at most {MAX_RELIABLE_LOSS:.0%}, got "
                             f"{self.loss:.1%}: TCP all but stops beyond it (a datagram link drops whole messages at "
                             "any rate below 100%)")
        self.rtt_ms = 2.0 * self.delay_ms if rtt_ms is None else _require_finite_nonneg("rtt_ms", rtt_ms)
        for name, value in (("mss_bytes", mss_bytes), ("initial_window", initial_window)):
            if isinstance(value, bool) or int(value) != value or value < 1:
                raise ValueError(f"{name} must be a whole number >= 1, got {value!r}")
        self.mss_bytes = int(mss_bytes)
        self.window = RenoWindow(cwnd=float(initial_window))
        if queue_bytes is not None and (not self.reliable or isinstance(queue_bytes, bool)
                                        or int(queue_bytes) != queue_bytes or queue_bytes < self.mss_bytes):
            raise ValueError(f"queue_bytes is a reliable link's bottleneck queue, at least one segment "
                             f"({self.mss_bytes} bytes), got {queue_bytes!r}")
        self.queue_bytes = None if queue_bytes is None else int(queue_bytes)
        self._bottleneck: collections.deque[tuple[float, int]] = collections.deque()   # (departs, bytes) queued
        self._bottleneck_bytes = 0
        self._unsent: collections.deque[tuple[float, int]] = collections.deque()   # (departs, bytes), in order
        self._unsent_bytes = 0

        loss_seq, jitter_seq = np.random.SeedSequence(self.seed).spawn(2)
        self._loss_rng = np.random.default_rng(loss_seq)
        self._jitter_rng = np.random.default_rng(jitter_seq)
        self._link_free_at = -math.inf
        self._last_arrival = -math.inf
        self._next_seq = 0
        self._in_flight: list[tuple[float, int, Delivery]] = []
        self.stats = LinkStats()

    def __repr__(self) -> str:
        return (
            f"LinkModel(delay_ms={self.delay_ms}, jitter_ms={self.jitter_ms}, "
            f"jitter={self.jitter!r}, rate_mbit={self.rate_mbit}, loss={self.loss}, "
            f"reorder={self.reorder}, seed={self.seed}"
            + (f", rate_trace={self.rate_trace.name!r}" if self.rate_trace is not None else "")
            + (f", reliable=True, rtt_ms={self.rtt_ms}" if self.reliable else "") + ")"
        )

    # -- sending -------------------------------------------------------------

    def serialization_time(self, size_bytes: int) -> float:
        """Seconds needed to put ``size_bytes`` on the wire (0 without a rate)."""
        if self.rate_mbit is None:
            return 0.0
        return size_bytes * 8.0 / (self.rate_mbit * 1e6)

    def _draw_jitter_s(self) -> float:
        # One draw per send (dropped or not) so message i's jitter depends only on seed and i.
        j = self.jitter_ms * 1e-3
        if j == 0.0:
            return 0.0
        if self.jitter == "uniform":
            return float(self._jitter_rng.uniform(-j, j))
        return float(self._jitter_rng.normal(0.0, j))

    def send(self, t: float, message: Any, size_bytes: int) -> Delivery | None:
        """Offer ``message`` of ``size_bytes`` at virtual time ``t`` seconds.

        Returns the :class:`Delivery` (also queued for :meth:`poll`), or
        ``None`` if the message was dropped.
        """
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"send time t must be finite, got {t!r}")
        if isinstance(size_bytes, bool) or int(size_bytes) != size_bytes or size_bytes < 0:
            raise ValueError(f"size_bytes must be a non-negative integer, got {size_bytes!r}")
        size_bytes = int(size_bytes)

        seq = self._next_seq
        self._next_seq += 1
        self.stats.sent += 1
        self.stats.bytes_sent += size_bytes

        if self.reliable:
            jitter_s = self._draw_jitter_s()
            depart = self._send_segments(t, size_bytes)
        else:
            dropped = bool(self._loss_rng.random() < self.loss)
            jitter_s = self._draw_jitter_s()
            if dropped:
                self.stats.dropped += 1
                self.stats.bytes_dropped += size_bytes
                return None
            depart = self._serialize(t, size_bytes)
        arrive = depart + max(0.0, self.delay_ms * 1e-3 + jitter_s)
        if not self.reorder:
            arrive = max(arrive, self._last_arrival)
        self._last_arrival = max(self._last_arrival, arrive)

        delivery = Delivery(message, size_bytes, t, depart, arrive, seq)
        heapq.heappush(self._in_flight, (arrive, seq, delivery))
        return delivery

    def _serialize(self, t: float, size_bytes: int) -> float:
        """When ``size_bytes`` offered at ``t`` have left, behind what the link already carries."""
        if self.rate_trace is not None:
            start = max(t, self._link_free_at) - self.trace_start
            depart, self._trace_cursor = self.rate_trace.depart(start, size_bytes, self._trace_cursor)
            depart += self.trace_start
            self._link_free_at = depart
            return depart
        depart = max(t, self._link_free_at) + self.serialization_time(size_bytes)
        if self.rate_mbit is not None:
            self._link_free_at = depart
        return depart

    def _send_segments(self, t: float, size_bytes: int) -> float:
        """A reliable link's message: its segments leave as the window allows, lost ones again a round trip later.
        Returns when its last segment left."""
        rtt, w, mss = self.rtt_ms * 1e-3, self.window, self.mss_bytes
        self.unsent_bytes(t)   # forget what has left
        new = max(1, -(-size_bytes // mss))
        seg_bytes = size_bytes / new
        resend: collections.deque[tuple[float, int]] = collections.deque()   # (when the loss is known, segments)
        x = t
        depart = t
        on_wire = 0      # segments of this message serialized so far, sent again ones included
        while new or resend:
            if x >= w.round_start + rtt:
                w.next_round(x)
            room = w.room()
            if new:
                n = min(room, new)
            else:
                ready, n_lost = resend[0]
                if x < ready:
                    x = ready
                    continue
                n = min(room, n_lost)
            if n == 0:
                x = w.round_start + rtt   # the window is full: wait for this round's acknowledgements
                continue
            if new:
                new -= n
            elif n == resend[0][1]:
                resend.popleft()
            else:
                resend[0] = (resend[0][0], resend[0][1] - n)
            sent_at = max(x, self._link_free_at)
            if w.used == 0:   # the round's acknowledgements come back a round trip after its first segment left
                w.round_start = max(w.round_start, sent_at)
            fits = n if self.queue_bytes is None else self._segments_fitting(x, n, seg_bytes)
            if fits:   # whole bytes, counted over the message's segments so that its first ones add up to its size
                batch = round((on_wire + fits) * seg_bytes) - round(on_wire * seg_bytes)
                on_wire += fits
                batch_departs = self._serialize(x, batch)
                depart = max(depart, batch_departs)
                self._unsent.append((max(batch_departs, self._unsent[-1][0] if self._unsent else batch_departs),
                                     batch))
                self._unsent_bytes += batch
                if self.queue_bytes is not None and batch_departs > x:
                    self._bottleneck.append((batch_departs, batch))
                    self._bottleneck_bytes += batch
            lost = n - fits + (int(self._loss_rng.binomial(fits, self.loss)) if self.loss else 0)
            self.stats.segments_overflowed += n - fits
            w.used += n
            w.lost += lost
            self.stats.segments_sent += n
            if lost:
                self.stats.segments_lost += lost
                resend.append((sent_at + rtt, lost))
        return depart

    def _segments_fitting(self, t: float, n: int, seg_bytes: float) -> int:
        """How many of ``n`` segments sent at ``t`` the bottleneck's queue takes. Acknowledgements release a window
        over a round trip, not at once, and a fixed rate drains the queue meanwhile: only what the window sends
        beyond the rate (its excess over rate x round trip) fills it. Under a rate trace nothing is credited."""
        room = self._queue_room(t)
        per_segment = max(1.0, seg_bytes)
        if self.rate_mbit is not None:
            excess = 1.0 - self.rate_mbit * 1e6 / 8 * self.rtt_ms * 1e-3 / max(1.0, self.window.cwnd * self.mss_bytes)
            if excess <= 0.0:
                return n
            per_segment *= excess
        return min(n, int(room / per_segment))

    def unsent_bytes(self, t: float) -> int:
        """A reliable link's bytes accepted by :meth:`send` that have not left by ``t``: waiting for the window or
        in the queue before the rate (what a TCP sender's kernel holds unsent)."""
        while self._unsent and self._unsent[0][0] <= t:
            self._unsent_bytes -= self._unsent.popleft()[1]
        return self._unsent_bytes

    def unsent_at_most(self, limit: int, t: float) -> float:
        """When, from ``t`` on, a reliable link's unsent bytes are down to ``limit`` or fewer if nothing more is
        sent (``t``: they are already)."""
        left = self.unsent_bytes(t)
        if left <= limit:
            return t
        for departs, size in self._unsent:
            left -= size
            if left <= limit:
                return departs
        return self._unsent[-1][0]

    def _queue_room(self, t: float) -> int:
        """Bytes the bottleneck's drop-tail queue still takes at ``t`` (a reliable link with ``queue_bytes``)."""
        while self._bottleneck and self._bottleneck[0][0] <= t:
            self._bottleneck_bytes -= self._bottleneck.popleft()[1]
        return max(0, self.queue_bytes - self._bottleneck_bytes)

    # -- receiving -----------------------------------------------------------

    def poll(self, now: float) -> list[Delivery]:
        """Remove and return messages with ``t_arrive <= now``, in arrival order
        (ties broken by send order)."""
        out: list[Delivery] = []
        while self._in_flight and self._in_flight[0][0] <= now:
            out.append(heapq.heappop(self._in_flight)[2])
        self.stats.delivered += len(out)
        self.stats.bytes_delivered += sum(d.size_bytes for d in out)
        return out

    def next_arrival(self) -> float | None:
        """Arrival time of the earliest message still in flight, or ``None``."""
        return self._in_flight[0][0] if self._in_flight else None

    def pending(self) -> int:
        """Number of messages in flight (sent, not dropped, not yet polled)."""
        return len(self._in_flight)

    @property
    def window_bytes(self) -> int:
        """A reliable link's congestion window in bytes (what one round trip carries now)."""
        return int(self.window.cwnd * self.mss_bytes)

    @property
    def link_free_at(self) -> float:
        """Virtual time at which the sender's queue drains (``-inf`` if never used)."""
        return self._link_free_at


# -- parse helpers for CLIs ----------------------------------------------------

_NUMBER = r"([+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)"
_DURATION_RE = re.compile(rf"^\s*{_NUMBER}\s*(us|usec|ms|msec|s|sec|secs)?\s*$", re.IGNORECASE)
_RATE_RE = re.compile(rf"^\s*{_NUMBER}\s*([a-z]*)\s*$", re.IGNORECASE)
_LOSS_RE = re.compile(rf"^\s*{_NUMBER}\s*(%?)\s*$")
_SIZE_RE = re.compile(rf"^\s*{_NUMBER}\s*([kmg]?)b?\s*$", re.IGNORECASE)
_SIZE_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30}

_DURATION_TO_MS = {None: 1.0, "us": 1e-3, "usec": 1e-3, "ms": 1.0, "msec": 1.0, "s": 1e3, "sec": 1e3, "secs": 1e3}

# tc(8) units: "...bit" are bits per second, "...bps" are BYTES per second.
_RATE_TO_MBIT = {
    "": 1.0,  # a bare number is Mbit/s
    "bit": 1e-6,
    "kbit": 1e-3,
    "mbit": 1.0,
    "gbit": 1e3,
    "tbit": 1e6,
    "bps": 8e-6,
    "kbps": 8e-3,
    "mbps": 8.0,
    "gbps": 8e3,
    "tbps": 8e6,
}


def parse_duration_ms(text: str | float) -> float:
    """Parse a netem-style duration into milliseconds.

    ``"20ms"``, ``"0.02s"``, ``"500us"`` and bare numbers (milliseconds, e.g.
    ``"20"``) are accepted; the result must be finite and >= 0.
    """
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value = float(text)
    else:
        m = _DURATION_RE.match(str(text))
        if m is None:
            raise ValueError(f"cannot parse duration {text!r}: expected e.g. '20ms', '0.02s', '500us' or '20'")
        unit = m.group(2).lower() if m.group(2) else None
        value = float(m.group(1)) * _DURATION_TO_MS[unit]
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"duration {text!r} must be finite and >= 0")
    return value


def parse_rate_mbit(text: str | float) -> float:
    """Parse a tc-style rate into Mbit/s.

    ``"200mbit"``, ``"1gbit"``, ``"500kbit"``, ``"9600bit"``; bare numbers are
    Mbit/s.  As in tc(8), ``"...bps"`` units mean *bytes* per second
    (``"1mbps"`` == 8 Mbit/s).  The result must be finite and > 0.
    """
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value = float(text)
    else:
        m = _RATE_RE.match(str(text))
        unit = m.group(2).lower() if m else None
        if m is None or unit not in _RATE_TO_MBIT:
            raise ValueError(
                f"cannot parse rate {text!r}: expected e.g. '200mbit', '1gbit', '500kbit' or a bare Mbit/s number"
            )
        value = float(m.group(1)) * _RATE_TO_MBIT[unit]
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"rate {text!r} must be finite and > 0")
    return value


def parse_loss(text: str | float) -> float:
    """Parse a loss probability into a fraction in ``[0, 1)``.

    ``"0.5%"`` -> 0.005; a bare number is already a fraction (``"0.005"``).
    """
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value, percent = float(text), False
    else:
        m = _LOSS_RE.match(str(text))
        if m is None:
            raise ValueError(f"cannot parse loss {text!r}: expected a percentage like '0.5%' or a fraction like '0.005'")
        percent = m.group(2) == "%"
        value = float(m.group(1)) / (100.0 if percent else 1.0)
    if not (0.0 <= value < 1.0):
        hint = "" if percent or value < 1.0 else f" (did you mean '{text}%'?)"
        raise ValueError(f"loss {text!r} must be in [0, 1) as a fraction or [0%, 100%) as a percentage{hint}")
    return value


def parse_bytes(text: str | int, minimum: int = 1) -> int:
    """Parse a size in bytes, tc-style: ``"64k"`` / ``"64kb"`` (KiB), ``"16m"`` (MiB), ``"1g"``, or a bare number of
    bytes. The result must be a whole number of bytes, at least ``minimum`` (a queue needs one; a limit may be 0)."""
    if isinstance(text, int) and not isinstance(text, bool):
        value = float(text)
    else:
        m = _SIZE_RE.match(str(text))
        if m is None:
            raise ValueError(f"cannot parse size {text!r}: expected e.g. '64k', '16m' or a number of bytes")
        value = float(m.group(1)) * _SIZE_UNITS[m.group(2).lower()]
    if not math.isfinite(value) or value < minimum:
        raise ValueError(f"size {text!r} must be at least {minimum} byte{'' if minimum == 1 else 's'}")
    return int(value)
