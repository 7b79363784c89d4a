"""Trace replay in virtual time (QUASAR §4.1.3): a client, a server and a link between them, on one clock.

This is the virtual-time driver of the session core (:mod:`quadcast.protocol.session`); the live server and
client drive the same core on their event loops. The client follows the trace at `client_hz` (60) and sends its
pose at `server_hz` (30) over the uplink; the server session decides, on each pose it receives, to render and
encode a frame for the pose predicted at the time the frame will be shown, and the payload crosses the downlink
(delay + jitter + size/rate, loss of whole messages, or with ``tcp`` of a TCP stream's segments, which are sent
again: :mod:`quadcast.sim.link`); the client session decides which arrived payloads to apply (dependent frames
wait for a self-contained one after a loss) and when to ask for a reference, and the client shows its newest state
reprojected to its true pose. Nothing depends on how fast the machine is: when it is slower than real time,
virtual time simply waits. The same seed gives the same run.

The downlink runs at a fixed rate or along a Mahimahi rate trace (:mod:`quadcast.sim.ratetrace`). The client
reports each frame's arrival (time and bytes) back to the server over a path with the uplink's latency and jitter
(its own random stream, so runs without a rate controller are what they were); with a rate controller
(``ReplayConfig.rate``) the server session picks each frame's operating point from those reports, and the
replay applies it to the method server before it encodes the frame. With a gaze trace (``ReplayConfig.gaze``)
the client sends the gaze with each pose, as a live client does (``PoseUpdate.gaze``), and the server foveates
around the one its newest pose carried; without one, around the view centre.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from quadcast.client.method import Coverage, MethodClient
from quadcast.codec.decoder import VideoError
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import FramePayload
from quadcast.protocol.messages import PoseUpdate, ReceiveReport, ReferenceRequest, encode_message
from quadcast.protocol.prediction import PredictorSettings
from quadcast.protocol.rate import OperatingPoint, RateConfig
from quadcast.protocol.session import (ClientSession, EncodeFrame, RequestReference, SendReport, ServerSession,
                                       ServerSessionConfig)
from quadcast.render.camera import Pose
from quadcast.render.gaze import GazeTrace
from quadcast.render.traces import Trace
from quadcast.server.method import MethodServer
from quadcast.sim.link import LinkModel
from quadcast.sim.ratetrace import RateTrace


@dataclass
class ReplayConfig:
    latency_ms: float = 20.0
    jitter_ms: float = 10.0
    rate_mbit: float | None = None
    loss: float = 0.0
    tcp: bool = False    # the downlink is one TCP stream: loss is of its segments, sent again (a reliable LinkModel)
    # with tcp: the server takes its next frame once the link holds at most a window and this many bytes unsent, as
    # the live server waits for its kernel's unsent bytes (quadcast server --unsent) behind the TCP link's model
    unsent_bytes: int = 16 * 1024
    queue_bytes: int | None = None   # with tcp: the drop-tail queue before the rate (None: it takes everything)
    client_hz: float = 60.0
    server_hz: float = 30.0
    predict: bool = True
    predictor: PredictorSettings | None = None     # None: the default predictor
    seed: int = 0
    server_delay_ms: float = 0.0   # virtual time the server spends per frame
    reference_timeout_s: float = 1.5
    rate_trace: RateTrace | None = None   # the downlink's capacity over time (instead of rate_mbit)
    rate: RateConfig | None = None        # the server's rate controller (None: no adaptation)
    point: OperatingPoint | None = None   # without a controller: a fixed operating point
    gaze: GazeTrace | None = None         # where the viewer looks (None: the view centre)

    def server_session(self) -> ServerSessionConfig:
        """The server session of a replay: one shared clock, the link's nominal latency as the downlink estimate."""
        return ServerSessionConfig(predict=self.predict, predictor=self.predictor, downlink_s=self.latency_ms / 1e3,
                                   encode_s=self.server_delay_ms / 1e3, clock_offset_s=0.0, rate=self.rate,
                                   point=self.point)


@dataclass
class DisplayedFrame:
    """One client display tick: what it showed and the figures of that moment."""

    index: int
    t: float                       # virtual time = scene time (s)
    pose: Pose                     # the user's true pose
    image: np.ndarray
    frame_id: int                  # newest server frame applied (-1: none yet)
    render_pose: Pose | None       # the pose that frame was rendered for
    age_ms: float                  # display time - the frame's render time
    client_ms: dict = field(default_factory=dict)
    coverage: Coverage | None = None   # how the client's render covered the display (holes)


@dataclass
class ReplayTotals:
    duration_s: float = 0.0
    bytes_video: int = 0
    bytes_geometry: int = 0
    bytes_total: int = 0
    frames_sent: int = 0
    frames_lost: int = 0                  # lost on the downlink
    frames_before_payload: int = 0        # display ticks before the first payload was applied (shown black)
    payloads: list = field(default_factory=list)    # per server frame sent: (frame type, bytes, stats)
    client: object = None                 # the client session's counters
    server: object = None                 # the server session's counters
    sent: list = field(default_factory=list)     # per frame sent: SentFrame
    ages: list = field(default_factory=list)     # per display tick: (t, age_ms or nan, frame_id)
    rate: object = None                   # the rate controller's final state (RateState) when there is one


@dataclass
class SentFrame:
    """One server frame on the downlink: when it was sent and arrived (nan: lost), its bytes, its operating point
    (ladder index and name; None without a rate controller) and the controller's estimates when it was sent."""

    frame_id: int
    t_sent: float
    t_arrive: float
    bytes: int
    point_index: int | None = None
    point: str | None = None
    capacity_mbps: float | None = None
    queue_delay_ms: float | None = None


def replay(trace: Trace, server: MethodServer, client: MethodClient, config: ReplayConfig,
           display_frames: int, on_display: Callable[[DisplayedFrame], None] | None = None,
           show: Callable[[int], bool] | None = None) -> ReplayTotals:
    """Run the loop for `display_frames` client frames. `show(i)` says whether frame i is rendered (for scoring);
    the state is updated on every frame regardless. `on_display` receives each shown frame."""
    up = LinkModel(config.latency_ms, config.jitter_ms, rate_mbit=None, loss=0.0, seed=config.seed)
    down = LinkModel(config.latency_ms, config.jitter_ms, rate_mbit=config.rate_mbit, loss=config.loss,
                     seed=config.seed + 1, rate_trace=config.rate_trace, reliable=config.tcp,
                     queue_bytes=config.queue_bytes if config.tcp else None)
    back = LinkModel(config.latency_ms, config.jitter_ms, rate_mbit=None, loss=0.0, seed=config.seed + 2)  # reports
    server_session = ServerSession(config.server_session())
    client_session = ClientSession(config.reference_timeout_s)
    client_session.connected(0.0)
    hello_report = ReceiveReport(client_session.announce_reports().entries)
    totals = ReplayTotals(client=client_session.counters, server=server_session.counters)
    rate = server_session.rate
    points: dict[int, int | None] = {}          # frame id -> ladder index it was made at
    back.send(0.0, hello_report, len(encode_message(hello_report)))
    t0 = float(trace.times[0])
    send_period, display_period = 1.0 / config.server_hz, 1.0 / config.client_hz
    server_delay = config.server_delay_ms / 1e3
    in_flight: tuple[float, EncodeFrame] | None = None      # (ready at, decision) of the frame being encoded
    next_send = 0.0
    checked = 0.0       # the server's queue was last looked at then
    newest: FramePayload | None = None

    def encode(decision: EncodeFrame | None) -> None:
        nonlocal in_flight
        if decision is not None:
            in_flight = (decision.started + server_delay, decision)

    def send_queued(until: float) -> None:
        """Send what the server's queue holds, each frame when the link takes it, up to `until`: at once, or over
        TCP once the link holds at most a window and `unsent_bytes` unsent (the live server's wait, ``quadcast
        server --unsent``). A frame queued since the last call (at `checked`) goes no earlier than that."""
        nonlocal checked
        while server_session.queue:
            ready = checked
            if config.tcp:
                ready = down.unsent_at_most(down.window_bytes + config.unsent_bytes, checked)
            if ready > until:
                break
            send(ready, server_session.next_to_send())
            checked = ready
        checked = max(checked, until)

    def finish_encode(until: float) -> None:
        """The frame in flight is done if it is ready by `until`: queue it (and send what the link takes), start
        the next one."""
        nonlocal in_flight
        while in_flight is not None and in_flight[0] <= until:
            ready, decision = in_flight
            send_queued(ready)
            in_flight = None
            payload = server.encode_decision(decision)
            points[payload.frame_id] = decision.point_index
            encode(server_session.frame_encoded(ready, payload, payload.self_contained, ready - decision.started))
            send_queued(ready)

    def send(ready: float, p: FramePayload) -> None:
        """One frame onto the downlink at `ready`."""
        size = p.size_bytes
        totals.frames_sent += 1
        totals.bytes_video += len(p.video)
        totals.bytes_geometry += len(p.geometry)
        totals.bytes_total += size
        totals.payloads.append((p.frame_type, len(p.video) + len(p.geometry), p.stats))
        server_session.frame_sent(ready, p.frame_id, size)
        d = down.send(ready, p, size)
        if d is None:
            totals.frames_lost += 1
        index = points.pop(p.frame_id, None)
        st = rate.state if rate is not None else None
        totals.sent.append(SentFrame(
            p.frame_id, ready, d.t_arrive if d is not None else float("nan"), size, index,
            rate.points[index].name if index is not None else None,
            st.capacity_mbps if st is not None else None,
            st.queue_delay_s * 1e3 if st is not None and st.queue_delay_s is not None else None))

    def timers(until: float) -> None:
        """Run the server session's timer (a frame waiting for the flood guard or its point's frame rate) up to
        `until`, as the live server's encoder task does."""
        while (t := server_session.timer()) is not None and t <= until:
            finish_encode(t)
            if server_session.timer() != t:
                continue
            decision = server_session.handle_timer(t)
            encode(decision)
            finish_encode(t)
            if decision is None:
                break

    def request(decision: RequestReference | None, now: float) -> None:
        if decision is not None:
            msg = ReferenceRequest(decision.reason)
            up.send(now, msg, len(encode_message(msg)))

    for i in range(display_frames):
        now = i * display_period
        # Client -> server: poses at the server rate.
        while next_send <= now + 1e-9:
            p, q = trace.pose_at(t0 + next_send)
            gaze = None if config.gaze is None else config.gaze.angles_at(next_send)
            pose_msg = PoseUpdate(0, next_send, p, q, gaze)
            up.send(next_send, pose_msg, len(encode_message(pose_msg)))
            next_send += send_period
        # Server: every message that has arrived by now, in arrival order (poses and requests first on a tie).
        for d in sorted(up.poll(now) + back.poll(now), key=lambda d: (d.t_arrive, isinstance(d.message,
                                                                                              ReceiveReport))):
            finish_encode(d.t_arrive)
            timers(d.t_arrive)
            send_queued(d.t_arrive)
            m = d.message
            if isinstance(m, ReferenceRequest):
                server_session.reference_requested(d.t_arrive)
                continue
            if isinstance(m, ReceiveReport):
                encode(server_session.report_received(d.t_arrive, m.entries))
            else:
                encode(server_session.pose_received(d.t_arrive, m.t_client, m.position, m.quat, m.gaze))
            finish_encode(d.t_arrive)
        finish_encode(now)
        timers(now)
        send_queued(now)
        # Server -> client: apply what arrived (and report its arrival).
        for d in down.poll(now):
            payload: FramePayload = d.message
            report: SendReport = client_session.frame_arrived(d.t_arrive, payload.frame_id, d.size_bytes)
            msg = ReceiveReport(report.entries)
            back.send(d.t_arrive, msg, len(encode_message(msg)))
            if not client_session.frame_received(now, payload.frame_id, payload.self_contained):
                request(client_session.tick(now), now)
                continue
            try:
                client.receive(payload)
                newest = payload
                applied, reason = True, ""
            except (ProtocolError, VideoError) as exc:
                applied, reason = False, str(exc)
            request(client_session.frame_processed(now, applied, client.needs_reference, reason), now)
        request(client_session.tick(now), now)
        if newest is None:
            totals.frames_before_payload += 1
        totals.ages.append((now, (now - newest.t) * 1e3 if newest else float("nan"),
                            newest.frame_id if newest else -1))
        if show is not None and not show(i):
            continue
        p, q = trace.pose_at(t0 + now)
        pose = Pose(p, q)
        image = client.render(pose)
        stats = getattr(client, "stats", {}) or {}
        frame = DisplayedFrame(
            i, now, pose, image, newest.frame_id if newest else -1,
            Pose(newest.position, newest.quat) if newest else None,
            (now - newest.t) * 1e3 if newest else float("nan"), dict(stats.get("ms", {})), client.coverage())
        if on_display:
            on_display(frame)
    totals.duration_s = display_frames * display_period
    totals.rate = rate.state if rate is not None else None
    return totals
