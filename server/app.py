"""The live quadcast server (``quadcast server``): an asyncio process streaming one method to several clients.

Per connection (:class:`Session`): the client's :class:`quadcast.protocol.messages.Hello` is checked (version,
method, size, token) before anything is allocated; then the session's :class:`SessionPipeline` (renderer + the
method's server, with their own GL context) runs in a worker *process* of its own
(:class:`quadcast.render.worker.ProcessWorker`, ``spawn``), so the event loop only moves messages: it sends (pose,
time, reference?) down a pipe and gets the encoded payload bytes back. (moderngl holds the GIL during GL calls, so
a worker *thread* -- ``worker="thread"``, kept for comparison, see ``quadcast.cli.stall`` -- stalls the loop while
it renders.)

Every decision is the session core's (:class:`quadcast.protocol.session.ServerSession`, which the virtual-time
replay drives too): each pose, reference request and receive report goes into it; it says when to encode a frame,
for which predicted pose and display time and (with ``adapt``, :mod:`quadcast.protocol.rate`) at which operating
point; encoded frames go through its bounded, chain-safe send queue to the socket, and each one sent is told back
to it. This module only carries those decisions out: one encode at a time on the worker, one sender.

The method's server half comes from the ``make_server(name, renderer, config)`` the server is given (the registry
:func:`quadcast.methods.make_server`; it must be picklable to reach a worker process).

Robustness: a malformed message or any failure ends only its session, after an :class:`ErrorMessage` (a worker
process that dies -- killed, crashed -- ends its session with ``ErrorCode.INTERNAL`` naming it); worker processes
are terminated when their session ends and when the server closes, and die with the server; incoming
messages are capped at ``max_message_bytes``.

Limits (:class:`quadcast.protocol.admission.ServerLimits`, one :class:`~quadcast.protocol.admission.Admission`
for every listener): at most ``max_preauth`` connections awaiting their handshake and ``max_per_ip`` connections
per address (others are closed at once); a connection must finish its TLS handshake and Hello within
``handshake_timeout``; at most ``max_sessions`` sessions run, and a Hello beyond that is answered
``ErrorCode.BUSY`` with a retry-after; a session whose client sends no pose for ``idle_timeout`` is ended
(``ErrorCode.TIMEOUT``; only pose traffic counts, see the session core).

Security: the server binds 127.0.0.1 unless told otherwise, and refuses any other bind without a shared-secret
token, and a token without TLS (``tls_cert``/``tls_key``) unless ``allow_plaintext_token``.
"""
from __future__ import annotations

import asyncio
import collections
import hmac
import ipaddress
import itertools
import logging
import math
import os
import ssl
import time
from dataclasses import dataclass
from typing import Callable

from quadcast.protocol.admission import Admission, Refusal, ServerLimits, Ticket
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import encode_frame_payload, peek_frame_id
from quadcast.protocol.messages import (PROTOCOL_VERSION, Bye, ErrorCode, ErrorMessage, Frame, Hello, PoseUpdate,
                                        ReceiveReport, ReferenceRequest, Welcome, encode_message)
from quadcast.protocol.methods import METHODS, MethodConfig
from quadcast.protocol.rate import load_ladder, resolve_point, session_rate
from quadcast.protocol.session import EncodeFrame, ServerCounters, ServerSession, ServerSessionConfig
from quadcast.render.camera import Pose
from quadcast.render.gl import WARM_UP_SIZE
from quadcast.render.worker import GLWorker, ProcessWorker, WorkerDied, WorkerError
from quadcast.transport.channel import Channel, TcpChannel
from quadcast.transport.tls import server_context

__all__ = ["ServerConfig", "PipelineSpec", "SessionPipeline", "Session", "LiveServer", "check_bind"]

log = logging.getLogger("quadcast.server")


@dataclass
class ServerConfig:
    """What a :class:`LiveServer` serves and its limits."""

    scene: str = "builtin:courtyard"
    methods: tuple[str, ...] = ("quasar",)
    host: str = "127.0.0.1"
    port: int = 0
    token: str = ""
    server_hz: float = 30.0
    max_width: int = 1920
    max_height: int = 1080
    viewcell_m: float = 0.5
    reference_every: int = 5
    crf: float | None = None            # None: each method's own (quadcast.protocol.methods.DEFAULT_CRF)
    chroma_qp_offset: int | None = None  # x264's; None: each method's own (methods.DEFAULT_CHROMA_QP_OFFSET)
    lead_ms: float = 40.0               # a frame's first display - render start, beyond the measured encode time
    predict: bool = True
    max_prediction_s: float = 0.5       # never extrapolate the pose further ahead (the predictor is kinematic)
    max_frame_hz: float = 60.0          # flood guard: frames start at most this often, however fast poses come
    max_sessions: int = 4               # limits: see quadcast.protocol.admission.ServerLimits
    max_preauth: int = 32
    max_per_ip: int = 8
    handshake_timeout: float = 10.0
    idle_timeout: float = 20.0          # a session whose client sends no pose for this long is closed
    retry_after: float = 5.0            # a busy server's hint to the client
    max_message_bytes: int = 64 * 1024  # client -> server messages are small (Hello, poses, requests)
    queue_frames: int = 3               # per-session send queue
    # TCP: the next frame is taken from the queue once at most this many bytes of the last ones wait in the kernel
    # (Linux), so frames queue where stale ones are dropped, not behind a slow link (TCP_NOTSENT_LOWAT's idea)
    unsent_bytes: int = 16 * 1024
    tls_cert: str | None = None         # PEM certificate chain: serve TLS (TCP, and WebRTC's signalling)
    tls_key: str | None = None          # its PEM private key (None: in tls_cert)
    allow_plaintext_token: bool = False  # a token on a non-loopback bind needs TLS unless this is set
    max_peer_connections: int = 8       # WebRTC: peer connections at once (open or opening)
    stun: str | None = None             # WebRTC: a STUN server URL (default: none, host candidates only)
    pace_mbit: float | None = None      # WebRTC: each session's RTP sent no faster than this (default: unpaced)
    worker: str = "process"             # where a session renders and encodes: "process" or "thread"
    worker_start_timeout: float = 60.0  # a session's worker must be ready (GL context, scene, server) by then
    # worker processes kept booted for the next sessions (worker="process"): all of them while no session runs;
    # while sessions run, one is booted when the last spare is claimed (LiveServer.claim_process)
    spare_workers: int = 2
    # a spare worker booted while no session runs first encodes a few small frames of every method served and
    # drops them (SessionHost), so that a session's first frames do not wait for llvmpipe to compile shaders
    warm_up: bool = True
    adapt: bool = False                 # rate controller: each frame's operating point from the receive reports
    target_mbps: float | None = None    # the rate controller's ceiling (implies adapt)
    ladder: str | None = None           # the operating points (default: the measured ladder shipped)
    # without a controller: every session's frames at this operating point (a ladder point's name or
    # "key=value,...", quadcast.protocol.rate.resolve_point; quasar's knobs, other methods ignore it)
    point: str | None = None

    def __post_init__(self) -> None:
        if self.worker not in ("process", "thread"):
            raise ValueError(f"--worker: expected process or thread, got {self.worker!r}")
        unknown = [m for m in self.methods if m not in METHODS]
        if not self.methods or unknown:
            raise ValueError(f"--method: unknown method(s) {', '.join(unknown) or '(none)'}; "
                             f"methods are {', '.join(METHODS)}")
        if not (0 < self.server_hz <= 240):
            raise ValueError(f"--hz: expected 0 < hz <= 240, got {self.server_hz}")
        if not (0 < self.max_frame_hz <= 1000):
            raise ValueError(f"max_frame_hz: expected 0 < hz <= 1000, got {self.max_frame_hz}")
        if not 0 <= self.spare_workers <= 8:
            raise ValueError(f"--spare-workers: expected 0..8, got {self.spare_workers}")
        if self.queue_frames < 1 or self.max_peer_connections < 1:
            raise ValueError("--max-peer-connections and the queue length must be >= 1")
        if self.unsent_bytes < 0:
            raise ValueError(f"unsent_bytes: expected >= 0, got {self.unsent_bytes}")
        if self.pace_mbit is not None and not (math.isfinite(self.pace_mbit) and self.pace_mbit > 0):
            raise ValueError(f"--pace: expected a rate > 0 Mbit/s, got {self.pace_mbit}")
        if self.tls_key is not None and self.tls_cert is None:
            raise ValueError("--tls-key needs --tls-cert")
        self.limits()                    # ValueError naming a bad limit
        self.check_video()
        ladder = load_ladder(self.ladder) if self.adapt or self.target_mbps is not None else None
        # ValueError / LadderError: bad ladder. Above it, what quasar sends without adaptation (RateConfig.own)
        self._rate = None if ladder is None else session_rate(ladder, self.target_mbps, self.crf, self.viewcell_m,
                                                              self.reference_every)
        if self.point is not None and self._rate is not None:
            raise ValueError("--point fixes the operating point; --adapt chooses it: give one of them")
        self._point = None if self.point is None else \
            resolve_point(self.point, load_ladder(self.ladder) if "=" not in self.point else None)
        check_bind(self.host, self.token, tls=self.tls_cert is not None,
                   allow_plaintext_token=self.allow_plaintext_token)

    def limits(self) -> ServerLimits:
        """The admission limits."""
        return ServerLimits(max_sessions=self.max_sessions, max_preauth=self.max_preauth, max_per_ip=self.max_per_ip,
                            handshake_timeout_s=self.handshake_timeout, idle_timeout_s=self.idle_timeout,
                            retry_after_s=self.retry_after)

    def check_video(self) -> None:
        """ValueError naming the option, unless every method served can code its video with ``crf`` and
        ``chroma_qp_offset``: found here, not when each session's worker builds its encoder and fails."""
        from quadcast.codec.encoder import VideoSettings
        from quadcast.protocol.methods import method_video
        for method in self.methods:
            try:
                VideoSettings(**method_video(method, self.crf, self.chroma_qp_offset))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"--crf / --chroma-qp-offset ({method}): {exc}") from None

    def ssl_context(self) -> ssl.SSLContext | None:
        """The server's TLS context, or None without ``tls_cert``."""
        return None if self.tls_cert is None else server_context(self.tls_cert, self.tls_key)

    def session_config(self) -> ServerSessionConfig:
        """The session core's settings: the client's clock is estimated from its poses."""
        return ServerSessionConfig(predict=self.predict, downlink_s=self.lead_ms / 1e3,
                                   max_prediction_s=self.max_prediction_s, queue_frames=self.queue_frames,
                                   min_frame_interval_s=1.0 / self.max_frame_hz, idle_timeout_s=self.idle_timeout,
                                   rate=self._rate, point=self._point)


def check_bind(host: str, token: str, tls: bool = False, allow_plaintext_token: bool = False) -> None:
    """Refuse to listen on a non-loopback address without a shared-secret token, or with a token that would
    cross the network in clear (no TLS) unless ``allow_plaintext_token``."""
    try:
        loopback = ipaddress.ip_address(host).is_loopback
    except ValueError:
        loopback = host == "localhost"
    if loopback:
        return
    if not token:
        raise ValueError(f"--host {host}: binding a non-loopback address needs --token (a shared secret that "
                         f"clients send in Hello)")
    if not tls and not allow_plaintext_token:
        raise ValueError(f"--host {host}: the token would cross the network in clear; serve TLS (--tls-cert and "
                         f"--tls-key) or accept that with --allow-plaintext-token")


def peer_ip(peer: str) -> str:
    """The address part of a ``host:port`` peer string."""
    return peer.rpartition(":")[0].strip("[]") or peer


# -------------------------------------------------------------------------------------------- pipeline

@dataclass(frozen=True)
class PipelineSpec:
    """What a session's worker builds (picklable: it crosses to the worker process)."""

    make_server: Callable          # (method name, renderer, MethodConfig) -> MethodServer
    scene: str
    method: str
    width: int
    height: int
    fovy_deg: float
    viewcell_m: float
    reference_every: int
    crf: float | None
    chroma_qp_offset: int | None = None


WARM_UP_FRAMES = 3
"""A reference frame and two residual frames: every pass a session's frames run."""


def warm_up_path(scene, frames: int = WARM_UP_FRAMES, dt: float = 0.1) -> list[tuple[Pose, float]]:
    """(pose, scene time) pairs for a warm-up: from the scene's spawn point, 0.15 m forward and 4 degrees to the
    left at each step, `dt` seconds apart, so that the residual frames reveal something."""
    x, y, z = scene.spawn.position
    out = []
    for k in range(frames):
        yaw = scene.spawn.yaw_deg + 4.0 * k
        step = 0.15 * k
        position = (x - step * math.sin(math.radians(yaw)), y, z - step * math.cos(math.radians(yaw)))
        out.append((Pose.from_euler(position, 0.0, yaw), dt * k))
    return out


class SessionPipeline:
    """A session's renderer and method server: what its worker (process or thread) runs.

    Built inside the worker: in a worker process (``ctx=None``) on the process's own headless GL context, with the
    scene loaded there; in a :class:`GLWorker` thread on that thread's context. :meth:`encode` renders and encodes
    one frame and returns it as wire bytes (:func:`quadcast.protocol.frame.encode_frame_payload`), whether it is
    self-contained, and the server's figures for it.
    """

    def __init__(self, spec: PipelineSpec, ctx=None, scene=None, renderer=None) -> None:
        """`renderer`: a :class:`~quadcast.render.renderer.DeferredRenderer` of the scene to draw with (a worker's
        that warmed up), else one is made."""
        from quadcast.render.renderer import DeferredRenderer
        from quadcast.render.scene import load_scene
        self.spec = spec
        self.renderer = renderer or DeferredRenderer(scene if scene is not None else load_scene(spec.scene), ctx)
        config = MethodConfig(width=spec.width, height=spec.height, fovy_deg=spec.fovy_deg,
                              viewcell_radius=spec.viewcell_m, reference_every=spec.reference_every, crf=spec.crf,
                              chroma_qp_offset=spec.chroma_qp_offset)
        self.server = spec.make_server(spec.method, self.renderer, config)

    def encode(self, decision: EncodeFrame) -> tuple[bytes, bool]:
        """The frame `decision` asks for (:meth:`~quadcast.server.method.MethodServer.encode_decision`)."""
        payload = self.server.encode_decision(decision)
        return encode_frame_payload(payload), payload.self_contained

    def warm_up(self, frames: int = WARM_UP_FRAMES) -> None:
        """Encode `frames` frames along :func:`warm_up_path` and drop them (see :class:`SessionHost`)."""
        self.server.warm_up(warm_up_path(self.renderer.scene, frames))

    def close(self) -> None:
        self.server.close()


class SessionHost:
    """The handler of a session's worker process: warmed up before any session claims it (modules imported,
    headless GL context made, scene loaded: a few seconds on llvmpipe; and, given `warm_up`, a few frames of each
    method run and dropped, so that the shaders are compiled), then :meth:`build` makes the claiming session's
    :class:`SessionPipeline` (fast), and :meth:`encode` runs it. The server keeps one such process spare, so a new
    session waits for its pipeline, not for a process to boot or its shaders to compile."""

    def __init__(self, scene: str, warm_up: tuple[PipelineSpec, ...] = ()) -> None:
        """`warm_up`: pipelines (small ones, :data:`WARM_UP_SIZE`) to build, run for a few frames
        (:meth:`SessionPipeline.warm_up`) and drop before the worker is ready; their renderer is kept for the
        session's pipeline, on the same context. On llvmpipe a session's first frames otherwise compile its shaders:
        a 480x270 courtyard session's first two took 2.2 and 1.2 s where Mesa's shader cache was empty, 0.14 and 0.10 s
        after a warm-up (docs/speed.md, stop 53), and it sends the same bytes. :attr:`warm_up_ms` says how long each
        method's took. A warm-up that fails fails the worker's start, naming the method."""
        from quadcast.render.gl import gl_context
        from quadcast.render.renderer import DeferredRenderer
        from quadcast.render.scene import load_scene
        gl_context()
        self.scene = load_scene(scene)
        self.pipeline: SessionPipeline | None = None
        self.renderer = DeferredRenderer(self.scene) if warm_up else None
        self.warm_up_ms: dict[str, float] = {}
        for spec in warm_up:
            t0 = time.perf_counter()
            try:
                pipeline = SessionPipeline(spec, renderer=self.renderer)
                try:
                    pipeline.warm_up()
                finally:
                    pipeline.close()
            except Exception as exc:
                raise RuntimeError(f"warm-up of {spec.method} at {spec.width}x{spec.height} failed: "
                                   f"{type(exc).__name__}: {exc}") from exc
            self.warm_up_ms[spec.method] = (time.perf_counter() - t0) * 1e3

    def warm_up_times(self) -> dict[str, float]:
        """How long each method's warm-up took (ms)."""
        return dict(self.warm_up_ms)

    def build(self, spec: PipelineSpec) -> int:
        if self.pipeline is not None:
            raise RuntimeError("SessionHost.build: this worker already serves a session")
        self.pipeline = SessionPipeline(spec, scene=self.scene, renderer=self.renderer)
        return os.getpid()

    def encode(self, decision: EncodeFrame) -> tuple[bytes, bool]:
        if self.pipeline is None:
            raise RuntimeError("SessionHost.encode: no pipeline built")
        return self.pipeline.encode(decision)

    def close(self) -> None:
        if self.pipeline is not None:
            self.pipeline.close()
            self.pipeline = None


class _ThreadWorker:
    """A session pipeline on a :class:`GLWorker` thread in the server's process (``worker="thread"``)."""

    kind = "thread"

    def __init__(self, name: str, spec: PipelineSpec, scene) -> None:
        self.name, self.spec, self.scene = name, spec, scene
        self.gl: GLWorker | None = None
        self.pipeline: SessionPipeline | None = None
        self.pid = os.getpid()
        self.died = asyncio.Event()       # never set: a thread cannot be killed on its own

    async def start(self, timeout: float) -> int:
        self.gl = GLWorker(self.name)
        self.pipeline = await asyncio.wait_for(self.gl.call(SessionPipeline, self.spec, self.gl.ctx, self.scene),
                                               timeout)
        return self.pid

    async def encode(self, decision: EncodeFrame) -> tuple[bytes, bool]:
        return await self.gl.call(self.pipeline.encode, decision)

    @property
    def death(self) -> str | None:
        return None

    async def close(self) -> None:
        if self.gl is None:
            return
        gl, self.gl = self.gl, None
        if self.pipeline is not None:
            try:
                await gl.call(self.pipeline.close)
            except Exception:  # noqa: BLE001
                log.exception("%s: closing the method server failed", self.name)
        await asyncio.get_running_loop().run_in_executor(None, gl.close)


class _ProcessWorker:
    """A session pipeline in a worker process of its own (``worker="process"``, the default)."""

    kind = "process"

    def __init__(self, name: str, spec: PipelineSpec, proc: ProcessWorker) -> None:
        self.name, self.spec, self.proc = name, spec, proc
        self.pid: int | None = None
        self.died = asyncio.Event()

    async def start(self, timeout: float) -> int:
        """Wait for the (spare) process to be warm, then build this session's pipeline in it."""
        try:
            await self.proc.start(timeout)
        finally:
            if self.proc.died is not None:
                self.died = self.proc.died
        self.pid = await asyncio.wait_for(self.proc.call("build", self.spec), timeout)
        return self.pid

    async def encode(self, decision: EncodeFrame) -> tuple[bytes, bool]:
        return await self.proc.call("encode", decision)

    @property
    def death(self) -> str | None:
        return self.proc.death if self.proc is not None else None

    def kill_now(self) -> None:
        """For server shutdown: stop the process at once (its session's close reaps it)."""
        if self.proc is not None and self.proc.process.is_alive():
            self.proc.process.kill()

    async def close(self) -> None:
        """Ask the process to close its method server and exit; terminate it if it does not (bounded)."""
        if self.proc is None or getattr(self, "_closing", False):
            return
        self._closing = True
        await asyncio.get_running_loop().run_in_executor(None, self.proc.close)


# --------------------------------------------------------------------------------------------- session

_WAKE = object()
"""What the reader puts in the encoder's queue to make it look at the core's timer again."""


def _fmt(value: float | None, scale: float = 1.0) -> str:
    return "?" if value is None else f"{value * scale:.1f}"


class SessionError(Exception):
    """Ends a session with an ErrorMessage(code, text)."""

    def __init__(self, code: int, text: str, retry_after_s: float = 0.0) -> None:
        super().__init__(text)
        self.code, self.retry_after_s = code, retry_after_s


class Session:
    """One client over a :class:`Channel`: the handshake, then the session core's decisions run by three tasks --
    the reader (poses and requests in), the encoder (one frame at a time on the worker) and the sender."""

    def __init__(self, server: "LiveServer", channel: Channel, session_id: int, ticket: Ticket,
                 handshake_deadline: float | None = None) -> None:
        """``ticket``: the connection's place in the server's admission (admitted here once its Hello passes);
        ``handshake_deadline``: loop time by which the Hello must have come (default: handshake_timeout from now)."""
        self.server, self.channel, self.id = server, channel, session_id
        self.ticket, self.handshake_deadline = ticket, handshake_deadline
        self.cfg = server.config
        self.core = ServerSession(self.cfg.session_config())
        self.worker: _ThreadWorker | _ProcessWorker | None = None
        self._decisions: asyncio.Queue = asyncio.Queue()        # EncodeFrame decisions, or _WAKE
        self._queued = asyncio.Event()
        self.frames_sent = 0
        self.bytes_sent = 0
        self._point = None

    # -- handshake

    def _check_hello(self, hello: Hello) -> None:
        cfg = self.cfg
        if hello.version != PROTOCOL_VERSION:
            raise SessionError(ErrorCode.UNSUPPORTED_VERSION,
                               f"Hello.version {hello.version} is not supported (server speaks {PROTOCOL_VERSION})")
        if cfg.token and not hmac.compare_digest(hello.token.encode(), cfg.token.encode()):
            raise SessionError(ErrorCode.UNAUTHORIZED, "Hello.token: wrong or missing token")
        if hello.method not in cfg.methods:
            raise SessionError(ErrorCode.UNKNOWN_METHOD,
                               f"Hello.method {hello.method!r} is not served here (served: {', '.join(cfg.methods)})")
        w, h = hello.width, hello.height
        if w > cfg.max_width or h > cfg.max_height or w < 16 or h < 16 or w % 2 or h % 2:
            raise SessionError(ErrorCode.BAD_REQUEST, f"Hello size {w}x{h}: expected even sizes from 16x16 to "
                                                      f"{cfg.max_width}x{cfg.max_height}")

    async def _start_worker(self, hello: Hello) -> None:
        """The session's worker (a process unless ``config.worker == "thread"``) with its pipeline built."""
        cfg = self.cfg
        spec = PipelineSpec(self.server.make_server, cfg.scene, hello.method, hello.width, hello.height,
                            hello.fovy_deg, cfg.viewcell_m, cfg.reference_every, cfg.crf, cfg.chroma_qp_offset)
        self.worker = self.server.make_worker(f"session-{self.id}", spec)
        self.server.workers.add(self.worker)
        try:
            await self.worker.start(cfg.worker_start_timeout)
        except WorkerError as exc:
            raise SessionError(ErrorCode.INTERNAL, f"session worker could not start: {exc}") from None
        except (WorkerDied, asyncio.TimeoutError) as exc:
            raise SessionError(ErrorCode.INTERNAL, f"session worker could not start: "
                                                   f"{exc or 'timed out'}") from None

    async def run(self) -> None:
        """The whole session; never raises (errors end it with an ErrorMessage)."""
        tasks: list[asyncio.Task] = []
        loop = asyncio.get_running_loop()
        try:
            deadline = self.handshake_deadline
            if deadline is None:
                deadline = loop.time() + self.cfg.handshake_timeout
            try:
                msg = await asyncio.wait_for(self.channel.recv(), max(0.0, deadline - loop.time()))
            except asyncio.TimeoutError:
                raise SessionError(ErrorCode.TIMEOUT, f"no Hello within {self.cfg.handshake_timeout:g} s") from None
            if msg is None:
                return
            if not isinstance(msg, Hello):
                raise SessionError(ErrorCode.PROTOCOL, f"expected Hello first, got {type(msg).__name__}")
            self._check_hello(msg)
            refusal = self.ticket.admit()
            if refusal is not None:
                raise SessionError(refusal.code, refusal.text, refusal.retry_after_s)
            await self._start_worker(msg)
            await self.channel.send(Welcome(self.id, self.cfg.server_hz))
            self.core.opened(loop.time())
            log.info("session %d (%s): %s %dx%d, worker %s pid %d (event loop pid %d)", self.id,
                     self.channel.peer, msg.method, msg.width, msg.height, self.worker.kind, self.worker.pid,
                     os.getpid())
            tasks = [asyncio.create_task(self._reader(), name=f"s{self.id}-reader"),
                     asyncio.create_task(self._encoder(), name=f"s{self.id}-encoder"),
                     asyncio.create_task(self._sender(), name=f"s{self.id}-sender"),
                     asyncio.create_task(self._watch_worker(), name=f"s{self.id}-watch")]
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
            for t in done:
                if not t.cancelled() and t.exception() is not None:
                    raise t.exception()
        except SessionError as exc:
            log.warning("session %d (%s): %s", self.id, self.channel.peer, exc)
            await self._send_error(exc.code, str(exc), exc.retry_after_s)
        except ProtocolError as exc:
            log.warning("session %d (%s): malformed input: %s", self.id, self.channel.peer, exc)
            await self._send_error(ErrorCode.PROTOCOL, f"malformed message: {exc}")
        except (ConnectionError, OSError) as exc:
            log.info("session %d (%s): connection lost: %s", self.id, self.channel.peer, exc)
        except Exception as exc:  # noqa: BLE001 -- a session must never take the server down
            log.exception("session %d (%s): internal error", self.id, self.channel.peer)
            await self._send_error(ErrorCode.INTERNAL, f"internal server error: {type(exc).__name__}: {exc}")
        finally:
            for t in tasks:
                t.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
            await self.channel.close()
            await self._release()
            self.ticket.close()              # the session slot is free once its worker is gone
            c, q = self.core.counters, self.core.queue.counters
            self.server.session_ended(c)
            log.info("session %d ended: %d poses (%d with a gaze), %d frames encoded (mean %.0f ms each), %d sent "
                     "(%d bytes), %d reference requests, queue dropped %d stale + %d new, %d receive reports, %d frame "
                     "starts held back for the link", self.id, c.poses, c.gazes, c.frames_encoded,
                     c.encode_s_total * 1e3 / max(c.frames_encoded, 1), self.frames_sent, self.bytes_sent,
                     c.reference_requests, q.dropped_stale, q.dropped_new, c.reports, c.frames_paced)

    async def _send_error(self, code: int, text: str, retry_after_s: float = 0.0) -> None:
        try:
            await asyncio.wait_for(self.channel.send(ErrorMessage(int(code), text[:1000], retry_after_s)), 2.0)
        except Exception:  # noqa: BLE001 -- the peer may be gone already
            pass

    async def _release(self) -> None:
        if self.worker is None:
            return
        worker, self.worker = self.worker, None
        try:
            await worker.close()
        finally:
            self.server.workers.discard(worker)

    # -- tasks

    async def _reader(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            deadline = self.core.idle_deadline()       # moved only by poses the core takes
            try:
                msg = await asyncio.wait_for(self.channel.recv(),
                                             None if deadline is None else max(0.0, deadline - loop.time()))
            except asyncio.TimeoutError:
                deadline = self.core.idle_deadline()
                if deadline is not None and loop.time() >= deadline:
                    raise SessionError(ErrorCode.TIMEOUT, f"no pose received for {self.cfg.idle_timeout:g} s "
                                                          f"(only poses keep a session open)") from None
                continue
            if msg is None or isinstance(msg, Bye):
                return
            if isinstance(msg, PoseUpdate):
                try:
                    decision = self.core.pose_received(loop.time(), msg.t_client, msg.position, msg.quat, msg.gaze)
                except ValueError as exc:
                    raise ProtocolError(f"PoseUpdate: {exc}") from None
                self._decide(decision)
            elif isinstance(msg, ReferenceRequest):
                self.core.reference_requested(loop.time())
                log.info("session %d: reference requested (%s)", self.id, msg.reason)
            elif isinstance(msg, ReceiveReport):
                self._decide(self.core.report_received(loop.time(), msg.entries))
            elif isinstance(msg, ErrorMessage):
                log.warning("session %d: client error %d: %s", self.id, msg.code, msg.text)
                return
            else:
                raise SessionError(ErrorCode.PROTOCOL, f"unexpected {type(msg).__name__} from a client")

    def _decide(self, decision: EncodeFrame | None) -> None:
        """Hand a decision to the encoder; without one, wake it if the core's timer is now set (a pose that waits
        for the flood guard or its point's frame rate while the encoder is idle)."""
        if decision is not None:
            self._decisions.put_nowait(decision)
        elif not self.core.encoding and self.core.timer() is not None:
            self._decisions.put_nowait(_WAKE)

    async def _watch_worker(self) -> None:
        """End the session as soon as its worker process dies, even while no encode is under way."""
        await self.worker.died.wait()
        raise SessionError(ErrorCode.INTERNAL, f"session worker died: {self.worker.death}")

    async def _encode(self, decision: EncodeFrame) -> tuple[Frame, bool]:
        """One frame from the worker, as the wire message that carries it (the worker's bytes, not re-encoded)."""
        try:
            data, self_contained = await self.worker.encode(decision)
        except WorkerDied as exc:
            raise SessionError(ErrorCode.INTERNAL, f"session worker died: {exc}") from None
        except WorkerError as exc:
            raise SessionError(ErrorCode.INTERNAL, f"render/encode failed: {exc}") from None
        return Frame(data), self_contained

    async def _encoder(self) -> None:
        """Run the core's encode decisions one at a time; wake for its timer (flood guard, a point's frame rate),
        and look at the timer again whenever the reader says an event may have set it (:data:`_WAKE`)."""
        loop = asyncio.get_running_loop()
        while True:
            deadline = self.core.timer()
            try:
                timeout = None if deadline is None else max(0.0, deadline - loop.time())
                decision = await asyncio.wait_for(self._decisions.get(), timeout)
            except asyncio.TimeoutError:
                decision = self.core.handle_timer(loop.time())
            while decision is not None and decision is not _WAKE:
                frame, self_contained = await self._encode(decision)
                now = loop.time()
                decision = self.core.frame_encoded(now, frame, self_contained, now - decision.started)
                self._queued.set()

    async def _sender(self) -> None:
        while True:
            await self.channel.wait_sent(self.cfg.unsent_bytes)
            frame = self.core.next_to_send()
            if frame is None:
                self._queued.clear()
                await self._queued.wait()
                continue
            before = self.channel.bytes_out
            await self.channel.send(frame)
            self.core.frame_sent(asyncio.get_running_loop().time(), peek_frame_id(frame.payload), len(frame.payload))
            self.frames_sent += 1
            self.bytes_sent += self.channel.bytes_out - before
            if self.core.rate is not None and self.core.rate.point is not self._point:
                self._point = self.core.rate.point
                log.info("session %d: operating point %s (capacity %s Mbit/s, queue %s ms)", self.id,
                         self._point.name, _fmt(self.core.rate.state.capacity_mbps),
                         _fmt(self.core.rate.state.queue_delay_s, 1e3))


# ---------------------------------------------------------------------------------------------- server

class LiveServer:
    """Accepts connections (TCP, or WebRTC through :mod:`quadcast.transport.webrtc`) and runs a :class:`Session` for each."""

    def __init__(self, config: ServerConfig, make_server: Callable, transport: str = "tcp") -> None:
        """``make_server(method, renderer, MethodConfig)`` builds a session's method server (in its worker: a
        module-level function, e.g. :func:`quadcast.methods.make_server`)."""
        if transport not in ("tcp", "webrtc"):
            raise ValueError(f"--transport: expected tcp or webrtc, got {transport!r}")
        if config.pace_mbit is not None and transport != "webrtc":
            raise ValueError("--pace paces WebRTC's RTP packets; over TCP the kernel's congestion control sets the "
                             "pace (use --transport webrtc, or leave --pace out)")
        from quadcast.render.scene import load_scene
        self.config, self.transport, self.make_server = config, transport, make_server
        self.totals = ServerCounters()      # of the sessions that ended
        self.sessions_ended = 0
        self.scene = load_scene(config.scene)
        self.admission = Admission(config.limits())   # every listener's connections and sessions
        self.ssl = config.ssl_context()
        self.workers: set = set()          # the sessions' live workers (killed at close if still there)
        self._ids = itertools.count(1)
        self._sessions: set[asyncio.Task] = set()
        self._tcp: asyncio.AbstractServer | None = None
        self._rtc = None
        self._spares: collections.deque[ProcessWorker] = collections.deque()
        self._closing = False

    def _spawn_spares(self, at_most: int | None = None) -> None:
        """Boot worker processes until ``spare_workers`` (or `at_most`, if fewer) are spare (a session claims one
        instead of waiting for a process to boot: seconds on a loaded machine). Those booted while no session runs
        warm up (``config.warm_up``, :class:`SessionHost`); one booted beside running sessions does not, as that
        would take more of the CPU their frames need."""
        if self.config.worker != "process" or self._closing:
            return
        wanted = self.config.spare_workers if at_most is None else min(at_most, self.config.spare_workers)
        warm_up = self.warm_up_specs() if self.config.warm_up and self.active == 0 else ()
        while len(self._spares) < wanted:
            self._spares.append(ProcessWorker(SessionHost, (self.config.scene, warm_up), "session-worker"))

    def warm_up_specs(self) -> tuple[PipelineSpec, ...]:
        """The pipelines a spare worker warms up with: every method served, at :data:`WARM_UP_SIZE`."""
        cfg = self.config
        return tuple(PipelineSpec(self.make_server, cfg.scene, method, *WARM_UP_SIZE, 60.0, cfg.viewcell_m,
                                  cfg.reference_every, cfg.crf, cfg.chroma_qp_offset) for method in cfg.methods)

    @property
    def active(self) -> int:
        """Sessions running now."""
        return self.admission.sessions

    def make_worker(self, name: str, spec: PipelineSpec) -> "_ProcessWorker | _ThreadWorker":
        """A new session's worker (not started): a spare worker process, or a GL thread (``worker="thread"``)."""
        if self.config.worker == "process":
            return _ProcessWorker(name, spec, self.claim_process())
        return _ThreadWorker(name, spec, self.scene)

    def claim_process(self) -> ProcessWorker:
        """A worker process for a new session: the oldest (warmest) spare, or a new one. While sessions run, the
        spare it took is replaced only if it was the last: booting a process (modules, GL context, scene: about
        3 s of CPU here) beside running sessions takes their frames' CPU (`quadcast demo`: 38-39 frames in its 10 s
        against 43-50 without). The others are booted when no session runs (`session_ended`)."""
        proc = None
        while self._spares and proc is None:
            proc = self._spares.popleft()
            if not proc.alive:
                proc.close(timeout=0.0)
                proc = None
        if proc is None:
            proc = ProcessWorker(SessionHost, (self.config.scene,), "session-worker")
        self._spawn_spares(at_most=1)
        return proc

    def session_ended(self, counters: ServerCounters) -> None:
        """Add an ended session's counters to :attr:`totals`."""
        self.sessions_ended += 1
        for name, value in vars(counters).items():
            setattr(self.totals, name, getattr(self.totals, name) + value)
        if self.active == 0:             # the machine is free again: boot the spares sessions took
            self._spawn_spares()

    @property
    def port(self) -> int:
        if self._tcp is not None:
            return self._tcp.sockets[0].getsockname()[1]
        if self._rtc is not None:
            return self._rtc.port
        raise RuntimeError("LiveServer.port: not started")

    async def start(self) -> None:
        cfg = self.config
        self._spawn_spares()
        # the first session should not wait for a process to boot, nor share the CPU with spares still booting
        for spare in list(self._spares):
            try:
                await spare.start(cfg.worker_start_timeout)
                warmed = await spare.call("warm_up_times")
            except (WorkerDied, WorkerError, asyncio.TimeoutError) as exc:
                await self._close_spares()
                raise RuntimeError(f"server: the session worker process could not start: {exc}") from None
            if warmed:
                log.info("session worker %d warmed up: %s", spare.pid,
                         ", ".join(f"{method} {ms:.0f} ms" for method, ms in warmed.items()))
        if self.transport == "tcp":
            self._tcp = await asyncio.start_server(self._on_tcp, cfg.host, cfg.port, limit=1 << 16)
        else:
            from quadcast.transport.webrtc import SignallingPolicy, WebRtcListener
            policy = SignallingPolicy(token=cfg.token, ssl=self.ssl, admission=self.admission,
                                      max_peer_connections=cfg.max_peer_connections, stun=cfg.stun)
            self._rtc = WebRtcListener(cfg.host, cfg.port, self.serve_channel,
                                       max_message_bytes=cfg.max_message_bytes, policy=policy,
                                       pace_mbit=cfg.pace_mbit)
            await self._rtc.start()

    async def _close_spares(self) -> None:
        self._closing = True
        spares, self._spares = list(self._spares), collections.deque()
        for spare in spares:
            await asyncio.get_running_loop().run_in_executor(None, lambda s=spare: s.close(timeout=1.0))

    async def _on_tcp(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """An accepted TCP connection: admission first (nothing is read before), then TLS, then the session -- or,
        when its first bytes are an HTTP request, the browser viewer (server/web.py)."""
        from quadcast.server.web import serve_web, starts_http
        peer = writer.get_extra_info("peername")
        peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        ticket = self.admission.open(peer_ip(peer))
        if isinstance(ticket, Refusal):
            log.info("connection from %s refused: %s", peer, ticket.text)
            if self.ssl is None:         # in clear the refusal costs one write; under TLS just close
                writer.write(encode_message(ErrorMessage(int(ticket.code), ticket.text, ticket.retry_after_s)))
            writer.close()
            return
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.config.handshake_timeout
        try:
            if self.ssl is not None:
                try:
                    # (its own timeout: wrapped in wait_for, start_tls never completes on Python 3.11)
                    await writer.start_tls(self.ssl, ssl_handshake_timeout=self.config.handshake_timeout)
                except (asyncio.TimeoutError, ssl.SSLError, ConnectionError, OSError) as exc:
                    log.info("connection from %s: TLS handshake failed: %s", peer,
                             exc or "timed out")
                    writer.close()
                    return
            # the first bytes tell a binary-protocol client from a browser (HTTP: the viewer page, its WebSocket)
            try:
                first = await asyncio.wait_for(reader.readexactly(4), max(0.0, deadline - loop.time()))
            except asyncio.IncompleteReadError as exc:
                first = exc.partial
            except (asyncio.TimeoutError, ConnectionError, OSError):
                first = b""          # the session's own handshake timeout ends it with an ErrorMessage
            if starts_http(first):
                await serve_web(self, reader, writer, first, ticket)
            else:
                await self.serve_channel(TcpChannel(reader, writer, self.config.max_message_bytes, initial=first),
                                         ticket, deadline)
        finally:
            ticket.close()

    async def serve_channel(self, channel: Channel, ticket: Ticket | None = None,
                            handshake_deadline: float | None = None) -> None:
        """Run one session on an accepted channel until it ends (``ticket``: its admission, taken here from the
        channel's peer address when not given)."""
        if ticket is None:
            ticket = self.admission.open(peer_ip(channel.peer))
            if isinstance(ticket, Refusal):
                log.info("connection from %s refused: %s", channel.peer, ticket.text)
                try:
                    await asyncio.wait_for(channel.send(ErrorMessage(int(ticket.code), ticket.text,
                                                                     ticket.retry_after_s)), 2.0)
                except Exception:  # noqa: BLE001 -- the peer may be gone already
                    pass
                await channel.close()
                return
        task = asyncio.current_task()
        self._sessions.add(task)
        try:
            await Session(self, channel, next(self._ids), ticket, handshake_deadline).run()
        except asyncio.CancelledError:
            pass            # server shutdown: the session cleaned up in its finally; end this task normally
        finally:
            ticket.close()
            self._sessions.discard(task)

    async def close(self) -> None:
        """Stop accepting, end every session (each logs its figures), close the listeners; bounded in time."""
        if self._tcp is not None:
            self._tcp.close()
        await self._close_spares()
        for t in list(self._sessions):
            t.cancel()
        if self._sessions:
            await asyncio.wait(list(self._sessions), timeout=10.0)
        for worker in list(self.workers):     # sessions that did not end in time: no process outlives us
            if isinstance(worker, _ProcessWorker):
                log.warning("%s: killing its worker process %s at shutdown", worker.name, worker.pid)
                worker.kill_now()
        if self._rtc is not None:
            try:
                await asyncio.wait_for(self._rtc.close(), 10.0)
            except asyncio.TimeoutError:
                log.warning("WebRTC listener did not close within 10 s")

    async def serve_forever(self) -> None:
        if self._tcp is None and self._rtc is None:
            await self.start()
        try:
            await asyncio.Event().wait()
        finally:
            await self.close()


def server_summary_line(server: LiveServer) -> str:
    cfg = server.config
    return (f"server: listening on {cfg.host}:{server.port} ({server.transport}{', TLS' if server.ssl else ''}), "
            f"scene {cfg.scene}, methods {','.join(cfg.methods)}, {cfg.server_hz:g} Hz")

