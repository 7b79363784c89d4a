"""TcpChannel: what it can tell of its own unsent bytes, and waiting for them to go (the server's next frame)."""
from __future__ import annotations

import asyncio
import socket
import sys

import pytest

from quadcast.protocol.messages import Frame
from quadcast.transport.channel import open_tcp_channel

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the kernel's unsent bytes: Linux only")


def test_wait_sent_holds_the_sender_until_a_stalled_peer_reads():
    async def body():
        accepted: asyncio.Queue = asyncio.Queue()

        async def on_accept(reader, writer):
            writer.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 * 1024)
            await accepted.put((reader, writer))

        server = await asyncio.start_server(on_accept, "127.0.0.1", 0, limit=4096)
        port = server.sockets[0].getsockname()[1]
        channel = await open_tcp_channel("127.0.0.1", port, 1 << 16)
        reader, writer = await accepted.get()
        assert channel.unsent_bytes() == 0
        await asyncio.wait_for(channel.wait_sent(0), 1.0)      # nothing waits: at once

        frame = Frame(b"x" * 4_000_000)                          # far more than the peer's buffers take
        send = asyncio.create_task(channel.send(frame))
        await asyncio.sleep(0.2)
        assert channel.unsent_bytes() > 1_000_000
        waiting = asyncio.create_task(channel.wait_sent(16 * 1024))
        await asyncio.sleep(0.2)
        assert not waiting.done()                                # the peer reads nothing: the sender waits

        got = 0
        while got < 4_000_000:                                   # the peer reads it all: the wait ends
            got += len(await reader.read(1 << 20))
        await asyncio.wait_for(asyncio.gather(send, waiting), 5.0)
        assert channel.unsent_bytes() <= 16 * 1024
        await channel.close()
        writer.close()
        server.close()
        await server.wait_closed()
    asyncio.run(asyncio.wait_for(body(), 20.0))
