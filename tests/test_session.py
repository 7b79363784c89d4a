"""The session core (quadcast.protocol.session): its decisions, and the same decisions from both of its drivers.

The cross-driver test runs one event sequence through the virtual-time replay (quadcast.sim.replay) and through the
live server's asyncio session (quadcast.server.app.Session) -- the latter on an event loop whose clock is virtual,
with a fake channel and a fake worker -- and checks that every decision is identical; with a rate controller
too (receive reports in, each frame's operating point and the frames held back out), over a slow downlink.
"""
from __future__ import annotations

import asyncio
import heapq
import types

import numpy as np
import pytest

from quadcast.protocol.messages import Bye, Frame, Hello, PoseUpdate, ReceiveReport, ReferenceRequest, Welcome
from quadcast.protocol.rate import Ladder, OperatingPoint, RateConfig
from quadcast.protocol.session import (ClientSession, EncodeFrame, FrameQueue, RequestReference, ServerSession,
                                       ServerSessionConfig)
from quadcast.render.gaze import GazeTrace
from quadcast.transport.channel import Channel
from stubs import StubClient, StubServer

Q0 = np.array([0.0, 0.0, 0.0, 1.0])


def _pose(x: float) -> tuple[np.ndarray, np.ndarray]:
    return np.array([x, 1.6, 0.0]), Q0


# ------------------------------------------------------------------------------------------ send queue

def test_frame_queue_drops_stale_frames_but_never_a_dependency():
    q = FrameQueue(max_frames=2)
    assert q.push("r0", self_contained=True) is False
    assert q.push("d1", self_contained=False) is False
    # full: the new dependent frame is refused (not the frame it depends on) and a self-contained one is needed
    assert q.push("d2", self_contained=False) is True
    # later dependent frames depend on the refused one: refused too, until a self-contained frame comes
    assert q.push("d3", self_contained=False) is True
    assert q.pop() == "r0"
    assert q.push("d4", self_contained=False) is True
    # a self-contained frame replaces the stale queue (newest wins) and mends the chain
    assert q.push("r5", self_contained=True) is False
    assert len(q) == 1 and q.pop() == "r5" and q.pop() is None
    assert q.push("d6", self_contained=False) is False and q.pop() == "d6"
    c = q.counters
    assert (c.pushed, c.dropped_new, c.dropped_stale) == (7, 3, 1)
    with pytest.raises(ValueError, match="max_frames"):
        FrameQueue(0)


# -------------------------------------------------------------------------------------------- server

def test_server_encodes_each_pose_and_predicts_the_display_time():
    s = ServerSession(ServerSessionConfig(downlink_s=0.05, clock_offset_s=0.0, hold_share=0.0))
    d = s.pose_received(0.0, 0.0, *_pose(0.0))
    assert isinstance(d, EncodeFrame) and d.display_t == pytest.approx(0.05) and not d.reference
    assert s.pose_received(0.01, 0.01, *_pose(0.01)) is None          # busy: coalesces
    assert s.pose_received(0.02, 0.02, *_pose(0.02)) is None
    d = s.frame_encoded(0.03, "f0", True, 0.03)                       # the next frame starts at once, newest pose
    assert d is not None and d.started == 0.03
    # constant velocity 1 m/s along x, extrapolated to the display time: the first encode time taken as it is
    assert d.display_t == pytest.approx(0.03 + 0.03 + 0.05)
    assert d.position[0] == pytest.approx(d.display_t, abs=1e-9)
    assert s.next_to_send() == "f0" and s.next_to_send() is None
    assert s.frame_encoded(0.05, "f1", False, 0.02) is None           # nothing new arrived
    assert s.pose_received(0.04, 0.015, *_pose(0.015)) is None         # out of order: ignored
    assert s.counters.poses_ignored == 1 and s.counters.frames_encoded == 2


def test_server_aims_each_frame_into_the_time_it_is_shown():
    """A frame is shown from its arrival until the next one replaces it: it is predicted for hold_share of the way
    into that time. Here the encoder sets the pace (0.2 s a frame, poses every 10 ms), so the interval is the
    running encode-time estimate: the first frame's time, then a running mean."""
    share, downlink = 0.5, 0.04
    s = ServerSession(ServerSessionConfig(downlink_s=downlink, clock_offset_s=0.0, hold_share=share))
    d = s.pose_received(0.0, 0.0, *_pose(0.0))
    assert d.display_t == pytest.approx(downlink + share / 30)         # nothing measured yet: 30 frames/s assumed
    now = 0.0
    for k in range(1, 21):                                             # poses every 10 ms while it encodes
        s.pose_received(now + 0.01 * k, now + 0.01 * k, *_pose(now + 0.01 * k))
    d = s.frame_encoded(0.2, "f0", True, 0.2)
    assert s.encode_estimate_s == pytest.approx(0.2) and s.display_interval_s() == pytest.approx(0.2)
    assert d.display_t == pytest.approx(0.2 + 0.2 + downlink + share * 0.2)
    assert d.position[0] == pytest.approx(d.display_t, abs=1e-9)      # 1 m/s along x, extrapolated to it
    for k in range(1, 11):
        s.pose_received(0.2 + 0.01 * k, 0.2 + 0.01 * k, *_pose(0.2 + 0.01 * k))
    d = s.frame_encoded(0.3, "f1", False, 0.1)                        # a faster frame: the running mean
    estimate = 0.8 * 0.2 + 0.2 * 0.1
    assert s.encode_estimate_s == pytest.approx(estimate)
    assert d.display_t == pytest.approx(0.3 + estimate + downlink + share * estimate)
    # a frame rate cap longer than the encode time sets the interval instead
    capped = ServerSession(ServerSessionConfig(downlink_s=downlink, clock_offset_s=0.0, min_frame_interval_s=0.5,
                                               max_prediction_s=2.0))
    d = capped.pose_received(0.0, 0.0, *_pose(0.0))
    assert d.display_t == pytest.approx(downlink + 0.5 * 0.5)
    with pytest.raises(ValueError, match="hold_share"):
        ServerSessionConfig(hold_share=1.5)


def _yaw(deg: float) -> np.ndarray:
    half = np.radians(deg) / 2
    return np.array([0.0, np.sin(half), 0.0, np.cos(half)])


def _run_yaw(yaw, seconds: float = 2.0, encode_s: float = 0.3) -> tuple[ServerSession, list]:
    """Poses at 60 Hz along yaw(t) (degrees), an encoder taking `encode_s` a frame; returns the core and its
    decisions."""
    s = ServerSession(ServerSessionConfig(downlink_s=0.02, clock_offset_s=0.0))
    decisions, busy_until = [], None
    for k in range(int(seconds * 60)):
        t = k / 60
        if busy_until is not None and t >= busy_until:
            d = s.frame_encoded(busy_until, f"f{len(decisions)}", True, encode_s)
            busy_until = None
            if d is not None:
                decisions.append(d)
                busy_until = d.started + encode_s
        d = s.pose_received(t, t, np.array([0.0, 1.6, 0.0]), _yaw(yaw(t)))
        if d is not None:
            decisions.append(d)
            busy_until = t + encode_s
    return s, decisions


def test_server_measures_how_far_the_head_strayed_from_its_predictions():
    """Each frame's predicted rotation is compared with the poses the client sends while the frame is shown; the
    decisions carry the mean of the last frames' largest angles (None until a frame's hold has passed)."""
    still, decisions = _run_yaw(lambda t: 10.0)
    assert decisions[0].rotation_miss_deg is None and still.rotation_miss_deg() == pytest.approx(0.0, abs=1e-6)
    assert decisions[-1].rotation_miss_deg == pytest.approx(0.0, abs=1e-6)
    # turning steadily at 60 deg/s: predicted ~0.47 s ahead (encode 0.3 + link 0.02 + half the hold), of which the
    # damped horizon keeps ~0.24 s (14 deg short), and the head turns another 9 deg either side of the middle of
    # the 0.3 s it is shown: about 19 deg
    steady, _ = _run_yaw(lambda t: 60.0 * t)
    assert 10.0 < steady.rotation_miss_deg() < 30.0
    # shaking +-30 deg at 1.25 Hz: predictions overshoot at each reversal, and the miss is far larger
    shaking, decisions = _run_yaw(lambda t: 30.0 * np.sin(2 * np.pi * 1.25 * t))
    assert shaking.rotation_miss_deg() > steady.rotation_miss_deg() + 5.0
    assert decisions[-1].rotation_miss_deg is not None and decisions[-1].rotation_miss_deg > 0


def test_server_decisions_carry_the_gaze_of_the_newest_pose_taken():
    """A frame centres on the gaze its newest pose carried; a pose the predictor drops (out of order) does not move
    it, a pose without one says no gaze, and a gaze out of bounds is refused, naming it."""
    s = ServerSession(ServerSessionConfig(clock_offset_s=0.0))
    q = [0.0, 0.0, 0.0, 1.0]
    d = s.pose_received(0.0, 0.0, [0, 0, 0], q, (10.0, -5.0))
    assert d.gaze_deg == (10.0, -5.0)
    s.frame_encoded(0.01, "f0", True, 0.01)
    assert s.pose_received(0.05, -1.0, [0, 0, 0], q, (-30.0, 0.0)) is None      # older than the newest: ignored
    d = s.pose_received(0.06, 0.1, [0, 0, 0], q, (20.0, 2.0)) or s.handle_timer(1.0)
    assert d.gaze_deg == (20.0, 2.0)
    s.frame_encoded(1.01, "f1", False, 0.01)
    d = s.pose_received(1.05, 0.2, [0, 0, 0], q) or s.handle_timer(2.0)
    assert d.gaze_deg is None
    assert s.counters.gazes == 2 and s.counters.poses_ignored == 1
    with pytest.raises(ValueError, match="gaze: .*89 degrees"):
        s.pose_received(1.1, 0.3, [0, 0, 0], q, (0.0, 95.0))


def test_server_reference_requests_and_refused_frames_make_the_next_frame_self_contained():
    s = ServerSession(ServerSessionConfig(clock_offset_s=0.0, queue_frames=1))
    s.pose_received(0.0, 0.0, *_pose(0.0))
    s.reference_requested(0.01)
    s.pose_received(0.02, 0.02, *_pose(0.0))
    d = s.frame_encoded(0.03, "r0", True, 0.03)
    assert d.reference                                        # the request reaches the next frame
    s.pose_received(0.04, 0.04, *_pose(0.0))
    d = s.frame_encoded(0.05, "d1", False, 0.02)             # the queue is full (r0 unsent): d1 refused
    assert d.reference and s.queue.counters.dropped_new == 1
    assert s.next_to_send() == "r0" and s.next_to_send() is None


def test_server_estimates_the_client_clock_and_caps_the_horizon():
    s = ServerSession(ServerSessionConfig(downlink_s=0.04, max_prediction_s=0.1, predict=False, hold_share=0.0))
    d = s.pose_received(100.0, 7.0, *_pose(0.0))             # the client's clock is 93 s behind ours
    assert d.display_t == pytest.approx(7.04)
    s.frame_encoded(100.5, "f", True, 0.5)                   # a slow encode: the lead is capped
    d = s.pose_received(101.0, 8.0, *_pose(0.0))
    assert d.display_t == pytest.approx(8.0 + 0.1)


def test_server_flood_guard_defers_frames_to_its_timer():
    s = ServerSession(ServerSessionConfig(clock_offset_s=0.0, min_frame_interval_s=0.1))
    assert s.pose_received(0.0, 0.0, *_pose(0.0)) is not None
    assert s.frame_encoded(0.01, "f0", True, 0.01) is None
    assert s.timer() is None
    for k in range(1, 20):                                   # a flood of poses within the interval
        assert s.pose_received(0.01 + k * 1e-3, 0.01 + k * 1e-3, *_pose(0.0)) is None
    assert s.timer() == pytest.approx(0.1)
    assert s.handle_timer(0.05) is None
    d = s.handle_timer(0.1)
    assert d is not None and d.started == 0.1 and s.timer() is None
    assert s.counters.poses == 20


def test_server_rejects_bad_config():
    with pytest.raises(ValueError, match="downlink_s"):
        ServerSessionConfig(downlink_s=-1)
    with pytest.raises(ValueError, match="queue_frames"):
        ServerSessionConfig(queue_frames=0)


# -------------------------------------------------------------------------------------------- client

def test_client_waits_for_a_self_contained_frame_and_asks_on_evidence_only():
    c = ClientSession(reference_timeout_s=1.0)
    c.connected(0.0)
    assert c.tick(0.5) is None                                # nothing arrived: no request
    assert c.frame_received(0.6, 3, self_contained=False) is False     # joined mid-chain: skip
    r = c.tick(0.6)
    assert isinstance(r, RequestReference) and "self-contained" in r.reason
    assert c.frame_received(0.7, 4, self_contained=False) is False
    assert c.tick(0.7) is None                                # asked 0.1 s ago
    assert c.frame_received(1.7, 5, self_contained=False) is False
    assert c.tick(1.7) is not None                            # still needed, timeout passed: ask again
    assert c.frame_received(1.8, 6, self_contained=True) is True
    assert c.frame_processed(1.8, True, needs_reference=False) is None
    assert c.frame_received(1.9, 7, self_contained=False) is True
    assert c.frame_processed(1.9, True, needs_reference=False) is None
    k = c.counters
    assert (k.frames_received, k.frames_skipped, k.frames_applied, k.reference_requests) == (5, 3, 2, 2)


def test_client_loss_and_rejection():
    c = ClientSession(reference_timeout_s=1.0)
    c.connected(0.0)
    assert c.frame_received(0.0, 0, True) and c.frame_processed(0.0, True, False) is None
    # a gap in the frame ids: what follows depends on what was lost
    assert c.frame_received(0.1, 3, False) is False
    assert c.counters.frames_lost == 2 and c.tick(0.1) is not None
    assert c.frame_received(0.2, 4, True) and c.frame_processed(0.2, True, False) is None
    # a rejected frame that leaves the method client without its reference: ask at once
    assert c.frame_received(0.3, 5, False)
    r = c.frame_processed(0.3, False, needs_reference=True, reason="residual needs reference 2")
    assert r is not None and "reference 2" in r.reason and c.counters.rejections == ["residual needs reference 2"]
    # frames dropped unread (bad bytes, overflow) count as skipped and need a self-contained frame
    c.frames_dropped(0.4, 3, "receive queue overflowed")
    assert c.awaiting_self_contained and c.counters.frames_skipped == 4


# ------------------------------------------------------------------------------- one core, two drivers

class _Recording(ServerSession):
    """The server core, recording what it decided (and when)."""

    log: list

    def __init__(self, config=None):
        super().__init__(config)
        self.log, self.sent = [], []

    def _start(self, now):
        d = super()._start(now)
        self.log.append(("encode", d.started, d.position.tolist(), d.quat.tolist(), d.display_t, d.reference,
                         d.point_index, d.rotation_miss_deg, d.gaze_deg))
        return d

    def report_received(self, now, entries):
        self.log.append(("report", now, tuple(entries)))
        return super().report_received(now, entries)

    def frame_sent(self, now, frame_id, size_bytes):
        # kept apart: a message arriving at the very instant a frame is sent may be logged on either side of it
        self.sent.append((now, frame_id, size_bytes))
        return super().frame_sent(now, frame_id, size_bytes)

    def pose_received(self, now, t_client, position, quat, gaze_deg=None):
        self.log.append(("pose", now, t_client, gaze_deg))
        return super().pose_received(now, t_client, position, quat, gaze_deg)

    def reference_requested(self, now):
        self.log.append(("reference", now))
        return super().reference_requested(now)


def _virtual_time(loop: asyncio.AbstractEventLoop) -> None:
    """Make `loop` run on a virtual clock: when nothing is ready, time jumps to the next timer."""
    clock = [0.0]
    loop.time = lambda: clock[0]
    select = loop._selector.select

    def virtual_select(timeout=None):
        events = select(0)
        if not events and loop._scheduled and not loop._ready:
            clock[0] = max(clock[0], heapq.nsmallest(1, loop._scheduled)[0]._when)
        return events
    loop._selector.select = virtual_select


class _FakeChannel(Channel):
    """A channel fed by the test at exact (virtual) times; what the session sends is kept (it sends at once:
    nothing waits unsent, as :meth:`Channel.wait_sent` says by default)."""

    peer = "test"

    def __init__(self):
        self.inbox: asyncio.Queue = asyncio.Queue()
        self.sent: list = []
        self.bytes_out = 0

    async def recv(self):
        return await self.inbox.get()

    async def send(self, msg):
        self.sent.append(msg)

    async def close(self):
        pass


class _FakeWorker:
    """A session worker that takes exactly `delay` virtual seconds per frame."""

    kind, pid, death = "fake", 0, None

    def __init__(self, delay: float):
        self.delay, self.stub = delay, StubServer()
        self.died = asyncio.Event()

    async def encode(self, decision):
        from quadcast.protocol.frame import encode_frame_payload
        await asyncio.sleep(self.delay)
        p = self.stub.encode_decision(decision)
        return encode_frame_payload(p), p.self_contained

    async def close(self):
        pass


LADDER = Ladder(tuple(OperatingPoint(f"p{i}", crf=23 + i, mbps=m) for i, m in enumerate((0.1, 0.2, 0.4, 0.8))))


@pytest.mark.parametrize("server_delay_ms, adapt", [(0.0, False), (45.0, False), (0.0, True), (45.0, True)])
def test_replay_and_live_server_make_the_same_decisions(monkeypatch, server_delay_ms, adapt):
    import quadcast.server.app as app
    import quadcast.sim.replay as replay_mod
    from quadcast.protocol.admission import Admission
    from quadcast.render.traces import resolve_trace

    # 1. The virtual-time replay, with a lossy downlink so the client asks for references (with a rate controller:
    #    a downlink too slow for the best point, so the controller moves between points and holds frames back).
    sessions = []
    monkeypatch.setattr(replay_mod, "ServerSession", lambda cfg: sessions.append(_Recording(cfg)) or sessions[-1])
    cfg = replay_mod.ReplayConfig(latency_ms=30, jitter_ms=15, loss=0.0 if adapt else 0.15, seed=3,
                                  server_delay_ms=server_delay_ms, reference_timeout_s=0.2,
                                  rate_mbit=0.3 if adapt else None,
                                  rate=RateConfig(LADDER, start_mbps=1.0) if adapt else None,
                                  gaze=GazeTrace.parse("0 -10 5\n1000 20 -8\n2500 0 0\n"))
    replay_server = StubServer()
    replay_mod.replay(resolve_trace("builtin:walk"), replay_server, StubClient(), cfg, 180)
    replayed = sessions[0].log
    assert sum(1 for e in replayed if e[0] == "encode") > 40
    if adapt:
        core = sessions[0]
        assert sum(1 for e in replayed if e[0] == "report") > 40
        assert core.rate.state.decreases >= 1 and len({e[6] for e in replayed if e[0] == "encode"}) >= 2
        assert core.counters.frames_paced > 0
    else:
        assert any(e[0] == "reference" for e in replayed)           # the loss made the client ask
    if server_delay_ms:
        assert sum(1 for e in replayed if e[0] == "pose") > sum(1 for e in replayed if e[0] == "encode")

    # 2. The same events, at the same times, into the live server's session (virtual clock, fake I/O).
    session_config = cfg.server_session()
    live_sessions = []
    monkeypatch.setattr(app, "ServerSession", lambda c: live_sessions.append(_Recording(c)) or live_sessions[-1])

    workers = []

    class _Session(app.Session):
        async def _start_worker(self, hello):
            self.worker = _FakeWorker(server_delay_ms / 1e3)
            workers.append(self.worker)

    server = types.SimpleNamespace(
        config=types.SimpleNamespace(handshake_timeout=1e9, idle_timeout=1e9, max_sessions=1, methods=("quasar",),
                                     max_width=64, max_height=64, token="", server_hz=30.0, unsent_bytes=0,
                                     session_config=lambda: session_config),
        admission=Admission(), workers=set(), session_ended=lambda c: None)
    events = [e for e in replayed if e[0] in ("pose", "reference", "report")]
    trace = resolve_trace("builtin:walk")

    async def main():
        loop = asyncio.get_running_loop()
        _virtual_time(loop)
        channel = _FakeChannel()
        channel.inbox.put_nowait(Hello(1, "quasar", 32, 32, 60.0))
        at: dict[float, list] = {}          # messages arriving at the same instant keep their order
        for e in events:
            if e[0] == "pose":
                p, q = trace.pose_at(trace.times[0] + e[2])
                msg = PoseUpdate(0, e[2], p, q, e[3])
            elif e[0] == "report":
                msg = ReceiveReport(e[2])
            else:
                msg = ReferenceRequest("test")
            at.setdefault(e[1], []).append(msg)
        for when, msgs in at.items():
            loop.call_at(when, lambda m=msgs: [channel.inbox.put_nowait(x) for x in m])
        loop.call_at(events[-1][1] + 1.0, channel.inbox.put_nowait, Bye())
        await _Session(server, channel, 1, server.admission.open("test")).run()
        return channel

    loop = asyncio.new_event_loop()
    try:
        channel = loop.run_until_complete(main())
    finally:
        loop.close()
    assert isinstance(channel.sent[0], Welcome) and any(isinstance(m, Frame) for m in channel.sent)
    # The replay ends at its last display tick; the live session went on with what was pending then.
    end = 179 / 60 + 1e-9
    live = [e for e in live_sessions[0].log if e[1] <= end]
    assert events and live == replayed
    assert [e for e in live_sessions[0].sent if e[0] <= end] == sessions[0].sent
    # both drivers hand each decision's rotation miss to the method server before it encodes
    misses = replay_server.rotation_misses
    assert any(m is not None for m in misses) and workers[0].stub.rotation_misses[:len(misses)] == misses
    # ... and the gaze its newest pose carried: the replayed client sends its gaze trace with its poses
    gazes = replay_server.gazes
    assert len(set(gazes)) > 10 and workers[0].stub.gazes[:len(gazes)] == gazes


def test_replay_over_a_slow_tcp_link_holds_frames_back_as_the_live_server_does():
    # 20 kB frames at the pose rate (about 4.8 Mbit/s) into a 1 Mbit/s TCP downlink with a 32 kB queue, as
    # tests/test_live.py's slow link. The server takes its next frame
    # only once the link holds at most a window and `unsent_bytes` unsent, as the live server waits for its kernel's
    # unsent bytes: the frames wait in its queue, stale ones are dropped there, and the shown frames' age stays
    # bounded. Taking every frame at once (no wait), they fall further and further behind.
    import quadcast.sim.replay as replay_mod
    from quadcast.render.traces import resolve_trace

    def run(unsent_bytes):
        cfg = replay_mod.ReplayConfig(latency_ms=10, jitter_ms=0, rate_mbit=1.0, tcp=True, unsent_bytes=unsent_bytes,
                                      queue_bytes=32 * 1024, seed=1)
        totals = replay_mod.replay(resolve_trace("builtin:walk"), StubServer(size=20_000), StubClient(), cfg, 600)
        late = [age for t, age, _ in totals.ages if t > 7.0]
        return totals, float(np.mean(late))

    (held, held_age), (flooded, flooded_age) = run(16 * 1024), run(1 << 40)
    assert held.frames_sent < held.server.frames_encoded and flooded.frames_sent == flooded.server.frames_encoded
    assert all(b.t_sent >= a.t_sent for a, b in zip(held.sent, held.sent[1:]))
    assert held_age < 1000 < 3000 < flooded_age, (held_age, flooded_age)
