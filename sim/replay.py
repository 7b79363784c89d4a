"""Trace replay in virtual time (QUASAR §4.1.3): a client, a server and a link between them, on one clock.

The client follows the trace at `client_hz` (60) and sends its pose at `server_hz` (30) over the uplink; the
server, on each pose it receives, predicts the pose at the time its frame will be shown, renders and encodes
for it, and sends the payload over the downlink (delay + jitter + size/rate, loss); the client applies every
payload that has arrived and shows its newest state reprojected to its true pose. Nothing depends on how fast the
machine is: when it is slower than real time, virtual time simply waits. The same seed gives the same run.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from quadcast.client.method import MethodClient
from quadcast.codec.decoder import VideoError
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import FramePayload
from quadcast.render.camera import Pose
from quadcast.server.method import MethodServer
from quadcast.protocol.prediction import PosePredictor
from quadcast.sim.link import LinkModel
from quadcast.render.traces import Trace

POSE_MESSAGE_BYTES = 76       # a PoseUpdate on the wire (see protocol/messages.py)
REQUEST_MESSAGE_BYTES = 16


@dataclass
class ReplayConfig:
    latency_ms: float = 20.0
    jitter_ms: float = 10.0
    rate_mbit: float | None = None
    loss: float = 0.0
    client_hz: float = 60.0
    server_hz: float = 30.0
    predict: bool = True
    smooth: bool = False
    seed: int = 0
    server_delay_ms: float = 0.0   # virtual time the server spends per frame


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


@dataclass
class ReplayTotals:
    duration_s: float = 0.0
    bytes_video: int = 0
    bytes_geometry: int = 0
    bytes_total: int = 0
    frames_sent: int = 0
    frames_applied: int = 0
    frames_rejected: int = 0
    frames_lost: int = 0
    reference_requests: int = 0
    server_ms: list = field(default_factory=list)   # per server frame: {stage: ms}
    server_stats: list = field(default_factory=list)


def replay(trace: Trace, server: MethodServer, client: MethodClient, config: ReplayConfig,
           display_frames: int, on_display: Callable[[DisplayedFrame], None] | None = None,
           show: Callable[[int], bool] | None = None) -> ReplayTotals:
    """Run the loop for `display_frames` client frames. `show(i)` says whether frame i is rendered (for scoring);
    the state is updated on every frame regardless. `on_display` receives each shown frame."""
    up = LinkModel(config.latency_ms, config.jitter_ms, rate_mbit=None, loss=0.0, seed=config.seed)
    down = LinkModel(config.latency_ms, config.jitter_ms, rate_mbit=config.rate_mbit, loss=config.loss,
                     seed=config.seed + 1)
    predictor = PosePredictor(smooth=config.smooth)
    totals = ReplayTotals()
    t0 = float(trace.times[0])
    send_period, display_period = 1.0 / config.server_hz, 1.0 / config.client_hz
    next_send = 0.0
    server_busy_until = 0.0
    newest: FramePayload | None = None
    pending_request = False
    latency_estimate = config.latency_ms / 1e3

    for i in range(display_frames):
        now = i * display_period
        # Client -> server: poses at the server rate (and reference requests).
        while next_send <= now + 1e-9:
            p, q = trace.pose_at(t0 + next_send)
            up.send(next_send, ("pose", next_send, p, q), POSE_MESSAGE_BYTES)
            next_send += send_period
        # Server: every message that has arrived by now, in arrival order.
        for d in up.poll(now):
            kind = d.message[0]
            if kind == "reference":
                server.request_reference()
                continue
            _, t_sent, p, q = d.message
            predictor.observe(t_sent, p, q)
            start = max(d.t_arrive, server_busy_until)
            show_at = start + config.server_delay_ms / 1e3 + latency_estimate
            if config.predict:
                pp, pq = predictor.predict(show_at)
            else:
                pp, pq = p, q
            payload = server.encode(Pose(pp, pq), float(show_at))
            server_busy_until = start + config.server_delay_ms / 1e3
            totals.frames_sent += 1
            totals.server_ms.append(dict(payload.stats.get("ms", {})))
            totals.server_stats.append({k: v for k, v in payload.stats.items() if k != "ms"})
            size = payload.size_bytes
            totals.bytes_video += len(payload.video)
            totals.bytes_geometry += len(payload.geometry)
            totals.bytes_total += size
            if down.send(server_busy_until, payload, size) is None:
                totals.frames_lost += 1
        # Server -> client: apply what arrived.
        for d in down.poll(now):
            try:
                client.receive(d.message)
                newest = d.message
                totals.frames_applied += 1
            except (ProtocolError, VideoError):
                totals.frames_rejected += 1
            if client.needs_reference and not pending_request:
                up.send(now, ("reference",), REQUEST_MESSAGE_BYTES)
                totals.reference_requests += 1
                pending_request = True
            elif not client.needs_reference:
                pending_request = False
        if show is not None and not show(i):
            continue
        p, q = trace.pose_at(t0 + now)
        pose = Pose(p, q)
        image = client.render(pose)
        stats = getattr(client, "stats", {}) or {}
        frame = DisplayedFrame(
            i, now, pose, image, newest.frame_id if newest else -1,
            Pose(newest.position, newest.quat) if newest else None,
            (now - newest.t) * 1e3 if newest else float("nan"), dict(stats.get("ms", {})))
        if on_display:
            on_display(frame)
    totals.duration_s = display_frames * display_period
    return totals
