"""Tests for sim.proxy: the netem-like message-level TCP proxy, on 127.0.0.1 with ephemeral ports.

Every test runs under an asyncio timeout of a few seconds and cleans up after itself.
"""

import asyncio
import logging
import socket

import pytest

from quadcast.protocol.messages import Bye, Frame, MessageDecoder, PoseUpdate, encode_message
from quadcast.cli import main
from quadcast.sim.link import LinkModel
from quadcast.sim.proxy import LinkProxy, parse_link_args

TIMEOUT = 8.0


def run(coro):
    async def bounded():
        return await asyncio.wait_for(coro, TIMEOUT)
    return asyncio.run(bounded())


class EchoServer:
    """Writes back every byte it reads; records when a connection's EOF was seen."""

    def __init__(self):
        self.eof = asyncio.Event()
        self.connections = 0

    async def start(self):
        self.server = await asyncio.start_server(self._handle, "127.0.0.1", 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def _handle(self, reader, writer):
        self.connections += 1
        try:
            while data := await reader.read(65536):
                writer.write(data)
                await writer.drain()
        except ConnectionError:
            pass
        finally:
            self.eof.set()
            writer.close()

    async def close(self):
        self.server.close()
        await self.server.wait_closed()


async def proxied_echo(up: LinkModel, down: LinkModel, **kw):
    echo = await EchoServer().start()
    proxy = LinkProxy("127.0.0.1", 0, "127.0.0.1", echo.port, up, down, **kw)
    await proxy.start()
    reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
    return echo, proxy, reader, writer


async def teardown(echo, proxy, writer):
    writer.close()
    await proxy.close()
    await echo.close()


async def read_messages(reader, dec, n):
    out = []
    while len(out) < n:
        data = await reader.read(65536)
        assert data, f"connection closed after {len(out)} of {n} messages"
        out += dec.feed(data)
    return out


def pose(i):
    return PoseUpdate(i, i * 0.01, [i, 0.0, -i], [0.0, 0.0, 0.0, 1.0])


def test_messages_arrive_intact_and_in_order():
    async def body():
        echo, proxy, reader, writer = await proxied_echo(LinkModel(), LinkModel())
        msgs = [pose(i) if i % 5 else Frame(bytes([i % 251]) * (1000 * i + 1)) for i in range(60)]
        wire = b"".join(encode_message(m) for m in msgs)
        for i in range(0, len(wire), 777):  # chunking unrelated to message boundaries
            writer.write(wire[i:i + 777])
        await writer.drain()
        got = await read_messages(reader, MessageDecoder(), len(msgs))
        assert got == msgs
        st = proxy.stats
        assert st.up.messages_forwarded == st.down.messages_forwarded == 60
        assert st.up.bytes_forwarded == st.down.bytes_forwarded == len(wire)
        assert st.up.messages_dropped == st.down.messages_dropped == 0
        await teardown(echo, proxy, writer)
    run(body())


def test_round_trip_is_at_least_twice_the_delay():
    async def body():
        echo, proxy, reader, writer = await proxied_echo(LinkModel(delay_ms=30), LinkModel(delay_ms=30))
        loop = asyncio.get_running_loop()
        dec = MessageDecoder()
        for i in range(3):
            t0 = loop.time()
            writer.write(encode_message(pose(i)))
            (m,) = await read_messages(reader, dec, 1)
            assert m == pose(i)
            assert loop.time() - t0 >= 0.060
        await teardown(echo, proxy, writer)
    run(body())


def test_rate_serializes_messages():
    async def body():
        # 8 Mbit/s: a 10 000-byte message takes 10 ms on the wire; 10 back-to-back take >= 100 ms one way
        echo, proxy, reader, writer = await proxied_echo(LinkModel(rate_mbit=8), LinkModel())
        loop = asyncio.get_running_loop()
        msgs = [Frame(bytes([i]) * (10_000 - 5)) for i in range(10)]
        t0 = loop.time()
        writer.write(b"".join(encode_message(m) for m in msgs))
        got = await read_messages(reader, MessageDecoder(), 10)
        assert got == msgs
        assert loop.time() - t0 >= 0.100
        await teardown(echo, proxy, writer)
    run(body())


def test_loss_drops_whole_messages_and_keeps_framing():
    async def body():
        echo, proxy, reader, writer = await proxied_echo(LinkModel(loss=0.5, seed=7), LinkModel())
        n = 200
        writer.write(b"".join(encode_message(pose(i)) for i in range(n)))
        await writer.drain()
        st = proxy.stats
        while st.up.messages_forwarded + st.up.messages_dropped < n:
            await asyncio.sleep(0.01)
        got = await read_messages(reader, MessageDecoder(), st.up.messages_forwarded)
        seqs = [m.seq for m in got]
        assert seqs == sorted(set(seqs))  # in order, no duplicates
        assert all(m == pose(m.seq) for m in got)  # intact
        assert 70 <= len(got) <= 130, len(got)
        assert st.up.dropped_loss == n - len(got) and st.up.dropped_queue == 0
        # the stream still frames correctly after the losses
        writer.write(encode_message(Bye()))
        dec = MessageDecoder()
        rest = []
        while st.up.messages_forwarded + st.up.messages_dropped < n + 1:
            await asyncio.sleep(0.01)
        if st.up.messages_forwarded == len(got) + 1:
            rest = await read_messages(reader, dec, 1)
            assert rest == [Bye()]
        await teardown(echo, proxy, writer)
    run(body())


def test_closing_the_client_closes_the_upstream():
    async def body():
        echo, proxy, reader, writer = await proxied_echo(LinkModel(delay_ms=10), LinkModel(delay_ms=10))
        writer.write(encode_message(pose(1)))
        assert await read_messages(reader, MessageDecoder(), 1) == [pose(1)]
        assert proxy.stats.connections_open == 1
        writer.close()
        await asyncio.wait_for(echo.eof.wait(), 2.0)
        while proxy.stats.connections_open:
            await asyncio.sleep(0.01)
        await proxy.close()
        await echo.close()
    run(body())


def test_messages_in_flight_are_delivered_before_the_close():
    async def body():
        echo, proxy, reader, writer = await proxied_echo(LinkModel(delay_ms=50), LinkModel())
        writer.write(encode_message(pose(1)) + encode_message(Bye()))
        writer.write_eof()  # half-close: the proxy still delivers the two delayed messages first
        dec, got = MessageDecoder(), []
        while data := await reader.read(65536):
            got += dec.feed(data)
        assert got == [pose(1), Bye()]
        await teardown(echo, proxy, writer)
    run(body())


def test_a_target_ignoring_eof_is_closed_after_the_half_close_timeout():
    async def body():
        seen_eof, release = asyncio.Event(), asyncio.Event()

        async def stubborn(reader, writer):  # reads to EOF but never closes its side
            while await reader.read(65536):
                pass
            seen_eof.set()
            await release.wait()
            writer.close()

        server = await asyncio.start_server(stubborn, "127.0.0.1", 0)
        proxy = LinkProxy("127.0.0.1", 0, "127.0.0.1", server.sockets[0].getsockname()[1],
                          LinkModel(), LinkModel(), half_close_timeout=0.2)
        await proxy.start()
        reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
        writer.write(encode_message(Bye()))
        writer.write_eof()
        await asyncio.wait_for(seen_eof.wait(), 2.0)
        assert proxy.stats.connections_open == 1
        assert await asyncio.wait_for(reader.read(100), 2.0) == b""  # closed by the linger timer
        assert proxy.stats.connections_open == 0
        writer.close()
        await proxy.close()
        release.set()
        server.close()
        await server.wait_closed()
    run(body())


def test_invalid_framing_closes_the_connection(caplog):
    async def body():
        echo, proxy, reader, writer = await proxied_echo(LinkModel(), LinkModel(), max_message_bytes=1024)
        writer.write(encode_message(pose(1)))
        assert await read_messages(reader, MessageDecoder(), 1) == [pose(1)]
        writer.write(b"\xff\xff\xff\x7f" + b"garbage")
        assert await reader.read(65536) == b""  # closed by the proxy
        await asyncio.wait_for(echo.eof.wait(), 2.0)
        assert proxy.stats.framing_errors == 1
        await teardown(echo, proxy, writer)
    with caplog.at_level(logging.WARNING, logger="quadcast.proxy"):
        run(body())
    assert any("invalid framing" in r.getMessage() for r in caplog.records)


def test_queue_overflow_drops_messages_as_losses():
    async def body():
        # 1 Mbit/s, 5000-byte messages (40 ms each), 12 000-byte queue: a burst of 20 mostly overflows
        echo, proxy, reader, writer = await proxied_echo(LinkModel(rate_mbit=1), LinkModel(),
                                                          max_queue_bytes=12_000)
        msgs = [Frame(bytes([i]) * (5000 - 5)) for i in range(20)]
        writer.write(b"".join(encode_message(m) for m in msgs))
        st = proxy.stats
        while st.up.messages_in < 20:
            await asyncio.sleep(0.01)
        assert 2 <= st.up.messages_forwarded + proxy.up.pending() <= 8
        assert st.up.dropped_queue >= 12
        assert st.up.dropped_queue == st.up.messages_dropped == 20 - (st.up.messages_forwarded + proxy.up.pending())
        assert st.up.dropped_loss == 0
        got = await read_messages(reader, MessageDecoder(), 20 - st.up.dropped_queue)
        assert got == msgs[:len(got)]  # drop-tail: the first ones of the burst get through
        await teardown(echo, proxy, writer)
    run(body())


def test_a_tcp_link_stops_reading_the_sender_instead_of_dropping():
    async def body():
        # the same burst through a TCP model at 10% segment loss: nothing is lost, and the proxy stops reading the
        # sender while a window's worth waits to leave (a TCP sender's socket buffer), so it never holds the burst
        up = LinkModel(delay_ms=2, rate_mbit=1, loss=0.1, seed=3, reliable=True)
        echo, proxy, reader, writer = await proxied_echo(up, LinkModel())
        msgs = [Frame(bytes([i]) * (5000 - 5)) for i in range(20)]
        writer.write(b"".join(encode_message(m) for m in msgs))
        await asyncio.sleep(0.1)
        assert proxy.stats.up.messages_in < 20
        got = await read_messages(reader, MessageDecoder(), 20)
        assert got == msgs
        st = proxy.stats.up
        assert st.messages_dropped == st.dropped_queue == st.dropped_loss == 0
        assert up.stats.segments_lost > 0 and up.stats.dropped == 0
        await teardown(echo, proxy, writer)
    run(body())


def test_unreachable_target_closes_the_client(caplog):
    async def body():
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            dead_port = s.getsockname()[1]
        proxy = LinkProxy("127.0.0.1", 0, "127.0.0.1", dead_port, LinkModel(), LinkModel())
        async with proxy:
            reader, writer = await asyncio.open_connection("127.0.0.1", proxy.port)
            assert await reader.read(100) == b""
            assert proxy.stats.upstream_failures == 1
            writer.close()
    run(body())


def test_parse_link_args():
    link = parse_link_args("20ms", "2ms", "50mbit", "0.5%", seed=3)
    assert (link.delay_ms, link.jitter_ms, link.rate_mbit, link.loss, link.seed) == (20.0, 2.0, 50.0, 0.005, 3)
    assert parse_link_args("0.1s", 0, None, 0).rate_mbit is None
    assert parse_link_args(rate="").rate_mbit is None
    with pytest.raises(ValueError, match="rate"):
        parse_link_args(rate="fast")
    with pytest.raises(ValueError, match="loss"):
        parse_link_args(loss="50")


def test_proxy_rejects_shared_models():
    link = LinkModel()
    with pytest.raises(ValueError, match="different"):
        LinkProxy("127.0.0.1", 0, "127.0.0.1", 1, link, link)


def test_a_rate_trace_shapes_the_downlink_from_the_proxy_start(tmp_path):
    from quadcast.cli.live import link_models
    from quadcast.sim.ratetrace import trace_from_schedule
    path = tmp_path / "8mbit.mahi"
    path.write_text(trace_from_schedule([(0.1, 8.0)], "8mbit").to_text())
    up, down = link_models("0ms", "0ms", "50mbit", "0%", 1, rate_trace=str(path))
    assert up.rate_mbit == 50 and up.rate_trace is None
    assert down.rate_mbit is None and down.rate_trace is not None and down.rate_trace.mean_mbit == pytest.approx(8, rel=0.01)

    async def body():
        # the echo's answer crosses the traced downlink: 10 messages of 10,000 bytes take >= 100 ms at 8 Mbit/s
        echo, proxy, reader, writer = await proxied_echo(LinkModel(), down)
        loop = asyncio.get_running_loop()
        assert down.trace_start == pytest.approx(loop.time(), abs=1.0)
        msgs = [Frame(bytes([i]) * (10_000 - 5)) for i in range(10)]
        t0 = loop.time()
        writer.write(b"".join(encode_message(m) for m in msgs))
        got = await read_messages(reader, MessageDecoder(), 10)
        assert got == msgs
        assert loop.time() - t0 >= 0.095
        await teardown(echo, proxy, writer)
    run(body())


def test_the_link_command_builds_tcp_models_and_refuses_drop_messages_with_webrtc(capsys):
    from quadcast.cli.live import link_models
    up, down = link_models("20ms", "0ms", None, "1%", 0, reliable=True)
    assert up.reliable and down.reliable and down.rtt_ms == 40.0
    assert main(["link", "--listen", "0", "--to", "127.0.0.1:9", "--webrtc", "--drop-messages"]) == 2
    assert "--drop-messages is for the TCP link" in capsys.readouterr().err
