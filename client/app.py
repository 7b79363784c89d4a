"""The live headless client (``quadcast client``): follows a trace in wall-clock time against a live server.

:class:`LiveClient` connects (TCP, or WebRTC through :mod:`quadcast.transport.webrtc`), says Hello, and from the Welcome on
runs on its own clock ``t`` (seconds of trace since ``start``): it sends the trace pose at ``t`` at 30 Hz, and at
60 Hz applies every frame that arrived (in order, on a :class:`quadcast.transport.channel.GLWorker` thread) and renders the
newest state at the true pose of ``t``. Every ``record_every``-th displayed frame (after the first applied one)
is saved as a PNG with its figures in ``recording.json``; on exit :func:`quadcast.sim.evaluate.evaluate_recording` renders
ground truth for those frames and writes the same ``summary.json`` / ``frames.csv`` / ``report.html`` as
``quadcast eval``, with Mbps measured on the socket.

``stereo=True`` (``--stereo``, quasar and quadstream only): every displayed frame is also a stereo pair made by
:meth:`quadcast.client.quasar.QuasarClient.stereo_frame` -- the left eye drawn from the quad mesh, the right eye
synthesized with YORO (mode ``"yoro"``). Recorded frames keep both eyes (``frames/left_*.png``,
``frames/right_*.png``), the right eye's pose and the frame's cost ratio (the right eye also rendered from the
mesh, as ``quadcast eval --stereo`` does), and the summary gets ``stereo`` = {ssim, psnr, flip, cost_ratio} of the
synthesized right eye against the ground-truth right eye, scored with the same code as ``quadcast eval --stereo``.
The head-pose image is still recorded and scored for the main figures; it is drawn only for recorded frames, as the
eyes are what a stereo client shows.

The GL work runs on a :class:`quadcast.render.worker.GLWorker` *thread*: moderngl holds the GIL during GL calls, so the
client's event loop (pose sending, frame receiving) can stall while a frame renders. The client's pose I/O matters
less than the server's (which uses a worker process per session); poses are stamped with the client's clock when
sent, so a late pose is late, not wrong.

Receive reports: as each frame arrives (before it is decoded) the client tells the server its id, its size and
the arrival time on the clock its poses carry (:class:`quadcast.protocol.messages.ReceiveReport`); a server with a
rate controller (``quadcast server --adapt``) times the link with them.

Loss and resync: a residual for a reference the client lacks, a frame the H.264 decoder cannot use, or a gap
after a reconnect make the method client need a reference; the client then sends a ReferenceRequest (again every
``reference_timeout`` s while it still needs one) and keeps showing its last good state. If the connection
drops, it reconnects and, until a self-contained frame arrives, ignores frames that depend on what it missed.

Connecting: up to ``retries`` more attempts after a failed one, with exponential backoff (``retry_delay`` doubling
up to ``max_retry_delay``); a busy server (``ErrorCode.BUSY``, or HTTP 503 from WebRTC signalling) says when to
try again and the client waits at least that long. Refusals a retry cannot fix (token, method, size, version, a
certificate that does not verify) end the run at once. With ``tls`` (implied by ``tls_ca`` and ``insecure``) the
connection is TLS (WebRTC: the signalling is HTTPS; the media and data are DTLS either way).
"""
from __future__ import annotations

import asyncio
import collections
import json
import logging
import ssl
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path


from quadcast.codec.decoder import VideoError
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import FramePayload, peek_frame_id, residual_to_reference_bytes
from quadcast.protocol.messages import (PROTOCOL_VERSION, Bye, ErrorCode, ErrorMessage, Frame, Hello, PoseUpdate,
                                        ReceiveReport, ReferenceRequest, Welcome)
from quadcast.protocol.methods import METHODS, STEREO_METHODS, MethodConfig
from quadcast.protocol.session import ClientSession, RequestReference
from quadcast.render.camera import Pose
from quadcast.render.gaze import GazeTrace
from quadcast.render.scene import load_scene, place_trace
from quadcast.render.traces import SPAWN, resolve_trace
from quadcast.render.worker import GLWorker
from quadcast.transport.channel import Channel, ServerBusy, open_tcp_channel
from quadcast.transport.tls import client_context

__all__ = ["ClientConfig", "ClientTotals", "LiveClient", "FatalServerError"]

log = logging.getLogger("quadcast.client")

MAX_INBOX = 32
"""Frames received and not yet applied; past this the client drops them and asks for a reference."""

PNG_LEVEL = 1
"""zlib level of the recorded frames: they are written while the session runs, on the CPU the display loop (and, on
one machine, the server) needs; level 1 costs a quarter of PIL's default 6 for files 15% larger."""

FATAL_CODES = (ErrorCode.UNSUPPORTED_VERSION, ErrorCode.UNKNOWN_METHOD, ErrorCode.BAD_REQUEST,
               ErrorCode.UNAUTHORIZED)


class FatalServerError(RuntimeError):
    """The server refused the session for a reason a retry cannot fix (token, method, size, version)."""


@dataclass
class ClientConfig:
    """What a :class:`LiveClient` connects to, follows and records."""

    host: str
    port: int
    trace: str = "builtin:walk"
    out: str = "out/live"
    scene: str = "builtin:courtyard"      # for scoring only: the server decides what it renders
    method: str = "quasar"
    width: int = 960
    height: int = 540
    fovy_deg: float = 60.0
    duration: float | None = None         # seconds; default: the rest of the trace after `start`
    start: float = 0.0                    # trace time to start at
    anchor: str | None = None             # re-anchor the trace into the scene ("spawn" or "x,y,z[,yaw_deg]")
    gaze: str | None = None               # a gaze trace (render/gaze.py) to send with the poses; None: not tracked
    display_hz: float = 60.0
    pose_hz: float = 30.0
    record_every: int = 1
    token: str = ""
    transport: str = "tcp"
    retries: int = 5
    retry_delay: float = 0.5              # first backoff; doubles per failed attempt up to max_retry_delay
    max_retry_delay: float = 2.0
    max_busy_wait: float = 60.0           # never wait longer than this for a busy server's retry-after
    tls: bool = False                     # connect with TLS (implied by tls_ca / insecure)
    tls_ca: str | None = None             # PEM file of the CA (or self-signed certificate) to trust
    insecure: bool = False                # TLS without verifying the server (encryption only)
    stun: str | None = None               # WebRTC: a STUN server URL (default: none)
    connect_timeout: float = 5.0
    welcome_timeout: float = 30.0         # Hello -> Welcome: the server may have to boot a worker process
    reference_timeout: float = 1.5
    max_message_bytes: int = 64 * 1024 * 1024
    score: bool = True
    stereo: bool = False                  # also make and record a YORO stereo pair (quasar, quadstream)
    warm_up: bool = True                  # before connecting, receive and draw made-up frames (MethodClient.warm_up)
    labels: dict = field(default_factory=dict)   # copied into the summary (e.g. the link's latency_ms)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"--method: unknown method {self.method!r}; methods are {', '.join(METHODS)}")
        if self.transport not in ("tcp", "webrtc"):
            raise ValueError(f"--transport: expected tcp or webrtc, got {self.transport!r}")
        if self.record_every < 1:
            raise ValueError(f"--record-every must be >= 1, got {self.record_every}")
        if self.start < 0 or (self.duration is not None and not self.duration > 0):
            raise ValueError(f"--start must be >= 0 and --duration > 0, got {self.start} and {self.duration}")
        if self.retries < 0:
            raise ValueError(f"--retries must be >= 0, got {self.retries}")
        if not (0 < self.retry_delay <= self.max_retry_delay):
            raise ValueError(f"retry delays: expected 0 < retry_delay <= max_retry_delay, got {self.retry_delay} "
                             f"and {self.max_retry_delay}")
        if self.stereo and self.method not in STEREO_METHODS:
            raise ValueError(f"--stereo: the {self.method} client keeps no depth to synthesize an eye from; stereo "
                             f"works with the {' and '.join(STEREO_METHODS)} methods")
        self.ssl_context()                    # ValueError for a missing CA file, or --tls-ca with --insecure

    def ssl_context(self) -> ssl.SSLContext | None:
        """The client's TLS context, or None for a plaintext connection."""
        if not (self.tls or self.tls_ca or self.insecure):
            return None
        return client_context(self.tls_ca, self.insecure)

    def backoff(self, attempt: int) -> float:
        """Seconds to wait after failed attempt ``attempt`` (0-based)."""
        return min(self.retry_delay * 2.0 ** min(attempt, 30), self.max_retry_delay)


@dataclass
class ClientTotals:
    """What happened during a run besides the session core's counters (goes into recording.json and the summary)."""

    duration_s: float = 0.0
    bytes_socket: int = 0
    bytes_video: int = 0
    bytes_geometry: int = 0
    connections: int = 0
    reconnects: int = 0
    display_frames: int = 0
    frames_before_payload: int = 0        # displayed before the first payload was applied (black)
    recorded_frames: int = 0
    server_types: list = field(default_factory=list)   # per applied frame: (FrameType, bytes)


class LiveClient:
    """See the module docstring. ``await client.run()`` streams and records (returns the run's totals);
    :func:`quadcast.sim.evaluate.evaluate_recording` then scores the recording."""

    def __init__(self, config: ClientConfig, make_client) -> None:
        """``make_client(method, MethodConfig, ctx)`` builds the method's client half
        (:func:`quadcast.methods.make_client`)."""
        self.cfg = config
        self.make_client = make_client
        self.session = ClientSession(config.reference_timeout)
        self.trace = resolve_trace(config.trace)
        if config.start >= self.trace.duration:
            raise ValueError(f"--start {config.start:g} s is past the end of trace {config.trace!r} "
                             f"({self.trace.duration:.1f} s)")
        if config.anchor is not None:   # its pose at `start` goes to the anchor (the scene's spawn point for "spawn")
            scene = load_scene(config.scene) if config.anchor.strip() == SPAWN else None
            self.trace = place_trace(self.trace, config.anchor, scene, config.start)
        self.gaze = GazeTrace.load(config.gaze) if config.gaze is not None else None
        remaining = self.trace.duration - config.start
        self.duration = min(config.duration, remaining) if config.duration is not None else remaining
        self.out = Path(config.out)
        self.totals = ClientTotals()
        self.worker: GLWorker | None = None
        self.method_client = None
        self.channel: Channel | None = None
        self.inbox: collections.deque[FramePayload] = collections.deque()
        self.newest: FramePayload | None = None
        self.t0: float | None = None
        self.finished = asyncio.Event()
        self.records: list[dict] = []
        self._fatal: BaseException | None = None
        self._ssl = config.ssl_context()

    # ------------------------------------------------------------------ clock and poses

    def now_t(self) -> float:
        """Trace time (s since the trace start) on the client's clock."""
        return asyncio.get_running_loop().time() - self.t0 + self.cfg.start

    def pose_at(self, t: float) -> Pose:
        p, q = self.trace.pose_at(float(self.trace.times[0]) + min(t, self.trace.duration))
        return Pose(p, q)

    # ------------------------------------------------------------------ connection

    async def _open(self) -> Channel:
        cfg = self.cfg
        try:
            if cfg.transport == "tcp":
                return await open_tcp_channel(cfg.host, cfg.port, cfg.max_message_bytes, cfg.connect_timeout,
                                              ssl=self._ssl)
            from quadcast.transport.webrtc import open_webrtc_channel
            return await open_webrtc_channel(cfg.host, cfg.port, cfg.max_message_bytes, cfg.connect_timeout,
                                             token=cfg.token, ssl=self._ssl, stun=cfg.stun)
        except ssl.SSLCertVerificationError as exc:
            raise FatalServerError(f"TLS: the server's certificate did not verify ({exc.verify_message}); give "
                                   f"--tls-ca with the certificate to trust, or --insecure") from None
        except PermissionError as exc:
            raise FatalServerError(f"server refused the session: {exc}") from None

    async def _handshake(self) -> Channel:
        """One connection attempt: Hello -> Welcome."""
        cfg = self.cfg
        channel = await self._open()
        try:
            await channel.send(Hello(PROTOCOL_VERSION, cfg.method, cfg.width, cfg.height, cfg.fovy_deg, cfg.token))
            msg = await asyncio.wait_for(channel.recv(), cfg.welcome_timeout)
            if isinstance(msg, ErrorMessage):
                if msg.code in FATAL_CODES:
                    raise FatalServerError(f"server refused the session: {msg.text} (code {msg.code})")
                if msg.code == ErrorCode.BUSY:
                    raise ServerBusy(f"server busy: {msg.text}", msg.retry_after_s)
                raise ConnectionError(f"server error {msg.code}: {msg.text}")
            if not isinstance(msg, Welcome):
                raise ConnectionError(f"expected Welcome, got {type(msg).__name__ if msg else 'end of stream'}")
        except BaseException:
            self.totals.bytes_socket += channel.bytes_in
            await channel.close()
            raise
        self.totals.connections += 1
        log.info("connected to %s:%d, session %d", cfg.host, cfg.port, msg.session_id)
        print(f"client: connected to {cfg.host}:{cfg.port} ({cfg.transport}), session {msg.session_id}", flush=True)
        return channel

    async def _connect_with_retries(self) -> Channel | None:
        cfg = self.cfg
        for attempt in range(cfg.retries + 1):
            if self.finished.is_set():
                return None
            try:
                return await self._handshake()
            except FatalServerError:
                raise
            except (OSError, ConnectionError, asyncio.TimeoutError, ProtocolError) as exc:
                delay = cfg.backoff(attempt)
                if isinstance(exc, ServerBusy):
                    delay = max(delay, min(exc.retry_after_s, cfg.max_busy_wait))
                log.warning("connection attempt %d/%d to %s:%d failed: %s", attempt + 1, cfg.retries + 1,
                            cfg.host, cfg.port, exc or type(exc).__name__)
                if attempt < cfg.retries:
                    print(f"client: attempt {attempt + 1} failed ({exc or type(exc).__name__}); retrying in "
                          f"{delay:.1f} s", flush=True)
                    await asyncio.sleep(delay)
        return None

    async def _connection_loop(self, first: Channel) -> None:
        """Run each connection until it drops; reconnect while the run is not over."""
        channel: Channel | None = first
        while channel is not None:
            self.channel = channel
            self.session.connected(asyncio.get_running_loop().time())
            hello_report = self.session.announce_reports()
            try:
                await channel.send(ReceiveReport(hello_report.entries))     # "this client reports arrivals"
            except (ConnectionError, OSError):
                pass
            senders = [asyncio.create_task(self._send_poses(channel)), asyncio.create_task(self._receive(channel))]
            stop = asyncio.create_task(self.finished.wait())
            try:
                await asyncio.wait(senders + [stop], return_when=asyncio.FIRST_COMPLETED)
            finally:
                for t in senders + [stop]:
                    t.cancel()
                results = await asyncio.gather(*senders, return_exceptions=True)
            self.channel = None
            if self.finished.is_set():
                try:
                    await asyncio.wait_for(channel.send(Bye()), 1.0)
                except Exception:  # noqa: BLE001 -- best effort
                    pass
                self.totals.bytes_socket += channel.bytes_in
                await channel.close()
                return
            self.totals.bytes_socket += channel.bytes_in
            await channel.close()
            for r in results:
                if isinstance(r, FatalServerError):
                    self._fatal = r
                    self.finished.set()
                    return
            print(f"client: connection lost at t={self.now_t():.2f} s; reconnecting", flush=True)
            self.totals.reconnects += 1
            try:
                channel = await self._connect_with_retries()
            except FatalServerError as exc:
                self._fatal = exc
                self.finished.set()
                return
            if channel is None and not self.finished.is_set():
                print("client: could not reconnect; showing the last state until the end", flush=True)

    async def _send_poses(self, channel: Channel) -> None:
        loop = asyncio.get_running_loop()
        period, seq = 1.0 / self.cfg.pose_hz, 0
        next_tick = loop.time()
        while True:
            t = self.now_t()
            gaze = None if self.gaze is None else self.gaze.angles_at(t - self.cfg.start)
            await channel.send(PoseUpdate.from_pose(seq, t, self.pose_at(t), gaze))
            seq += 1
            next_tick = max(next_tick + period, loop.time())
            await asyncio.sleep(next_tick - loop.time())

    async def _receive(self, channel: Channel) -> None:
        while True:
            try:
                msg = await channel.recv()
            except ProtocolError as exc:
                log.warning("malformed message from the server: %s", exc)
                return
            if msg is None or isinstance(msg, Bye):
                return
            if isinstance(msg, ErrorMessage):
                print(f"client: server error {msg.code}: {msg.text}", flush=True)
                if msg.code in FATAL_CODES:
                    raise FatalServerError(msg.text)
                return
            if not isinstance(msg, Frame):
                log.warning("unexpected %s from the server", type(msg).__name__)
                return
            now = asyncio.get_running_loop().time()
            if len(msg.payload) >= 12:       # its arrival, for the server's rate controller (on the poses' clock)
                report = self.session.frame_arrived(self.now_t(), peek_frame_id(msg.payload), len(msg.payload))
                await channel.send(ReceiveReport(report.entries))
            try:
                payload = msg.decode(self.cfg.max_message_bytes)
            except ProtocolError as exc:
                log.warning("bad frame: %s", exc)
                self.session.frames_dropped(now, 1, f"bad frame: {exc}")
                continue
            self.totals.bytes_video += len(payload.video)
            self.totals.bytes_geometry += len(payload.geometry)
            self.inbox.append(payload)
            if len(self.inbox) > MAX_INBOX:
                self.session.frames_dropped(now, len(self.inbox), "receive queue overflowed")
                self.inbox.clear()

    async def _request_reference(self, decision: RequestReference | None) -> None:
        channel = self.channel
        if decision is None or channel is None:
            return
        try:
            await channel.send(ReferenceRequest(decision.reason))
            print(f"client: reference requested at t={self.now_t():.2f} s ({decision.reason})", flush=True)
        except (ConnectionError, OSError):
            pass

    # ------------------------------------------------------------------ GL side

    def _setup(self) -> None:
        cfg = self.cfg
        self.method_client = self.make_client(cfg.method, MethodConfig(width=cfg.width, height=cfg.height,
                                                                  fovy_deg=cfg.fovy_deg), self.worker.ctx)
        if cfg.stereo and not hasattr(self.method_client, "stereo_frame"):
            raise ValueError(f"--stereo: the {cfg.method} client cannot synthesize an eye")
        if cfg.warm_up:                        # before connecting: the first frame should not wait for compiling
            t0 = time.perf_counter()
            try:
                self.method_client.warm_up(stereo=cfg.stereo)
                log.info("warmed up in %.0f ms", (time.perf_counter() - t0) * 1e3)
            except Exception as exc:  # noqa: BLE001 -- only a head start is lost (its made-up frames need x264)
                log.warning("warm-up failed, going on without it: %s: %s", type(exc).__name__, exc)

    def _apply(self, payload: FramePayload) -> tuple[bool, bool, str]:
        """On the GL thread: apply one frame; (applied, the method client needs a reference, why not applied)."""
        try:
            self.method_client.receive(payload)
            return True, self.method_client.needs_reference, ""
        except (ProtocolError, VideoError) as exc:
            return False, self.method_client.needs_reference, str(exc)

    def _render(self, pose: Pose, record: bool = False):
        """On the GL thread: the newest state at ``pose`` (and, with stereo, both eyes; ``record``: also the right
        eye rendered, for the cost ratio). With stereo the eyes are what is shown, so the head-pose image, which
        is recorded and scored, is drawn only on recorded frames (None on the others)."""
        image, holes, ms = None, {}, {}
        if record or not self.cfg.stereo:
            t0 = time.perf_counter()
            image = self.method_client.render(pose)
            holes = self.method_client.coverage().figures() if record else {}   # only recorded frames report them
            stats = getattr(self.method_client, "stats", {}) or {}
            ms = dict(stats.get("ms", {}))
            ms.setdefault("render", (time.perf_counter() - t0) * 1e3)
        stereo = None
        if self.cfg.stereo:
            # the disocclusion masks are not recorded: no read-back of them
            frame = self.method_client.stereo_frame(pose, mode="yoro", with_rendered=record, masks=False)
            stereo = {"left": frame.left, "right": frame.right, "position": frame.other_camera.pose.position.tolist(),
                      "quat": frame.other_camera.pose.quat.tolist(), "cost_ratio": frame.cost_ratio}
            ms.update({f"stereo_{k}": v for k, v in frame.ms.items()})
        return image, ms, stereo, holes

    # ------------------------------------------------------------------ display

    async def _display(self) -> None:
        from PIL import Image
        loop = asyncio.get_running_loop()
        period = 1.0 / self.cfg.display_hz
        frames_dir = self.out / "frames"
        frames_dir.mkdir(parents=True, exist_ok=True)
        next_tick = loop.time()
        index = 0
        first_applied = False
        while True:
            t = self.now_t()
            if t - self.cfg.start >= self.duration:
                break
            tot, session = self.totals, self.session
            while self.inbox:
                payload = self.inbox.popleft()
                now = loop.time()
                if not session.frame_received(now, payload.frame_id, payload.self_contained):
                    await self._request_reference(session.tick(now))
                    continue
                applied, needs_reference, reason = await self.worker.call(self._apply, payload)
                if applied:
                    self.newest = payload
                    tot.server_types.append((payload.frame_type, len(payload.video) + len(payload.geometry)))
                    if not first_applied:
                        first_applied = True
                        print(f"client: first frame applied at t={t:.2f} s", flush=True)
                else:
                    log.info("rejected frame %d: %s", payload.frame_id, reason)
                await self._request_reference(session.frame_processed(loop.time(), applied, needs_reference, reason))
            await self._request_reference(session.tick(loop.time()))
            pose = self.pose_at(t)
            record = index % self.cfg.record_every == 0
            image, ms, stereo, holes = await self.worker.call(self._render, pose, record)
            tot.display_frames += 1
            tot.frames_before_payload += self.newest is None
            if self.newest is not None and record:
                name = f"frames/display_{index:05d}.png"
                images = {name: image}
                n = self.newest
                render_pose = Pose(n.position, n.quat)
                entry = {
                    "index": index, "t": t, "position": pose.position.tolist(), "quat": pose.quat.tolist(),
                    "image": name, "frame_id": int(n.frame_id), "age_ms": (t - n.t) * 1e3,
                    "pose_error_cm": render_pose.distance_to(pose) * 100,
                    "pose_error_deg": render_pose.angle_to_deg(pose), "client_ms": ms, **holes}
                if self.gaze is not None:           # where the viewer looked: the foveal score centres on it
                    entry["gaze_deg"] = self.gaze.angles_at(t - self.cfg.start).tolist()
                if stereo is not None:
                    left, right = f"frames/left_{index:05d}.png", f"frames/right_{index:05d}.png"
                    images.update({left: stereo["left"], right: stereo["right"]})
                    entry["stereo"] = {"left": left, "right": right, "synthesized": "right",
                                       "position": stereo["position"], "quat": stereo["quat"],
                                       "cost_ratio": stereo["cost_ratio"]}

                def save(images=images) -> None:
                    for n_, im in images.items():
                        Image.fromarray(im).save(self.out / n_, compress_level=PNG_LEVEL)
                await loop.run_in_executor(None, save)
                self.records.append(entry)
                tot.recorded_frames += 1
            index += 1
            next_tick = max(next_tick + period, loop.time())
            await asyncio.sleep(max(0.0, next_tick - loop.time()))

    # ------------------------------------------------------------------ run

    async def run(self) -> dict:
        cfg = self.cfg
        self.out.mkdir(parents=True, exist_ok=True)
        self.worker = GLWorker("client")
        try:
            await self.worker.call(self._setup)
            first = await self._connect_with_retries()
            if first is None:
                raise ConnectionError(f"could not connect to {cfg.host}:{cfg.port} after {cfg.retries + 1} "
                                      f"attempt(s)")
            self.t0 = asyncio.get_running_loop().time()
            conn = asyncio.create_task(self._connection_loop(first))
            display = asyncio.create_task(self._display())
            await asyncio.wait([conn, display], return_when=asyncio.FIRST_COMPLETED)
            if display.done():
                display.result()
            elif self._fatal is not None:
                display.cancel()
                await asyncio.gather(display, return_exceptions=True)
            else:
                await display
            self.totals.duration_s = asyncio.get_running_loop().time() - self.t0
            self.finished.set()
            await asyncio.wait_for(conn, 5.0)
            if self._fatal is not None:
                raise self._fatal
        finally:
            self.finished.set()
            if self.method_client is not None:
                try:
                    await self.worker.call(self.method_client.close)
                except Exception:  # noqa: BLE001
                    log.exception("closing the method client failed")
            await asyncio.get_running_loop().run_in_executor(None, self.worker.close)
        self._write_recording()
        return {**asdict(self.totals), **asdict(self.session.counters)}

    def _write_recording(self) -> None:
        cfg, tot = self.cfg, self.totals
        rate = (lambda b: b * 8 / tot.duration_s / 1e6) if tot.duration_s > 0 else (lambda b: None)  # noqa: E731
        c = self.session.counters
        summary = {
            "trace": cfg.trace, "start_s": cfg.start, "duration_s": tot.duration_s, "transport": cfg.transport,
            "display_frames": tot.display_frames, "every": cfg.record_every,
            "frames_before_payload": tot.frames_before_payload,
            "mbps": rate(tot.bytes_socket), "mbps_video": rate(tot.bytes_video),
            "mbps_geometry": rate(tot.bytes_geometry), "server_frames": c.frames_received,
            "frames_applied": c.frames_applied, "frames_lost": c.frames_lost,
            "frames_rejected": c.frames_rejected, "frames_skipped": c.frames_skipped,
            "reference_requests": c.reference_requests, "connections": tot.connections,
            "reconnects": tot.reconnects, "bytes_socket": tot.bytes_socket,
            "residual_to_reference_bytes": residual_to_reference_bytes(tot.server_types),
            **cfg.labels,
        }
        rec = {"method": cfg.method, "scene": cfg.scene, "trace": cfg.trace, "size": [cfg.width, cfg.height],
               "fovy_deg": cfg.fovy_deg, "mbps": summary["mbps"], "stereo": cfg.stereo, "summary": summary,
               "frames": self.records}
        (self.out / "recording.json").write_text(json.dumps(rec, indent=1))
