"""I/O shared by the live server and client: the GL worker thread and the TCP message channel.

:class:`GLWorker` is the one thread of a process (or of one live server / client inside a process) that runs GL.
moderngl contexts are current on one thread, so every GL call -- rendering, encoding, decoding into textures --
goes through :meth:`GLWorker.call` from the asyncio loop, one job at a time in submission order, and the event loop
(pose I/O) never waits on the GPU. The worker makes its own headless EGL context, so several workers (a server and
a client in one test process) and a main-thread :func:`render.gl.gl_context` coexist.

:class:`TcpChannel` is the sans-I/O protocol (:mod:`protocol.messages`) on an asyncio stream: length-prefixed
messages in, typed messages out, with byte counters. :mod:`sim.webrtc` has the same interface over WebRTC.
"""
from __future__ import annotations

import asyncio
import collections
import concurrent.futures
import ctypes.util
import threading
from typing import Any, Callable

import moderngl

from protocol.frame import FramePayload
from protocol.messages import Frame, Message, MessageDecoder, encode_message
from render.gl import EGL_PACKAGES, REQUIRED_GL, GLUnavailableError

__all__ = ["GLWorker", "Channel", "TcpChannel", "open_tcp_channel", "contains_idr", "is_self_contained"]

_READ_CHUNK = 1 << 16


class GLWorker:
    """A thread owning a private headless GL context; runs submitted jobs one at a time, in order.

    ``await worker.call(fn, *args)`` runs ``fn(*args)`` on the thread and returns its result (or raises its
    exception). :attr:`ctx` is the thread's context: pass it to everything that makes GL objects
    (``DeferredRenderer(scene, worker.ctx)``, ``make_client(name, config, worker.ctx)``) and only touch those
    objects inside jobs. :meth:`close` finishes the queued jobs and stops the thread.
    """

    def __init__(self, name: str = "gl") -> None:
        self._jobs: "collections.deque[tuple | None]" = collections.deque()
        self._wake = threading.Condition()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.ctx: moderngl.Context | None = None
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise self._error

    def _run(self) -> None:
        try:
            if ctypes.util.find_library("EGL") is None:
                raise GLUnavailableError(f"libEGL was not found: install Debian's {EGL_PACKAGES}")
            try:
                self.ctx = moderngl.create_standalone_context(backend="egl", require=REQUIRED_GL)
            except Exception as exc:
                raise GLUnavailableError(f"GL worker: could not create a headless GL {REQUIRED_GL} context through "
                                         f"EGL ({exc}); Mesa needs {EGL_PACKAGES}") from exc
        except BaseException as exc:
            self._error = exc
            self._ready.set()
            return
        self._ready.set()
        while True:
            with self._wake:
                while not self._jobs:
                    self._wake.wait()
                job = self._jobs.popleft()
            if job is None:
                break
            future, fn, args = job
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(fn(*args))
            except BaseException as exc:  # handed to the caller
                future.set_exception(exc)
        self.ctx.release()

    def submit(self, fn: Callable[..., Any], *args) -> concurrent.futures.Future:
        """Queue ``fn(*args)``; returns a future of its result."""
        if self._closed:
            raise RuntimeError("GLWorker.submit: the worker is closed")
        future: concurrent.futures.Future = concurrent.futures.Future()
        with self._wake:
            self._jobs.append((future, fn, args))
            self._wake.notify()
        return future

    async def call(self, fn: Callable[..., Any], *args) -> Any:
        """Run ``fn(*args)`` on the GL thread without blocking the event loop."""
        return await asyncio.wrap_future(self.submit(fn, *args))

    @property
    def pending(self) -> int:
        """Jobs queued and not started."""
        return len(self._jobs)

    def close(self, timeout: float = 30.0) -> None:
        """Run what is queued, then stop the thread and release the context."""
        if self._closed:
            return
        self._closed = True
        with self._wake:
            self._jobs.append(None)
            self._wake.notify()
        self._thread.join(timeout)


def contains_idr(access_unit: bytes) -> bool:
    """Whether an Annex-B H.264 access unit holds an IDR slice (NAL type 5)."""
    from client.video import nal_unit_types
    return 5 in nal_unit_types(access_unit)


def is_self_contained(payload: FramePayload) -> bool:
    """A frame the client can apply whatever it received before: a reference frame whose video is an IDR."""
    from protocol.frame import PayloadType
    return payload.frame_type == PayloadType.REFERENCE and contains_idr(payload.video)


class Channel:
    """A bidirectional message channel (the interface of :class:`TcpChannel` and :class:`sim.webrtc.WebRtcChannel`).

    ``recv()`` returns the next message, or ``None`` once the peer closed; it raises
    :class:`protocol.errors.ProtocolError` for malformed input. ``send(msg)`` writes one message (waiting while
    the transport's buffer is full); ``send_frame(payload)`` sends a :class:`FramePayload`.
    ``bytes_in`` / ``bytes_out`` count what crossed the transport.
    """

    bytes_in: int = 0
    bytes_out: int = 0
    peer: str = "?"

    async def recv(self) -> Message | None:
        raise NotImplementedError

    async def send(self, msg: Message) -> None:
        raise NotImplementedError

    async def send_frame(self, payload: FramePayload) -> None:
        await self.send(Frame.from_payload(payload))

    async def close(self) -> None:
        raise NotImplementedError


class TcpChannel(Channel):
    """The wire protocol on an asyncio TCP stream; incoming messages are capped at ``max_message_bytes``."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 max_message_bytes: int) -> None:
        self.reader, self.writer = reader, writer
        self.decoder = MessageDecoder(max_message_bytes)
        self._pending: collections.deque[Message] = collections.deque()
        self.bytes_in = self.bytes_out = 0
        peer = writer.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        self.closed = False

    async def recv(self) -> Message | None:
        while not self._pending:
            try:
                data = await self.reader.read(_READ_CHUNK)
            except (ConnectionError, OSError):
                return None
            if not data:
                return None
            self.bytes_in += len(data)
            self._pending.extend(self.decoder.feed(data))   # ProtocolError on malformed input
        return self._pending.popleft()

    async def send(self, msg: Message) -> None:
        if self.closed:
            raise ConnectionError(f"channel to {self.peer} is closed")
        data = encode_message(msg)
        self.writer.write(data)   # one whole message per write: concurrent senders never interleave
        self.bytes_out += len(data)
        await self.writer.drain()

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.writer.close()
            await asyncio.wait_for(self.writer.wait_closed(), 2.0)
        except (ConnectionError, OSError, asyncio.TimeoutError):
            pass


async def open_tcp_channel(host: str, port: int, max_message_bytes: int, timeout: float = 5.0) -> TcpChannel:
    """Connect to ``host:port``; raises OSError / asyncio.TimeoutError when nobody answers."""
    reader, writer = await asyncio.wait_for(asyncio.open_connection(host, port), timeout)
    return TcpChannel(reader, writer, max_message_bytes)
