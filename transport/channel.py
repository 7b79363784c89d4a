"""The live protocol's message channel on an asyncio TCP stream (:class:`TcpChannel`, optionally TLS: see
:mod:`quadcast.transport.tls`), and the interface every transport's channel has (:class:`Channel`;
:mod:`quadcast.transport.webrtc` has the same over WebRTC): length-prefixed messages in, typed messages out
(:mod:`quadcast.protocol.messages`, sans-I/O), with byte counters.
"""
from __future__ import annotations

import asyncio
import collections
import ssl as _ssl
import struct
import sys

try:
    import fcntl
except ImportError:    # not on Windows: there TcpChannel.unsent_bytes() is None
    fcntl = None

from quadcast.protocol.frame import FramePayload
from quadcast.protocol.messages import Frame, Message, MessageDecoder, encode_message

__all__ = ["Channel", "TcpChannel", "open_tcp_channel", "ServerBusy"]

_READ_CHUNK = 1 << 16

_SIOCOUTQNSD = 0x894B          # Linux's ioctl for a TCP socket's bytes not yet sent (linux/sockios.h)
_UNSENT_POLL_S = (0.002, 0.010)   # how often a waiting sender looks again: first, and at most


class ServerBusy(ConnectionError):
    """The server has no room now (ErrorCode.BUSY, or HTTP 503 from WebRTC signalling): try again after
    ``retry_after_s`` seconds."""

    def __init__(self, text: str, retry_after_s: float) -> None:
        super().__init__(text)
        self.retry_after_s = float(retry_after_s)


class Channel:
    """A bidirectional message channel (the interface of :class:`TcpChannel` and :class:`quadcast.transport.webrtc.WebRtcChannel`).

    ``recv()`` returns the next message, or ``None`` once the peer closed; it raises
    :class:`quadcast.protocol.errors.ProtocolError` for malformed input. ``send(msg)`` writes one message (waiting while
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

    async def wait_sent(self, at_most_bytes: int) -> None:
        """Wait until at most ``at_most_bytes`` of what was sent still wait on this side to go out (where the
        transport can tell; otherwise at once). A sender that waits here before it picks its next frame picks
        the newest one, instead of queueing frames behind a slow link."""

    async def close(self) -> None:
        raise NotImplementedError


class TcpChannel(Channel):
    """The wire protocol on an asyncio TCP stream; incoming messages are capped at ``max_message_bytes``.
    ``initial``: bytes already read off the stream (a server that looked at them to tell protocols apart)."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 max_message_bytes: int, initial: bytes = b"") -> None:
        self.reader, self.writer = reader, writer
        self.decoder = MessageDecoder(max_message_bytes)
        self._pending: collections.deque[Message] = collections.deque()
        self.bytes_in = self.bytes_out = 0
        self._initial = bytes(initial)
        peer = writer.get_extra_info("peername")
        self.peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        self.closed = False

    async def recv(self) -> Message | None:
        while not self._pending:
            data, self._initial = self._initial, b""
            try:
                data = data or await self.reader.read(_READ_CHUNK)
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

    def unsent_bytes(self) -> int | None:
        """Bytes written but not yet on the wire: asyncio's buffer, plus the kernel's send queue not yet sent
        (Linux); None where the kernel's count cannot be read."""
        transport = self.writer.transport
        sock = self.writer.get_extra_info("socket")
        if transport is None or sock is None or fcntl is None or not sys.platform.startswith("linux"):
            return None
        try:
            queued = struct.unpack("i", fcntl.ioctl(sock.fileno(), _SIOCOUTQNSD, b"\0" * 4))[0]
        except (OSError, ValueError):
            return None
        return transport.get_write_buffer_size() + queued

    async def wait_sent(self, at_most_bytes: int) -> None:
        delay = _UNSENT_POLL_S[0]
        while not self.closed:
            unsent = self.unsent_bytes()
            if unsent is None or unsent <= at_most_bytes:
                return
            await asyncio.sleep(delay)
            delay = min(delay * 2, _UNSENT_POLL_S[1])

    async def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self.writer.close()
            await asyncio.wait_for(self.writer.wait_closed(), 2.0)
        except (ConnectionError, OSError, asyncio.TimeoutError):
            pass


async def open_tcp_channel(host: str, port: int, max_message_bytes: int, timeout: float = 5.0,
                           ssl: _ssl.SSLContext | None = None) -> TcpChannel:
    """Connect to ``host:port`` (with TLS when ``ssl`` is given: a client context, see
    :func:`quadcast.transport.tls.client_context`; the server's name checked against ``host``); raises OSError /
    asyncio.TimeoutError when nobody answers, :class:`ssl.SSLCertVerificationError` for a certificate that does
    not verify. Connecting and the TLS handshake share ``timeout``."""
    reader, writer = await asyncio.wait_for(
        asyncio.open_connection(host, port, ssl=ssl, server_hostname=host if ssl is not None else None), timeout)
    return TcpChannel(reader, writer, max_message_bytes)
