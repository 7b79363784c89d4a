"""A netem-like link for the WebRTC transport (what ``quadcast link --webrtc`` runs).

WebRTC does not go through a TCP proxy: the peers find each other's UDP addresses in the session descriptions
(ICE candidates) and talk directly. :class:`RtcLinkProxy` therefore sits in both places:

- **Signalling.** It listens for the client's ``POST /offer`` (HTTP, the server's own protocol,
  :mod:`quadcast.transport.webrtc`), and forwards it to the server with the same headers (the bearer token
  included). Before forwarding, each IPv4 candidate of the offer is replaced by a *stand-in*: a UDP socket of the
  link's, on its listen host, standing for that client address towards the server. The server's answer gets the
  same treatment the other way before it goes back. Other candidates (IPv6) are left out, so every path the
  peers can try runs through the link.
- **Media and data.** A datagram reaching the stand-in of a client address came from the server (from one of
  its answer's addresses): it crosses the ``down`` :class:`quadcast.sim.link.LinkModel` and leaves from the
  stand-in of that server address to the real client address, so each peer sees the other only as the
  stand-ins. ``up`` shapes the client's datagrams the same way. Loss drops single datagrams (RTP packets, SCTP
  chunks, STUN checks): what recovers from it is WebRTC's own machinery (NACKs and retransmission for the video,
  SCTP for the data channels).

Both directions share one model each across sessions and have a drop-tail queue of ``max_queue_bytes``, as
:class:`quadcast.sim.proxy.LinkProxy`'s. A session's stand-ins are closed after ``idle_timeout`` seconds without a
datagram (ICE's consent checks keep a live session busy), and at most ``max_sessions`` are kept: a signalling
request beyond that gets 503. A malformed request or a description with more than ``max_candidates`` candidates
gets 400, and the server is not asked.
"""
from __future__ import annotations

import asyncio
import ipaddress
import json
import logging

from quadcast.sim.link import LinkModel
from quadcast.sim.proxy import DEFAULT_MAX_QUEUE_BYTES, ShapedProxy
from quadcast.transport.webrtc import (ask_socket_buffers, error_body, http_response, parse_description,
                                      read_http_message)

__all__ = ["RtcLinkProxy", "candidate_addresses", "rewrite_candidates"]

log = logging.getLogger("quadcast.rtc_proxy")


def _ipv4(host: str) -> bool:
    try:
        return isinstance(ipaddress.ip_address(host), ipaddress.IPv4Address)
    except ValueError:
        return False


def _candidate_fields(line: str) -> list[str] | None:
    """The fields of an ``a=candidate:`` line (foundation, component, transport, priority, address, port, ...)."""
    if not line.startswith("a=candidate:"):
        return None
    fields = line[len("a=candidate:"):].split()
    if (len(fields) < 8 or fields[6] != "typ" or not (fields[5].isascii() and fields[5].isdigit())
            or not 0 < int(fields[5]) < 65536):
        raise ValueError(f"malformed ICE candidate line {line[:120]!r}")
    return fields


def _relayed_address(fields: list[str]) -> tuple[str, int] | None:
    """The (address, port) of a candidate the link relays (UDP, IPv4), else None."""
    return (fields[4], int(fields[5])) if fields[2].lower() == "udp" and _ipv4(fields[4]) else None


def candidate_addresses(sdp: str) -> list[tuple[str, int]]:
    """The distinct (address, port) of the description's UDP IPv4 candidates, in order."""
    out: dict[tuple[str, int], None] = {}      # ordered, and no quadratic search on a hostile description
    for line in sdp.splitlines():
        fields = _candidate_fields(line)
        if fields is not None and (addr := _relayed_address(fields)) is not None:
            out.setdefault(addr)
    return list(out)


def rewrite_candidates(sdp: str, stand_ins: dict[tuple[str, int], tuple[str, int]]) -> str:
    """``sdp`` with each UDP IPv4 candidate's address and port replaced by its stand-in's; every other candidate
    line is left out (a path the link would not see). Lines end in CRLF, as SDP's do."""
    lines = []
    for line in sdp.splitlines():
        fields = _candidate_fields(line)
        if fields is not None:
            addr = _relayed_address(fields)
            if addr not in stand_ins:
                continue
            fields[4], fields[5] = stand_ins[addr][0], str(stand_ins[addr][1])
            line = "a=candidate:" + " ".join(fields)
        lines.append(line)
    return "\r\n".join(lines) + ("\r\n" if sdp.endswith(("\r", "\n")) else "")


class _Route:
    """Datagrams from one stand-in to one real address: the sink a
    :class:`quadcast.sim.proxy.ShapedDirection` delivers to."""

    def __init__(self, stand_in: "_StandIn", dest: tuple[str, int]) -> None:
        self.stand_in, self.dest = stand_in, dest
        self.in_flight = {"up": 0, "down": 0}

    def write_buffer_size(self, direction: str) -> int:
        return 0

    def deliver(self, direction: str, raw: bytes) -> None:
        self.in_flight[direction] -= 1
        transport = self.stand_in.transport
        if transport is None or transport.is_closing():
            return
        try:
            transport.sendto(raw, self.dest)
        except (OSError, ValueError) as exc:      # never stops the direction's delivery for the other sessions
            log.info("link: datagram to %s not sent: %s", self.dest, exc)
            return
        stats = self.stand_in.session.proxy._directions[direction].stats
        stats.messages_forwarded += 1
        stats.bytes_forwarded += len(raw)


class _StandIn(asyncio.DatagramProtocol):
    """The link's UDP socket standing for one peer's address (``real``) towards the other peer."""

    def __init__(self, session: "_Session", side: str, real: tuple[str, int]) -> None:
        self.session, self.side, self.real = session, side, real
        self.transport: asyncio.DatagramTransport | None = None
        self.address: tuple[str, int] | None = None
        self._routes: dict[tuple[str, int], _Route] = {}

    def connection_made(self, transport) -> None:
        self.transport = transport
        self.address = transport.get_extra_info("sockname")[:2]
        sock = transport.get_extra_info("socket")
        if sock is not None:      # a frame is a burst of hundreds of datagrams: the kernel must not drop them first
            ask_socket_buffers(sock)

    def datagram_received(self, data: bytes, addr) -> None:
        # sent to the stand-in of a `side` address, so it came from the other side: it leaves from the stand-in
        # of its sender's address, towards the real address this socket stands for
        session = self.session
        other = "server" if self.side == "client" else "client"
        sender = session.stand_ins[other].get(tuple(addr[:2]))
        if sender is None:      # e.g. the server's first checks, before its answer came back through the link
            session.proxy.unknown_datagrams += 1
            return
        session.last_datagram = asyncio.get_running_loop().time()
        route = sender._routes.get(self.real)
        if route is None:
            route = sender._routes[self.real] = _Route(sender, self.real)
        shaped = session.proxy._directions["down" if self.side == "client" else "up"]
        shaped.submit(route, data, session.last_datagram)

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()


class _Session:
    """The stand-ins of one signalling exchange."""

    def __init__(self, proxy: "RtcLinkProxy", peer: str) -> None:
        self.proxy, self.peer = proxy, peer
        self.stand_ins: dict[str, dict[tuple[str, int], _StandIn]] = {"client": {}, "server": {}}
        self.last_datagram = asyncio.get_running_loop().time()

    async def stand_in_for(self, side: str, addrs: list[tuple[str, int]]) -> dict[tuple[str, int], tuple[str, int]]:
        """Open a stand-in for each of ``side``'s addresses; their (address, port) by real address."""
        loop = asyncio.get_running_loop()
        out = {}
        for real in addrs:
            _, stand_in = await loop.create_datagram_endpoint(
                lambda real=real: _StandIn(self, side, real), local_addr=(self.proxy.listen_host, 0))
            self.stand_ins[side][real] = stand_in
            out[real] = stand_in.address
        return out

    def close(self) -> None:
        for group in self.stand_ins.values():
            for stand_in in group.values():
                stand_in.close()


class RtcLinkProxy(ShapedProxy):
    """Signalling proxy and UDP relay shaping a WebRTC session's datagrams (see the module docstring).

    ``up`` shapes client -> server, ``down`` server -> client. :attr:`stats` counts datagrams (``messages_*``) per
    direction, signalling requests (``connections_accepted``), sessions with open stand-ins (``connections_open``),
    requests the server could not be asked (``upstream_failures``) and refused requests (``framing_errors``).
    """

    task_name = "rtc-link"

    def __init__(self, listen_host: str, listen_port: int, target_host: str, target_port: int,
                 up: LinkModel, down: LinkModel, *, max_queue_bytes: int = DEFAULT_MAX_QUEUE_BYTES,
                 request_timeout: float = 15.0, idle_timeout: float = 30.0, max_sessions: int = 16,
                 max_candidates: int = 16) -> None:
        super().__init__(listen_host, listen_port, target_host, target_port, up, down, max_queue_bytes)
        if not _ipv4(listen_host):
            raise ValueError(f"RtcLinkProxy: the listen host must be an IPv4 address (the stand-ins bind there), "
                             f"got {listen_host!r}")
        if max_sessions < 1 or max_candidates < 1:
            raise ValueError("RtcLinkProxy: max_sessions and max_candidates must be positive")
        self.request_timeout = float(request_timeout)
        self.idle_timeout = float(idle_timeout)
        self.max_sessions = int(max_sessions)
        self.max_candidates = int(max_candidates)
        self.unknown_datagrams = 0        # from an address no description named: dropped
        self._sessions: set[_Session] = set()
        self._tasks: set[asyncio.Task] = set()

    @property
    def address(self) -> str:
        return super().address + " (webrtc)"

    async def start(self) -> None:
        await super().start()
        self._tasks.update(d.task for d in self._directions.values())
        self._tasks.add(asyncio.create_task(self._close_idle(), name="rtc-link-idle"))

    async def close(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            server.close()
        for session in list(self._sessions):
            self._end(session)
        tasks = list(self._tasks)
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if server is not None:
            await server.wait_closed()

    def _end(self, session: _Session) -> None:
        if session in self._sessions:
            self._sessions.discard(session)
            self.stats.connections_open -= 1
            session.close()

    async def _close_idle(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(min(5.0, self.idle_timeout / 2))
            for session in list(self._sessions):
                if loop.time() - session.last_datagram > self.idle_timeout:
                    log.info("link %s: session of %s idle for %g s; its stand-ins closed", self.address,
                             session.peer, self.idle_timeout)
                    self._end(session)

    def _description(self, body: bytes, kind: str) -> dict:
        desc = parse_description(body, kind)
        addrs = candidate_addresses(desc["sdp"])
        if len(addrs) > self.max_candidates:
            raise ValueError(f"the {kind} names {len(addrs)} candidate addresses (cap {self.max_candidates})")
        return desc

    async def _on_accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        self._tasks.add(task)
        self.stats.connections_accepted += 1
        peer = writer.get_extra_info("peername")
        peer = f"{peer[0]}:{peer[1]}" if isinstance(peer, tuple) else str(peer)
        session: _Session | None = None
        try:
            try:
                start, headers, body = await asyncio.wait_for(read_http_message(reader), self.request_timeout)
                method, path, *_ = start.split(" ") + ["", ""]
                if method != "POST" or path != "/offer":
                    raise ValueError(f"{start[:60]!r}: the link forwards POST /offer only")
                offer = self._description(body, "offer")
            except (ValueError, asyncio.TimeoutError) as exc:
                self.stats.framing_errors += 1
                writer.write(http_response("400 Bad Request", error_body(f"link: {exc}")))
                return
            if len(self._sessions) >= self.max_sessions:
                writer.write(http_response("503 Service Unavailable", error_body(
                    f"link: {self.max_sessions} sessions already"), extra="Retry-After: 5\r\n"))
                return
            session = _Session(self, peer)
            self._sessions.add(session)
            self.stats.connections_open += 1
            offer["sdp"] = rewrite_candidates(offer["sdp"], await session.stand_in_for(
                "client", candidate_addresses(offer["sdp"])))
            status, answer_headers, answer = await self._ask_server(headers, json.dumps(offer).encode())
            if status.split(" ")[1:2] != ["200"]:      # refused (401, 403, 503, ...): passed on as it is
                retry = answer_headers.get("retry-after")
                reason = status.split(" ", 1)[1] if " " in status else "502 Bad Gateway"
                writer.write(http_response(reason, answer,
                                           answer_headers.get("content-type", "application/json"),
                                           f"Retry-After: {retry}\r\n" if retry else ""))
                return
            try:
                desc = self._description(answer, "answer")
            except ValueError as exc:
                raise ConnectionError(f"the server's answer: {exc}") from None
            desc["sdp"] = rewrite_candidates(desc["sdp"], await session.stand_in_for(
                "server", candidate_addresses(desc["sdp"])))
            writer.write(http_response("200 OK", json.dumps(desc).encode()))
            session = None        # kept: its datagrams flow until it idles
        except (OSError, asyncio.TimeoutError, ConnectionError) as exc:
            self.stats.upstream_failures += 1
            log.warning("link %s: signalling for %s failed: %s", self.address, peer, exc or "timed out")
            writer.write(http_response("502 Bad Gateway", error_body(f"link: the server could not be asked: {exc}")))
        finally:
            if session is not None:
                self._end(session)
            try:
                await writer.drain()
            except (ConnectionError, OSError):
                pass
            writer.close()
            self._tasks.discard(task)

    async def _ask_server(self, headers: dict, body: bytes) -> tuple[str, dict, bytes]:
        """POST the rewritten offer to the server with the client's Authorization; its (status line, headers,
        body)."""
        reader, writer = await asyncio.wait_for(
            asyncio.open_connection(self.target_host, self.target_port), self.request_timeout)
        try:
            auth = f"Authorization: {headers['authorization']}\r\n" if "authorization" in headers else ""
            writer.write((f"POST /offer HTTP/1.1\r\nHost: {self.target_host}:{self.target_port}\r\n"
                          f"Content-Type: application/json\r\n{auth}Content-Length: {len(body)}\r\n"
                          f"Connection: close\r\n\r\n").encode() + body)
            await writer.drain()
            try:
                return await asyncio.wait_for(read_http_message(reader), self.request_timeout)
            except ValueError as exc:
                raise ConnectionError(f"malformed answer: {exc}") from None
        finally:
            writer.close()
