"""A netem-like TCP proxy for the quadcast wire protocol (what ``quadcast link`` runs).

:class:`LinkProxy` listens on ``listen_host:listen_port``; for every accepted connection it opens one to
``target_host:target_port`` and forwards both directions.  It forwards *messages*, not bytes: each direction
splits its stream with :class:`quadcast.protocol.messages.MessageSplitter` (u32 length framing) and offers every whole
message to that direction's :class:`quadcast.sim.link.LinkModel` at ``loop.time()``; the message is written out when
the model says it arrives.  Delay and jitter postpone messages, and ``rate_mbit`` serializes them one after the
other.  With reliable models (``quadcast link``'s default) loss is of TCP segments: the model sends them again and
cuts its window, so a loss delays a message and those after it, and slows the stream; with datagram models it drops
whole messages (the receiver's framing never breaks).  A stream that is not valid framing (length 0 or above
``max_message_bytes``) closes that connection, with a log line.

The two models are the link: all connections share them (one bottleneck per direction, like netem on an
interface; a reliable model's window is one TCP stream's).  A datagram direction has a drop-tail queue of
``max_queue_bytes``: the bytes waiting to be serialized by the model plus those waiting in the receiver's socket
buffer; a message that would overflow it is dropped (counted as a loss) -- unless nothing is queued at all, so one
message larger than the queue still gets through an idle link.  Without a rate nothing waits to be serialized.  A
reliable model has its own queue (its ``queue_bytes``: segments that overflow it are lost and sent again), and its
direction stops reading from the sender while a window's worth waits to leave, as a TCP sender's socket buffer
would: the sending side's own socket fills (towards the target, the server, the proxy's receive buffer is small, see
:data:`RELIABLE_RCVBUF_BYTES`), and a server that watches its unsent bytes sees the link's pace.

When one side sends EOF, the proxy delivers what is still in flight towards the other side, then half-closes
towards it (``write_eof``), like TCP; the connection is closed once both directions are shut, or
``half_close_timeout`` seconds after the first one, or at once when a side fails or a stream is not valid framing.

Example::

    proxy = LinkProxy("127.0.0.1", 9000, "127.0.0.1", 9001,
                      up=parse_link_args("20ms", "2ms", "50mbit", "0.1%", seed=1),
                      down=parse_link_args("20ms", "2ms", "200mbit", "0.1%", seed=2))
    await proxy.start()
    ...
    await proxy.close()
"""
from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import socket
from dataclasses import dataclass, field

from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.messages import DEFAULT_MAX_MESSAGE_BYTES, MessageSplitter
from quadcast.sim.link import LinkModel, parse_duration_ms, parse_loss, parse_rate_mbit
from quadcast.sim.ratetrace import RateTrace

__all__ = ["DEFAULT_MAX_QUEUE_BYTES", "DirectionStats", "LinkProxy", "ProxyStats", "ShapedDirection", "ShapedProxy",
           "parse_link_args"]

log = logging.getLogger("quadcast.proxy")

DEFAULT_MAX_QUEUE_BYTES = 16 * 1024 * 1024
"""Default drop-tail queue limit per direction."""

_READ_CHUNK = 1 << 16

RELIABLE_RCVBUF_BYTES = 4 * 1024
"""The receive buffer of the proxy's socket to the target when the server -> client direction is reliable: small, so
that when the model's window holds the stream back the server's own kernel (and a sender watching its unsent
bytes) feels it, as over a real path, instead of the loopback's megabytes of autotuned buffer taking it all in. The
socket also takes the path's segment size (the model's ``mss_bytes``): with loopback's 64 kB segments a window this
small would open only after the persist timer's probes."""


def parse_link_args(delay: str | float = 0, jitter: str | float = 0, rate: str | float | None = None,
                    loss: str | float = 0, *, jitter_dist: str = "uniform", reorder: bool = False,
                    seed: int = 0, rate_trace: RateTrace | None = None, reliable: bool = False,
                    rtt: str | float | None = None, queue_bytes: int | None = None) -> LinkModel:
    """A :class:`LinkModel` from netem/tc-style CLI strings: ``delay="20ms"``, ``jitter="2ms"``,
    ``rate="50mbit"`` (``None`` or ``""`` = unlimited), ``loss="0.5%"``; or a Mahimahi ``rate_trace`` instead of
    the rate (its time 0 is when the proxy starts). ``reliable`` carries a TCP stream (segments lost and sent
    again, ``rtt`` its round trip: by default twice the delay, ``queue_bytes`` its bottleneck's drop-tail queue)."""
    rate_mbit = None if rate is None or (isinstance(rate, str) and not rate.strip()) else parse_rate_mbit(rate)
    return LinkModel(delay_ms=parse_duration_ms(delay), jitter_ms=parse_duration_ms(jitter), jitter=jitter_dist,
                     rate_mbit=rate_mbit, loss=parse_loss(loss), reorder=reorder, seed=seed, rate_trace=rate_trace,
                     reliable=reliable, rtt_ms=None if rtt is None else parse_duration_ms(rtt), queue_bytes=queue_bytes)


@dataclass
class DirectionStats:
    """Counters of one direction (``up`` = client -> target, ``down`` = target -> client)."""

    messages_in: int = 0          # whole messages read from the sending side
    bytes_in: int = 0
    messages_forwarded: int = 0   # written to the receiving side
    bytes_forwarded: int = 0
    messages_dropped: int = 0     # link loss + queue overflow
    bytes_dropped: int = 0
    dropped_loss: int = 0         # messages dropped by the link model's random loss
    dropped_queue: int = 0        # messages dropped because the queue was full


@dataclass
class ProxyStats:
    """Counters of a :class:`LinkProxy` since :meth:`LinkProxy.start`."""

    up: DirectionStats = field(default_factory=DirectionStats)
    down: DirectionStats = field(default_factory=DirectionStats)
    connections_accepted: int = 0
    connections_open: int = 0
    upstream_failures: int = 0    # the target refused / could not be reached
    framing_errors: int = 0       # connections closed because a stream was not valid framing


class ShapedDirection:
    """One shaped direction: the link model, its queue accounting and the task delivering its arrivals.

    :meth:`submit` takes a message with its sink, which has ``in_flight`` (a dict by direction name),
    ``write_buffer_size(name)`` (bytes still waiting in the receiving side's buffer) and ``deliver(name, raw)``
    (called when the model says the message arrives): a proxied TCP connection here, a UDP route in
    :mod:`quadcast.sim.rtc_proxy`."""

    def __init__(self, name: str, link: LinkModel, max_queue_bytes: int, stats: DirectionStats) -> None:
        self.name, self.link, self.max_queue_bytes, self.stats = name, link, max_queue_bytes, stats
        self._backlog: collections.deque[tuple[float, int]] = collections.deque()  # (t_depart, size)
        self._backlog_bytes = 0
        self._wake = asyncio.Event()
        self.task: asyncio.Task | None = None

    def queued_bytes(self, now: float) -> int:
        """Bytes accepted by the model that have not finished serializing at ``now``."""
        while self._backlog and self._backlog[0][0] <= now:
            self._backlog_bytes -= self._backlog.popleft()[1]
        return self._backlog_bytes

    def submit(self, conn, raw: bytes, now: float) -> None:
        self.stats.messages_in += 1
        self.stats.bytes_in += len(raw)
        waiting = self.queued_bytes(now) + conn.write_buffer_size(self.name)
        if not self.link.reliable and waiting > 0 and waiting + len(raw) > self.max_queue_bytes:
            self._drop(len(raw), queue=True)
            return
        d = self.link.send(now, (conn, raw), len(raw))
        if d is None:
            self._drop(len(raw), queue=False)
            return
        if d.t_depart > now:
            self._backlog.append((d.t_depart, len(raw)))
            self._backlog_bytes += len(raw)
        conn.in_flight[self.name] += 1
        self._wake.set()

    async def wait_for_room(self, conn) -> None:
        """A reliable link's sender stops while a window's worth waits to leave, as a TCP sender's socket buffer
        (which Linux sizes to about two windows: one in flight, one waiting) stops its writer: the proxy reads no
        further and the sending side's own socket fills."""
        loop = asyncio.get_running_loop()
        while not conn.closed:
            now = loop.time()
            if self.queued_bytes(now) + conn.write_buffer_size(self.name) < self.link.window_bytes:
                return
            until = self._backlog[0][0] if self._backlog else now + 0.005   # the receiver's buffer drains itself
            await asyncio.sleep(max(until - now, 0.001))

    def _drop(self, size: int, queue: bool) -> None:
        self.stats.messages_dropped += 1
        self.stats.bytes_dropped += size
        if queue:
            self.stats.dropped_queue += 1
        else:
            self.stats.dropped_loss += 1

    async def run(self) -> None:
        """Write every message to its receiver when the model says it arrives."""
        loop = asyncio.get_running_loop()
        while True:
            nxt = self.link.next_arrival()
            timer = None if nxt is None else loop.call_at(nxt, self._wake.set)
            try:
                await self._wake.wait()  # set by the timer, or by a submit (which may arrive earlier)
            finally:
                if timer is not None:
                    timer.cancel()
            self._wake.clear()
            for d in self.link.poll(loop.time()):
                conn, raw = d.message
                conn.deliver(self.name, raw)


class _Connection:
    """One proxied client <-> target connection pair."""

    def __init__(self, proxy: "LinkProxy", client: tuple, target: tuple) -> None:
        self.proxy = proxy
        self.readers = {"up": client[0], "down": target[0]}   # direction -> the stream it reads
        self.writers = {"up": target[1], "down": client[1]}   # direction -> the stream it writes
        self.in_flight = {"up": 0, "down": 0}
        self.eof = {"up": False, "down": False}
        self.shut = {"up": False, "down": False}    # EOF passed on to the receiving side
        self.closed = False
        self._linger: asyncio.TimerHandle | None = None
        self.tasks: list[asyncio.Task] = []
        self.peer = client[1].get_extra_info("peername")

    def write_buffer_size(self, direction: str) -> int:
        transport = self.writers[direction].transport
        return 0 if transport is None or self.closed else transport.get_write_buffer_size()

    def start(self) -> None:
        self.tasks = [asyncio.create_task(self._pump(d), name=f"proxy-{d}-{self.peer}") for d in ("up", "down")]

    async def _pump(self, direction: str) -> None:
        """Read the sending side, split it into messages and offer each to the direction's link."""
        reader, shaped = self.readers[direction], self.proxy._directions[direction]
        splitter = MessageSplitter(self.proxy.max_message_bytes)
        loop = asyncio.get_running_loop()
        try:
            while not self.closed:
                data = await reader.read(_READ_CHUNK)
                if not data:
                    break
                for raw in splitter.feed_raw(data):
                    shaped.submit(self, raw, loop.time())
                if shaped.link.reliable:
                    await shaped.wait_for_room(self)
        except ProtocolError as exc:
            self.proxy.stats.framing_errors += 1
            log.warning("proxy %s: closing connection from %s: invalid framing on the %s stream: %s",
                        self.proxy.address, self.peer, direction, exc)
            self.close()
            return
        except (ConnectionError, OSError) as exc:
            log.info("proxy %s: connection from %s: %s side failed: %s", self.proxy.address, self.peer,
                     "client" if direction == "up" else "target", exc)
            self.close()
            return
        self.eof[direction] = True
        self._maybe_finish(direction)

    def deliver(self, direction: str, raw: bytes) -> None:
        self.in_flight[direction] -= 1
        if self.closed:
            return
        stats = self.proxy._directions[direction].stats
        try:
            self.writers[direction].write(raw)
        except (ConnectionError, OSError, RuntimeError):
            self.close()
            return
        stats.messages_forwarded += 1
        stats.bytes_forwarded += len(raw)
        self._maybe_finish(direction)

    def _maybe_finish(self, direction: str) -> None:
        """Once a side sent EOF and its last message was delivered, half-close towards the other side; once both
        directions are shut (or ``half_close_timeout`` after the first one), close the connection."""
        if not self.eof[direction] or self.in_flight[direction] or self.shut[direction] or self.closed:
            return
        self.shut[direction] = True
        writer = self.writers[direction]
        try:
            if not writer.can_write_eof():
                raise OSError("transport cannot half-close")
            writer.write_eof()
        except (OSError, RuntimeError):
            self.close()
            return
        if all(self.shut.values()):
            self.close()
        elif self._linger is None:
            self._linger = asyncio.get_running_loop().call_later(self.proxy.half_close_timeout, self.close)

    def close(self) -> None:
        """Close both sides (buffered data is still flushed by the transports) and stop the readers."""
        if self.closed:
            return
        self.closed = True
        if self._linger is not None:
            self._linger.cancel()
        self.proxy.stats.connections_open -= 1
        self.proxy._connections.discard(self)
        for w in self.writers.values():
            w.close()
        current = asyncio.current_task()
        for t in self.tasks:
            if t is not current:
                t.cancel()


class ShapedProxy:
    """What both proxies share (:class:`LinkProxy` here, :class:`quadcast.sim.rtc_proxy.RtcLinkProxy`): a listening
    socket, a target, the two shaped directions and the counters. A subclass has ``_on_accept`` (the listening
    socket's connection handler) and ``close``; ``listen_port=0`` picks a free port (see :attr:`port`). Use ``await
    start()`` / ``await close()`` or ``async with``."""

    task_name = "proxy-link"

    def __init__(self, listen_host: str, listen_port: int, target_host: str, target_port: int,
                 up: LinkModel, down: LinkModel, max_queue_bytes: int) -> None:
        name = type(self).__name__
        if not isinstance(up, LinkModel) or not isinstance(down, LinkModel):
            raise TypeError(f"{name}: up and down must be LinkModel instances, got "
                            f"{type(up).__name__} and {type(down).__name__}")
        if up is down:
            raise ValueError(f"{name}: up and down must be two different LinkModel instances")
        if max_queue_bytes <= 0:
            raise ValueError(f"{name}: max_queue_bytes must be > 0, got {max_queue_bytes}")
        self.listen_host, self.listen_port = listen_host, int(listen_port)
        self.target_host, self.target_port = target_host, int(target_port)
        self.up, self.down = up, down
        self.max_queue_bytes = int(max_queue_bytes)
        self.stats = ProxyStats()
        self._server: asyncio.AbstractServer | None = None
        self._directions: dict[str, ShapedDirection] = {}

    @property
    def port(self) -> int:
        """The port actually listened on (useful with ``listen_port=0``)."""
        if self._server is None:
            raise RuntimeError(f"{type(self).__name__}.port: the proxy is not started")
        return self._server.sockets[0].getsockname()[1]

    @property
    def address(self) -> str:
        port = self.port if self._server is not None else self.listen_port
        return f"{self.listen_host}:{port}->{self.target_host}:{self.target_port}"

    def _reader_limit(self) -> int:
        """asyncio's read buffer per stream (it stops reading the socket at twice this): small with a reliable
        direction, see :data:`RELIABLE_RCVBUF_BYTES`."""
        return RELIABLE_RCVBUF_BYTES // 2 if self.up.reliable or self.down.reliable else 1 << 16

    async def _open_target(self) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        """The connection to the target; with a reliable server -> client direction, through a socket with a small
        receive buffer and the path's segment size (:data:`RELIABLE_RCVBUF_BYTES`)."""
        if not self.down.reliable:
            return await asyncio.open_connection(self.target_host, self.target_port, limit=self._reader_limit())
        loop = asyncio.get_running_loop()
        family, kind, proto, _, address = (await loop.getaddrinfo(self.target_host, self.target_port,
                                                                  type=socket.SOCK_STREAM))[0]
        sock = socket.socket(family, kind, proto)
        try:
            sock.setblocking(False)
            options = ((socket.SOL_SOCKET, socket.SO_RCVBUF, RELIABLE_RCVBUF_BYTES),
                       (socket.IPPROTO_TCP, getattr(socket, "TCP_MAXSEG", None), self.down.mss_bytes))
            for level, option, value in options:
                with contextlib.suppress(OSError, TypeError):   # without them: a looser emulation, not an error
                    sock.setsockopt(level, option, value)
            await loop.sock_connect(sock, address)
        except BaseException:
            sock.close()
            raise
        return await asyncio.open_connection(sock=sock, limit=self._reader_limit())

    async def start(self) -> None:
        """Start the two directions and listen; returns once the socket is bound."""
        if self._server is not None:
            raise RuntimeError(f"{type(self).__name__}.start: already started")
        for link in (self.up, self.down):        # a rate trace starts with the proxy
            if link.rate_trace is not None:
                link.trace_start = asyncio.get_running_loop().time()
        self._directions = {"up": ShapedDirection("up", self.up, self.max_queue_bytes, self.stats.up),
                            "down": ShapedDirection("down", self.down, self.max_queue_bytes, self.stats.down)}
        for d in self._directions.values():
            d.task = asyncio.create_task(d.run(), name=f"{self.task_name}-{d.name}")
        self._server = await asyncio.start_server(self._on_accept, self.listen_host, self.listen_port,
                                                  limit=self._reader_limit())
        log.info("%s %s: listening (up: %r, down: %r)", self.task_name, self.address, self.up, self.down)

    async def _on_accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        raise NotImplementedError

    async def close(self) -> None:
        raise NotImplementedError

    async def serve_forever(self) -> None:
        """Start (if needed) and run until cancelled; closes on the way out."""
        if self._server is None:
            await self.start()
        try:
            await self._server.serve_forever()
        finally:
            await self.close()

    async def __aenter__(self):
        await self.start()
        return self

    async def __aexit__(self, *exc) -> None:
        await self.close()


class LinkProxy(ShapedProxy):
    """An asyncio TCP proxy shaping each direction with its own :class:`quadcast.sim.link.LinkModel`.

    ``up`` shapes client -> target, ``down`` target -> client. :attr:`stats` counts messages and bytes forwarded
    and dropped per direction.
    """

    def __init__(self, listen_host: str, listen_port: int, target_host: str, target_port: int,
                 up: LinkModel, down: LinkModel, *, max_queue_bytes: int = DEFAULT_MAX_QUEUE_BYTES,
                 max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES, connect_timeout: float = 5.0,
                 half_close_timeout: float = 2.0) -> None:
        super().__init__(listen_host, listen_port, target_host, target_port, up, down, max_queue_bytes)
        self.max_message_bytes = int(max_message_bytes)
        self.connect_timeout = float(connect_timeout)
        self.half_close_timeout = float(half_close_timeout)
        self._connections: set[_Connection] = set()
        self._handlers: set[asyncio.Task] = set()

    async def close(self) -> None:
        """Stop listening, close every proxied connection and stop the link tasks."""
        server, self._server = self._server, None
        if server is not None:
            server.close()
        conns = list(self._connections)
        tasks = [t for c in conns for t in c.tasks] + list(self._handlers)
        for conn in conns:
            conn.close()
        tasks += [d.task for d in self._directions.values() if d.task is not None]
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if server is not None:
            await server.wait_closed()

    async def _on_accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        self._handlers.add(task)
        self.stats.connections_accepted += 1
        peer = writer.get_extra_info("peername")
        try:
            try:
                target = await asyncio.wait_for(self._open_target(), self.connect_timeout)
            except (OSError, asyncio.TimeoutError) as exc:
                self.stats.upstream_failures += 1
                log.warning("proxy %s: cannot reach the target for %s: %s", self.address, peer, exc)
                writer.close()
                return
            conn = _Connection(self, (reader, writer), target)
            self._connections.add(conn)
            self.stats.connections_open += 1
            conn.start()
            await asyncio.gather(*conn.tasks, return_exceptions=True)
        except asyncio.CancelledError:  # close(): end quietly (asyncio logs a callback task that ends cancelled)
            writer.close()
        finally:
            self._handlers.discard(task)
