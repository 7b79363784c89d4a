"""Trace replay in virtual time (QUASAR §4.1.3): a client, a server and a link between them, on one clock.

This is the virtual-time driver of the session core (:mod:`quadcast.protocol.session`); the live server and
client drive the same core on their event loops. The client follows the trace at `client_hz` (60) and sends its
pose at `server_hz` (30) over the uplink; the server session decides, on each pose it receives, to render and
encode a frame for the pose predicted at the time the frame will be shown, and the payload crosses the downlink
(delay + jitter + size/rate, loss); the client session decides which arrived payloads to apply (dependent frames
wait for a self-contained one after a loss) and when to ask for a reference, and the client shows its newest state
reprojected to its true pose. Nothing depends on how fast the machine is: when it is slower than real time,
virtual time simply waits. The same seed gives the same run.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from quadcast.client.method import Coverage, MethodClient
from quadcast.codec.decoder import VideoError
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import FramePayload
from quadcast.protocol.messages import PoseUpdate, ReferenceRequest, encode_message
from quadcast.protocol.prediction import PredictorSettings
from quadcast.protocol.session import (ClientSession, EncodeFrame, RequestReference, ServerSession,
                                       ServerSessionConfig)
from quadcast.render.camera import Pose
from quadcast.render.traces import Trace
from quadcast.server.method import MethodServer
from quadcast.sim.link import LinkModel

POSE_MESSAGE_BYTES = len(encode_message(PoseUpdate(0, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))))


@dataclass
class ReplayConfig:
    latency_ms: float = 20.0
    jitter_ms: float = 10.0
    rate_mbit: float | None = None
    loss: float = 0.0
    client_hz: float = 60.0
    server_hz: float = 30.0
    predict: bool = True
    predictor: PredictorSettings | None = None     # None: the default predictor
    seed: int = 0
    server_delay_ms: float = 0.0   # virtual time the server spends per frame
    reference_timeout_s: float = 1.5

    def server_session(self) -> ServerSessionConfig:
        """The server session of a replay: one shared clock, the link's nominal latency as the downlink estimate."""
        return ServerSessionConfig(predict=self.predict, predictor=self.predictor, downlink_s=self.latency_ms / 1e3,
                                   encode_s=self.server_delay_ms / 1e3, clock_offset_s=0.0)


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


def replay(trace: Trace, server: MethodServer, client: MethodClient, config: ReplayConfig,
           display_frames: int, on_display: Callable[[DisplayedFrame], None] | None = None,
           show: Callable[[int], bool] | None = None) -> ReplayTotals:
    """Run the loop for `display_frames` client frames. `show(i)` says whether frame i is rendered (for scoring);
    the state is updated on every frame regardless. `on_display` receives each shown frame."""
    up = LinkModel(config.latency_ms, config.jitter_ms, rate_mbit=None, loss=0.0, seed=config.seed)
    down = LinkModel(config.latency_ms, config.jitter_ms, rate_mbit=config.rate_mbit, loss=config.loss,
                     seed=config.seed + 1)
    server_session = ServerSession(config.server_session())
    client_session = ClientSession(config.reference_timeout_s)
    client_session.connected(0.0)
    totals = ReplayTotals(client=client_session.counters)
    t0 = float(trace.times[0])
    send_period, display_period = 1.0 / config.server_hz, 1.0 / config.client_hz
    server_delay = config.server_delay_ms / 1e3
    in_flight: tuple[float, EncodeFrame] | None = None      # (ready at, decision) of the frame being encoded
    next_send = 0.0
    newest: FramePayload | None = None

    def encode(decision: EncodeFrame | None) -> None:
        nonlocal in_flight
        if decision is None:
            return
        if decision.reference:
            server.request_reference()
        in_flight = (decision.started + server_delay, decision)

    def finish_encode(until: float) -> None:
        """The frame in flight is done if it is ready by `until`: send it, start the next one."""
        nonlocal in_flight
        while in_flight is not None and in_flight[0] <= until:
            ready, decision = in_flight
            in_flight = None
            payload = server.encode(Pose(decision.position, decision.quat), decision.display_t)
            encode(server_session.frame_encoded(ready, payload, payload.self_contained, ready - decision.started))
            while (p := server_session.next_to_send()) is not None:
                size = p.size_bytes
                totals.frames_sent += 1
                totals.bytes_video += len(p.video)
                totals.bytes_geometry += len(p.geometry)
                totals.bytes_total += size
                totals.payloads.append((p.frame_type, len(p.video) + len(p.geometry), p.stats))
                if down.send(ready, p, size) is None:
                    totals.frames_lost += 1

    def request(decision: RequestReference | None, now: float) -> None:
        if decision is not None:
            msg = ReferenceRequest(decision.reason)
            up.send(now, msg, len(encode_message(msg)))

    for i in range(display_frames):
        now = i * display_period
        # Client -> server: poses at the server rate.
        while next_send <= now + 1e-9:
            p, q = trace.pose_at(t0 + next_send)
            up.send(next_send, PoseUpdate(0, next_send, p, q), POSE_MESSAGE_BYTES)
            next_send += send_period
        # Server: every message that has arrived by now, in arrival order.
        for d in up.poll(now):
            finish_encode(d.t_arrive)
            if isinstance(d.message, ReferenceRequest):
                server_session.reference_requested(d.t_arrive)
                continue
            m = d.message
            encode(server_session.pose_received(d.t_arrive, m.t_client, m.position, m.quat))
            finish_encode(d.t_arrive)
        finish_encode(now)
        # Server -> client: apply what arrived.
        for d in down.poll(now):
            payload: FramePayload = d.message
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
    return totals
