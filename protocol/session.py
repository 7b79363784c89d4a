"""The session core, sans-I/O (after h11 / aioquic): events in, decisions out, no sockets, no clocks, no GL.

One :class:`ServerSession` per client on the server and one :class:`ClientSession` in the client hold every
decision a streaming session makes; the drivers only move bytes and run the method's GL work:

- the virtual-time replay (:mod:`quadcast.sim.replay`) feeds them events stamped with virtual time;
- the live asyncio server and client (:mod:`quadcast.server.app`, :mod:`quadcast.client.app`) feed them the same
  events stamped with their event loop's clock.

So the same events give the same decisions in both (``tests/test_session.py`` checks it).

Server side -- events: :meth:`ServerSession.pose_received`, :meth:`~ServerSession.reference_requested`,
:meth:`~ServerSession.frame_encoded`, :meth:`~ServerSession.frame_sent`, :meth:`~ServerSession.report_received`;
decisions: :class:`EncodeFrame` (render and encode for this predicted pose and display time, self-contained or
not, at this operating point, with how far the head strayed from the last frames' predicted rotations and where
the viewer looks) and the frames to send, in order, from :meth:`~ServerSession.next_to_send` (a bounded queue that
drops stale frames but never breaks a reference chain). With a rate controller (``ServerSessionConfig.rate``,
:mod:`quadcast.protocol.rate`) the session also picks each frame's operating point from the client's receive reports
and holds new frames back while the link is backed up.

Client side -- events: :meth:`ClientSession.frame_arrived`, :meth:`~ClientSession.frame_received`,
:meth:`~ClientSession.frame_processed`, :meth:`~ClientSession.frames_dropped`, :meth:`~ClientSession.tick`,
:meth:`~ClientSession.connected`; decisions: :class:`SendReport` (tell the server when a frame arrived), whether
to apply or skip a frame (dependent frames are skipped while the client waits for a self-contained one) and
:class:`RequestReference` (ask the server for a self-contained frame, again every ``reference_timeout_s`` while
one is still needed).

Times are seconds on the driver's clock (``now``); poses carry the client's clock (``t_client``).
"""
from __future__ import annotations

import collections
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from quadcast.protocol.pose import MAX_POSITION_M, MAX_TIME_S, check_gaze
from quadcast.protocol.prediction import PosePredictor, PredictorSettings
from quadcast.protocol.rate import OperatingPoint, RateConfig, RateController

__all__ = ["ServerSessionConfig", "ServerSession", "ServerCounters", "EncodeFrame", "FrameQueue", "QueueCounters",
           "ClientSession", "ClientCounters", "RequestReference", "SendReport"]

ENCODE_EMA = 0.2
"""Weight of the newest encode time in the server's running estimate."""

POSE_INTERVAL_EMA = 0.2
"""Weight of the newest pose interval in the server's running estimate (the frame rate the controller plans for)."""

MISS_FRAMES = 8
"""How many of the last frames' rotation misses :meth:`ServerSession.rotation_miss_deg` averages."""


# ------------------------------------------------------------------------------------------------- queue

@dataclass
class QueueCounters:
    """What a :class:`FrameQueue` did."""

    pushed: int = 0
    dropped_stale: int = 0     # queued frames made useless by a newer self-contained frame
    dropped_new: int = 0       # frames refused because the queue was full or their chain was broken


class FrameQueue:
    """A bounded send queue that drops stale frames without breaking decoding (sans-I/O).

    Every frame that is not self-contained (a QUASAR residual, or an H.264 P-frame of any method) depends on all
    frames since the last self-contained one, so the queue never drops a frame that a queued or later one depends
    on:

    - a self-contained frame replaces everything still queued (nothing after it needs them);
    - a dependent frame is queued if there is room; when the queue is full it is refused instead, the chain is
      *broken*, and every later dependent frame is refused too until a self-contained one arrives. :meth:`push`
      returns True in that case: the next frame must be self-contained.

    So the queue holds at most ``max_frames`` frames, and what it hands out is always decodable in order.
    """

    def __init__(self, max_frames: int = 3) -> None:
        if max_frames < 1:
            raise ValueError(f"FrameQueue: max_frames must be >= 1, got {max_frames}")
        self.max_frames = max_frames
        self._frames: collections.deque = collections.deque()
        self.broken = False
        self.counters = QueueCounters()

    def __len__(self) -> int:
        return len(self._frames)

    def push(self, frame: Any, self_contained: bool) -> bool:
        """Offer a frame (any object); returns True when the next frame must be self-contained."""
        self.counters.pushed += 1
        if self_contained:
            self.counters.dropped_stale += len(self._frames)
            self._frames.clear()
            self._frames.append(frame)
            self.broken = False
        elif self.broken or len(self._frames) >= self.max_frames:
            self.counters.dropped_new += 1
            self.broken = True
        else:
            self._frames.append(frame)
        return self.broken

    def pop(self) -> Any | None:
        """The oldest queued frame, or None."""
        return self._frames.popleft() if self._frames else None


# ------------------------------------------------------------------------------------------------ server

@dataclass(frozen=True)
class ServerSessionConfig:
    """How a server session predicts and queues.

    ``downlink_s`` is the expected time from a frame's send to its display (link latency, plus whatever the client
    adds). A frame is shown from then until the next one replaces it, one frame interval later
    (:meth:`ServerSession.display_interval_s`), so it is predicted for ``hold_share`` of the way into that time (0.5:
    its middle, where the pose error over the time it is shown is least): the client's clock now + the running
    encode-time estimate + ``downlink_s`` + ``hold_share`` times the interval, at most ``max_prediction_s`` ahead.
    The encode-time estimate starts at ``encode_s`` and takes the first frame's measured time as it is, then a
    running mean. ``clock_offset_s`` is the client's clock minus the driver's
    clock when it is known (0 in virtual time, where both share one clock); ``None`` estimates it from the newest
    pose (its ``t_client`` minus its arrival time), as a live server must. Frames start at least
    ``min_frame_interval_s`` apart (a flood guard: poses that come faster coalesce, and the frame for the newest one
    starts when the interval has passed -- see :meth:`ServerSession.timer`). ``idle_timeout_s``: a session whose
    client sent no *pose traffic* for this long is to be ended (:meth:`ServerSession.idle_deadline`); only a pose
    the predictor takes (valid, newer than the last by at least its minimum step) counts -- reference requests,
    repeated or stale poses do not (None: never).
    """

    predict: bool = True
    predictor: PredictorSettings | None = None   # None: quadcast.protocol.prediction.DEFAULT_PREDICTOR
    downlink_s: float = 0.04
    max_prediction_s: float = 0.5
    hold_share: float = 0.5
    encode_s: float = 0.0
    clock_offset_s: float | None = None
    queue_frames: int = 3
    min_frame_interval_s: float = 0.0
    idle_timeout_s: float | None = None
    rate: RateConfig | None = None
    point: OperatingPoint | None = None

    def __post_init__(self) -> None:
        if self.idle_timeout_s is not None and not (np.isfinite(self.idle_timeout_s) and self.idle_timeout_s > 0):
            raise ValueError(f"ServerSessionConfig.idle_timeout_s: expected a finite number > 0 or None, "
                             f"got {self.idle_timeout_s!r}")
        for name in ("downlink_s", "max_prediction_s", "encode_s", "min_frame_interval_s"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"ServerSessionConfig.{name}: expected a finite number >= 0, got {v!r}")
        if not (np.isfinite(self.hold_share) and 0 <= self.hold_share <= 1):
            raise ValueError(f"ServerSessionConfig.hold_share: expected a number in [0, 1], got {self.hold_share!r}")
        if self.queue_frames < 1:
            raise ValueError(f"ServerSessionConfig.queue_frames: expected >= 1, got {self.queue_frames}")
        if self.rate is not None and self.point is not None:
            raise ValueError("ServerSessionConfig: a fixed point and a rate controller exclude each other")


@dataclass(frozen=True)
class EncodeFrame:
    """Decision: render and encode one frame for ``position``/``quat`` at scene time ``display_t`` (the client's
    clock when it is expected to be shown); ``reference``: it must be self-contained."""

    position: np.ndarray
    quat: np.ndarray
    display_t: float
    reference: bool
    started: float        # driver clock when the decision was made
    point: OperatingPoint | None = None    # the operating point to encode at (None: the method's own settings)
    point_index: int | None = None         # its index in the rate controller's ladder
    # how far the head's rotation strayed from the predicted one while recent frames were shown (degrees;
    # ServerSession.rotation_miss_deg): what a view wider than the frame must cover. None: not measured yet
    rotation_miss_deg: float | None = None
    # where the viewer looked (degrees from the view axis, right and up) as the newest pose taken said: what a
    # foveated frame centres on. None: that pose carried no gaze
    gaze_deg: tuple[float, float] | None = None


@dataclass
class ServerCounters:
    """What a server session received and decided."""

    poses: int = 0
    poses_ignored: int = 0        # out of order or duplicate
    gazes: int = 0                # poses taken that carried the viewer's gaze
    reference_requests: int = 0
    frames_encoded: int = 0
    encode_s_total: float = 0.0
    reports: int = 0              # receive reports taken by the rate controller
    frames_paced: int = 0         # frame starts the rate controller held back (the link was backed up)


class ServerSession:
    """One client's session on the server (see the module docstring).

    Policy: a pose received while the encoder is idle starts a frame at once; poses received while it is busy
    coalesce, and the frame after it starts as soon as it finishes, for the newest pose (and no sooner than
    ``min_frame_interval_s`` after the one before). A reference request makes
    the next frame self-contained, and so does a frame the send queue had to refuse. With a rate controller a
    frame also waits while the controller says the link is backed up (:meth:`report_received` starts it when a
    report shows the backlog gone, or the next pose does), and each frame is made at the point it chooses.
    """

    def __init__(self, config: ServerSessionConfig | None = None) -> None:
        self.config = config or ServerSessionConfig()
        self.predictor = PosePredictor(self.config.predictor)
        self.queue = FrameQueue(self.config.queue_frames)
        self.counters = ServerCounters()
        self.encode_estimate_s = self.config.encode_s
        self._latest: tuple[float, float, np.ndarray, np.ndarray] | None = None   # arrival, t_client, p, q
        self._gaze: tuple[float, float] | None = None    # the gaze the newest pose taken carried
        self._want_reference = False
        self._encoding = False
        self._pose_pending = False
        self._last_start: float | None = None
        self._last_traffic: float | None = None     # driver clock of the session's start / newest pose taken
        self.rate = RateController(self.config.rate) if self.config.rate is not None else None
        self.pose_interval_s: float | None = None   # running estimate of the time between poses
        self._encoding_point: int | None = None      # ladder index of the frame being encoded
        # (frame, ladder index, self-contained) of the frames that may still be queued
        self._queued_points: collections.deque = collections.deque(maxlen=self.config.queue_frames + 2)
        self._popped_point: tuple[int | None, bool] = (None, False)    # (point, self-contained) of the frame popped
        self._paced = False                          # the last start was held back by the rate controller
        # frames being shown or about to be: [start, end of the expected hold (client clock), predicted rotation,
        # the largest angle (degrees) between it and a pose the client sent within the hold so far]
        self._aims: collections.deque = collections.deque(maxlen=MISS_FRAMES)
        self._misses: collections.deque = collections.deque(maxlen=MISS_FRAMES)   # finished frames' largest angles

    # -- events

    def opened(self, now: float) -> None:
        """The session started (its client was welcomed): the idle clock starts."""
        self._last_traffic = float(now)

    def pose_received(self, now: float, t_client: float, position, quat,
                      gaze_deg: tuple[float, float] | None = None) -> EncodeFrame | None:
        """A client pose arrived at ``now``, with the viewer's gaze at its time if the client tracks it (degrees,
        :func:`quadcast.protocol.pose.check_gaze`). Raises ValueError for a pose the predictor cannot use or a gaze
        out of bounds."""
        self.counters.poses += 1
        gaze = None if gaze_deg is None else check_gaze("gaze", gaze_deg)
        if not self.predictor.observe(t_client, position, quat):
            self.counters.poses_ignored += 1
            return None
        self._gaze = gaze
        self.counters.gazes += gaze is not None
        latest = self.predictor.latest
        self._check_aims(latest.t, latest.quat)
        if self._latest is not None:
            dt = latest.t - self._latest[1]
            self.pose_interval_s = dt if self.pose_interval_s is None else \
                (1 - POSE_INTERVAL_EMA) * self.pose_interval_s + POSE_INTERVAL_EMA * dt
        self._latest = (float(now), latest.t, latest.position, latest.quat)
        self._last_traffic = float(now)
        self._pose_pending = True
        return self._maybe_start(now)

    def _check_aims(self, t_client: float, quat: np.ndarray) -> None:
        """Compare a pose the client sent with the rotation predicted for the frames shown at its time."""
        q = np.asarray(quat, np.float64)
        while self._aims and self._aims[0][1] < t_client:
            self._misses.append(self._aims.popleft()[3])
        for aim in self._aims:
            if aim[0] <= t_client:
                cos_half = min(1.0, abs(float(np.dot(aim[2], q))))
                aim[3] = max(aim[3], float(np.degrees(2.0 * np.arccos(cos_half))))

    def rotation_miss_deg(self) -> float | None:
        """The mean over the last :data:`MISS_FRAMES` frames shown of the largest angle between a frame's predicted
        rotation and the client's poses while it was shown (None before a frame's hold has passed)."""
        return float(np.mean(self._misses)) if self._misses else None

    def reference_requested(self, now: float) -> None:
        """The client lost its reference state: the next frame is self-contained."""
        self.counters.reference_requests += 1
        self._want_reference = True

    def frame_encoded(self, now: float, frame: Any, self_contained: bool, encode_s: float) -> EncodeFrame | None:
        """The frame of the last :class:`EncodeFrame` is ready (``encode_s`` after it started): it joins the send
        queue, and the next frame starts at once if a newer pose arrived meanwhile."""
        self._encoding = False
        self.counters.frames_encoded += 1
        self.counters.encode_s_total += encode_s
        # the first measurement replaces the configured guess (a live server's 0 would take five frames to outgrow)
        weight = 1.0 if self.counters.frames_encoded == 1 else ENCODE_EMA
        self.encode_estimate_s = (1 - weight) * self.encode_estimate_s + weight * encode_s
        if self.queue.push(frame, self_contained):
            self._want_reference = True          # a frame was refused: the next one must stand alone
        if self.rate is not None:
            self._queued_points.append((frame, self._encoding_point, bool(self_contained)))
        return self._maybe_start(now)

    def frame_sent(self, now: float, frame_id: int, size_bytes: int) -> None:
        """The driver handed the frame :meth:`next_to_send` gave it last (id ``frame_id``, ``size_bytes`` of payload)
        to the transport."""
        if self.rate is not None:
            self.rate.frame_sent(now, frame_id, size_bytes, *self._popped_point)

    def report_received(self, now: float, entries) -> EncodeFrame | None:
        """The client's receive report (``(frame_id, bytes, t_arrive)`` entries, arrival on the client's clock)
        arrived: the rate controller takes it, and a frame held back for the link may start now."""
        if self.rate is None:
            return None
        self.counters.reports += 1
        self.rate.report(now, entries, self.frame_interval_s())
        return self._maybe_start(now)

    def frame_interval_s(self) -> float:
        """The time between frames the rate controller plans for: the pose interval or the encode time, whichever
        is longer (and no less than the flood guard's interval)."""
        interval = max(self.pose_interval_s or 0.0, self.encode_estimate_s, self.config.min_frame_interval_s)
        return interval if interval > 0 else 1.0 / 30.0

    def display_interval_s(self) -> float:
        """How long a frame is expected to be shown: the time until the next one, which starts no sooner than the
        least interval between starts allows (:meth:`frame_interval_s`, :meth:`min_interval_s`)."""
        return max(self.frame_interval_s(), self.min_interval_s())

    @property
    def point(self) -> OperatingPoint | None:
        """The operating point the next frame is made at (None: the method's own settings)."""
        return self.rate.point if self.rate is not None else self.config.point

    def min_interval_s(self) -> float:
        """The least time between two frame starts: the flood guard's, or the current point's frame rate cap."""
        point = self.point
        return max(self.config.min_frame_interval_s, 1.0 / point.fps if point is not None else 0.0)

    def timer(self) -> float | None:
        """When :meth:`handle_timer` must be called next (driver clock), or None: a pose waits for the flood
        guard's interval (or the operating point's frame rate) while the encoder is idle. A pose the rate controller
        holds back waits for a report or the next pose instead (no timer)."""
        if self._encoding or not self._pose_pending or self._last_start is None or self._paced:
            return None
        return self._last_start + self.min_interval_s()

    def handle_timer(self, now: float) -> EncodeFrame | None:
        """The time :meth:`timer` named has come (a driver whose clock rounds past it by a microsecond or less
        starts the frame at the time named, so every driver decides alike)."""
        t = self.timer()
        if t is not None and abs(now - t) <= 1e-6:
            now = t
        return self._maybe_start(now)

    def idle_deadline(self) -> float | None:
        """When the session is to be ended for want of pose traffic (driver clock), or None (no idle timeout, or
        not :meth:`opened`). Only poses the predictor takes move it (see :class:`ServerSessionConfig`)."""
        if self.config.idle_timeout_s is None or self._last_traffic is None:
            return None
        return self._last_traffic + self.config.idle_timeout_s

    def next_to_send(self) -> Any | None:
        """The next frame for the transport, in order (None when the queue is empty)."""
        frame = self.queue.pop()
        if frame is not None and self.rate is not None:
            self._popped_point = next(((i, sc) for f, i, sc in self._queued_points if f is frame), (None, False))
        return frame

    # -- state

    @property
    def encoding(self) -> bool:
        return self._encoding

    def client_clock(self, now: float) -> float:
        """The client's clock at driver time ``now``."""
        if self.config.clock_offset_s is not None:
            return now + self.config.clock_offset_s
        arrival, t_client, _, _ = self._latest
        return t_client + (now - arrival)

    def _maybe_start(self, now: float) -> EncodeFrame | None:
        if self._encoding or not self._pose_pending:
            return None
        if self._last_start is not None and now < self._last_start + self.min_interval_s() - 1e-9:
            return None
        if self.rate is not None and not self.rate.may_start(now, self.frame_interval_s()):
            self.counters.frames_paced += 1
            self._paced = True
            return None
        self._paced = False
        self._pose_pending = False
        self._last_start = now
        return self._start(now)

    def _start(self, now: float) -> EncodeFrame:
        cfg = self.config
        lead = min(self.encode_estimate_s + cfg.downlink_s + cfg.hold_share * self.display_interval_s(),
                   cfg.max_prediction_s)
        display_t = self.client_clock(now) + lead
        _, _, position, quat = self._latest
        if cfg.predict:
            predicted = self.predictor.predict(display_t)
            # the predictor's output is finite by construction; should it ever not be, render the pose as received
            if all(np.all(np.isfinite(v)) for v in predicted) and np.linalg.norm(predicted[1]) > 0.5:
                position, quat = predicted
        reference, self._want_reference = self._want_reference, False
        self._encoding = True
        point, index = self.config.point, None
        if self.rate is not None:
            index = self._encoding_point = self.rate.choose(now, self.frame_interval_s())
            point = self.rate.points[index]
        # a decision is always a pose the wire format accepts (the client checks the frame's pose as we check
        # the client's): extrapolation past the edge of the range stops at it
        position = np.clip(np.asarray(position, np.float64), -MAX_POSITION_M, MAX_POSITION_M)
        display_t = float(np.clip(display_t, -MAX_TIME_S, MAX_TIME_S))
        quat = np.asarray(quat, np.float64)
        # shown from its arrival until the next frame's, about one interval: the hold the miss is measured over
        hold = self.display_interval_s()
        arrival = display_t - cfg.hold_share * hold
        self._aims.append([arrival, arrival + hold, quat / np.linalg.norm(quat), 0.0])
        return EncodeFrame(position, quat, display_t, reference, float(now), point, index, self.rotation_miss_deg(),
                           self._gaze)


# ------------------------------------------------------------------------------------------------ client

@dataclass(frozen=True)
class RequestReference:
    """Decision: ask the server for a self-contained frame (``reason`` says why)."""

    reason: str


@dataclass(frozen=True)
class SendReport:
    """Decision: tell the server these frames arrived (``(frame_id, bytes, t_arrive)`` entries; a
    :class:`quadcast.protocol.messages.ReceiveReport`)."""

    entries: tuple


@dataclass
class ClientCounters:
    """What a client session received and decided."""

    frames_arrived: int = 0
    frames_received: int = 0
    frames_applied: int = 0
    frames_rejected: int = 0
    frames_skipped: int = 0      # dependent frames ignored while waiting for a self-contained one
    frames_lost: int = 0         # gaps in the server's frame ids
    reference_requests: int = 0
    rejections: list = field(default_factory=list)   # the first few reasons


class ClientSession:
    """The client's side of a session (see the module docstring).

    The client waits for a self-contained frame after connecting, after a gap in the server's frame ids and after
    frames were dropped before it could process them; until one arrives it skips dependent frames. It asks for a
    reference when it has evidence that it needs one (a frame skipped or rejected, or the method client saying it
    lost its reference), at most every ``reference_timeout_s`` while the need lasts -- never merely because nothing
    has arrived yet.
    """

    MAX_REASONS = 8

    def __init__(self, reference_timeout_s: float = 1.5) -> None:
        self.reference_timeout_s = float(reference_timeout_s)
        self.counters = ClientCounters()
        self.awaiting_self_contained = True
        self.needs_reference = False       # the method client's own view, from frame_processed
        self.last_frame_id: int | None = None
        self._last_request: float | None = None
        self._evidence = ""                # why a reference is needed, since the last request

    # -- events

    def frame_arrived(self, now: float, frame_id: int, size_bytes: int) -> SendReport:
        """A frame's last byte arrived off the network at ``now`` (the clock the client's poses carry), before
        it is decoded or applied: report it to the server at once (its rate controller times the link with it)."""
        self.counters.frames_arrived += 1
        return SendReport(((int(frame_id), int(size_bytes), float(now)),))

    def connected(self, now: float) -> None:
        """A (re)connection: nothing received before it can be continued."""
        self.awaiting_self_contained = True
        self.last_frame_id = None

    def announce_reports(self) -> SendReport:
        """What a client that reports arrivals sends right after it connects: an empty report, which tells the
        server's rate controller so (a slow first frame is then not taken for a client that never reports)."""
        return SendReport(())

    def frame_received(self, now: float, frame_id: int, self_contained: bool) -> bool:
        """A frame arrived; returns True to apply it, False to skip it."""
        c = self.counters
        c.frames_received += 1
        if self.last_frame_id is not None and frame_id > self.last_frame_id + 1:
            c.frames_lost += frame_id - self.last_frame_id - 1
            self.awaiting_self_contained = True
        self.last_frame_id = frame_id if self.last_frame_id is None else max(self.last_frame_id, frame_id)
        if self.awaiting_self_contained and not self_contained:
            c.frames_skipped += 1
            self._evidence = self._evidence or "waiting for a self-contained frame"
            return False
        return True

    def frame_processed(self, now: float, applied: bool, needs_reference: bool,
                        reason: str = "") -> RequestReference | None:
        """The method client applied (or rejected, with ``reason``) a frame; ``needs_reference`` is its state."""
        c = self.counters
        if applied:
            c.frames_applied += 1
            self.awaiting_self_contained = False
        else:
            c.frames_rejected += 1
            if len(c.rejections) < self.MAX_REASONS:
                c.rejections.append(reason)
            self._evidence = self._evidence or reason or "frame rejected"
        self.needs_reference = needs_reference
        if needs_reference:
            self._evidence = self._evidence or "reference missing"
        return self.tick(now)

    def frames_dropped(self, now: float, count: int, reason: str = "frames dropped before processing") -> None:
        """The driver dropped ``count`` received frames unprocessed (unreadable, or its inbox overflowed)."""
        self.counters.frames_skipped += count
        self.awaiting_self_contained = True
        self._evidence = self._evidence or reason

    def tick(self, now: float) -> RequestReference | None:
        """Whether to ask for a reference now."""
        if not (self.needs_reference or self.awaiting_self_contained):
            self._evidence = ""
            self._last_request = None
            return None
        if not self._evidence:
            return None
        if self._last_request is not None and now - self._last_request < self.reference_timeout_s:
            return None
        self._last_request = now
        self.counters.reference_requests += 1
        reason, self._evidence = self._evidence, ""
        return RequestReference(reason)
