"""The live protocol over a WebSocket (RFC 6455), for browsers: :class:`WebSocketChannel` has the
:class:`quadcast.transport.channel.Channel` interface.

The bytes are the TCP channel's: every wire message (length prefix, type, body; :mod:`quadcast.protocol.messages`)
travels as one binary WebSocket message, and what arrives is fed to the same capped
:class:`quadcast.protocol.messages.MessageDecoder` (which accepts any chunking, so fragmented WebSocket messages
need no special case). A text message is a protocol error.

The RFC 6455 machinery -- the HTTP upgrade handshake, framing, masking, ping/pong, the close handshake, size
limits -- is the ``websockets`` package's sans-I/O :class:`websockets.server.ServerProtocol`; this module only
moves its bytes over an asyncio stream that the server already accepted. That is why the library's own server is
not used: the live server shares one port between the binary TCP protocol, the viewer's HTTP requests and the
WebSocket, and decides which after reading the first bytes (:func:`read_http_request` takes them back).

Plain HTTP responses (the viewer's static files) go through the same protocol object: :func:`send_http_response`.
"""
from __future__ import annotations

import asyncio
import http
import urllib.parse

from websockets.datastructures import Headers
from websockets.exceptions import InvalidState
from websockets.frames import Opcode
from websockets.http11 import Request, Response
from websockets.protocol import State
from websockets.server import ServerProtocol

from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.messages import LENGTH_PREFIX, Message, encode_message
from quadcast.transport.channel import TcpChannel

__all__ = ["HttpRequestError", "WebSocketChannel", "read_http_request", "send_http_response", "accept_websocket",
           "same_origin"]

_READ_CHUNK = 1 << 16


class HttpRequestError(ValueError):
    """The bytes on a connection were not one valid HTTP/1.1 request (the protocol has answered already)."""


async def _flush(protocol: ServerProtocol, writer: asyncio.StreamWriter) -> bool:
    """Write what the protocol wants sent; False once it asked to close the connection (an empty chunk)."""
    eof = False
    for data in protocol.data_to_send():
        if data:
            writer.write(data)
        else:
            eof = True
    await writer.drain()
    if eof and writer.can_write_eof():
        try:
            writer.write_eof()
        except (OSError, RuntimeError):
            pass
    return not eof


async def read_http_request(reader: asyncio.StreamReader, writer: asyncio.StreamWriter, initial: bytes,
                            max_message_bytes: int) -> tuple[ServerProtocol, Request]:
    """Parse one HTTP request from ``initial`` + the stream (request line and header sizes capped by websockets).

    Returns the protocol (ready to answer with :func:`send_http_response` or :func:`accept_websocket`) and the
    request. A request that does not parse raises :class:`HttpRequestError` after the protocol answered it (400,
    414 or 431) where HTTP allows. Incoming WebSocket messages will be capped at ``max_message_bytes`` plus the
    length prefix.
    """
    protocol = ServerProtocol(max_size=max_message_bytes + LENGTH_PREFIX.size + 1)
    data = initial
    while True:
        if data:
            protocol.receive_data(data)
        else:
            protocol.receive_eof()
        for event in protocol.events_received():
            if isinstance(event, Request):
                return protocol, event
        if protocol.handshake_exc is not None or not data:
            await _flush(protocol, writer)
            raise HttpRequestError(f"not a valid HTTP request: {protocol.handshake_exc or 'connection closed'}")
        data = await reader.read(_READ_CHUNK)


async def send_http_response(protocol: ServerProtocol, writer: asyncio.StreamWriter, status: int, body: bytes,
                             content_type: str, extra_headers: dict | None = None) -> None:
    """Answer the request with a complete response; the connection is closed after it (``Connection: close``)."""
    headers = Headers()
    headers["Content-Type"] = content_type
    headers["Content-Length"] = str(len(body))
    headers["Cache-Control"] = "no-store"
    headers["X-Content-Type-Options"] = "nosniff"
    headers["Connection"] = "close"
    for name, value in (extra_headers or {}).items():
        headers[name] = value
    protocol.send_response(Response(int(status), http.HTTPStatus(int(status)).phrase, headers, body))
    await _flush(protocol, writer)


def same_origin(request: Request) -> bool:
    """Whether a browser's ``Origin`` names the host it connected to (non-browser clients send none).

    Browsers let any page open a WebSocket to any address; refusing foreign origins keeps another site's page
    from driving a viewer session on this server (the token, when set, is checked in Hello as for every client)."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    host = request.headers.get("Host", "")
    parsed = urllib.parse.urlsplit(origin)
    return bool(parsed.netloc) and parsed.netloc.lower() == host.lower() and parsed.scheme in ("http", "https")


async def accept_websocket(protocol: ServerProtocol, request: Request, reader: asyncio.StreamReader,
                           writer: asyncio.StreamWriter, max_message_bytes: int, peer: str) -> "WebSocketChannel":
    """Complete the upgrade handshake for ``request``; raises :class:`HttpRequestError` (after answering it) when
    it is not a valid WebSocket upgrade or comes from another origin."""
    if not same_origin(request):
        await send_http_response(protocol, writer, 403, b"WebSocket from another origin refused\n", "text/plain")
        raise HttpRequestError(f"WebSocket upgrade from origin {request.headers.get('Origin')!r} refused")
    response = protocol.accept(request)
    protocol.send_response(response)
    await _flush(protocol, writer)
    if response.status_code != 101:
        raise HttpRequestError(f"not a valid WebSocket upgrade: {protocol.handshake_exc}")
    return WebSocketChannel(protocol, reader, writer, max_message_bytes, peer)


class WebSocketChannel(TcpChannel):
    """The wire protocol over an open WebSocket (see the module docstring): a :class:`TcpChannel` whose bytes are
    WebSocket-framed by ``protocol``."""

    def __init__(self, protocol: ServerProtocol, reader: asyncio.StreamReader, writer: asyncio.StreamWriter,
                 max_message_bytes: int, peer: str | None = None) -> None:
        super().__init__(reader, writer, max_message_bytes)
        self.protocol = protocol
        if peer is not None:
            self.peer = peer
        self._eof = False

    async def recv(self) -> Message | None:
        while not self._pending:
            if self._eof:
                return None
            try:
                data = await self.reader.read(_READ_CHUNK)
            except (ConnectionError, OSError):
                return None
            self.bytes_in += len(data)
            if data:
                self.protocol.receive_data(data)
            else:
                self.protocol.receive_eof()
                self._eof = True
            for frame in self.protocol.events_received():
                if frame.opcode in (Opcode.BINARY, Opcode.CONT):
                    self._pending.extend(self.decoder.feed(frame.data))   # ProtocolError on malformed input
                elif frame.opcode is Opcode.TEXT:
                    raise ProtocolError("WebSocket: text message; the quadcast protocol is binary")
                elif frame.opcode is Opcode.CLOSE:
                    self._eof = True
            try:
                if not await _flush(self.protocol, self.writer):   # pongs, the close reply
                    self._eof = True
            except (ConnectionError, OSError):
                return None
            if self.protocol.parser_exc is not None:              # e.g. too large: the protocol sent its close
                self._eof = True
                raise ProtocolError(f"WebSocket: {self.protocol.parser_exc}")
        return self._pending.popleft()

    async def send(self, msg: Message) -> None:
        if self.closed or self._eof:
            raise ConnectionError(f"channel to {self.peer} is closed")
        try:
            self.protocol.send_binary(encode_message(msg))
        except InvalidState as exc:
            raise ConnectionError(f"channel to {self.peer}: {exc}") from None
        chunks = self.protocol.data_to_send()       # one whole message per write: concurrent senders never interleave
        self.writer.write(b"".join(chunks))
        self.bytes_out += sum(map(len, chunks))
        await self.writer.drain()

    async def close(self) -> None:
        if not self.closed and self.protocol.state is State.OPEN:
            try:
                self.protocol.send_close(1000, "bye")
                await asyncio.wait_for(_flush(self.protocol, self.writer), 2.0)
            except (ConnectionError, OSError, asyncio.TimeoutError, RuntimeError):
                pass
        await super().close()
