"""What the WebRTC tests share: QUASAR frames to send and to receive, a raw HTTP request to a signalling endpoint, a
server's session and a client connected to it, and the check that frames arrived as sent."""
from __future__ import annotations

import asyncio
import contextlib


def quasar_payloads(n: int, width: int = 160, height: int = 90):
    """n QUASAR frames of builtin:walk (a reference, then residuals; a reference every 10)."""
    from quadcast.methods import make_server
    from quadcast.protocol.methods import MethodConfig
    from quadcast.render.camera import Pose
    from quadcast.render.renderer import DeferredRenderer
    from quadcast.render.scene import load_scene
    from quadcast.render.traces import resolve_trace
    trace = resolve_trace("builtin:walk")
    server = make_server("quasar", DeferredRenderer(load_scene("builtin:courtyard")),
                         MethodConfig(width=width, height=height, reference_every=10))
    out = []
    for i in range(n):
        p, q = trace.pose_at(trace.times[0] + i / 30)
        out.append(server.encode(Pose(p, q), i / 30))
    server.close()
    return out


async def http_request(port: int, raw: bytes) -> bytes:
    """Send ``raw`` to 127.0.0.1:``port`` and read the whole answer."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(raw)
    await writer.drain()
    data = await asyncio.wait_for(reader.read(), 10)
    writer.close()
    return data


async def post_offer_body(port: int, body: bytes) -> bytes:
    """``POST /offer`` with ``body`` as it is (JSON or not) to 127.0.0.1:``port``, and the whole answer."""
    return await http_request(port, b"POST /offer HTTP/1.1\r\nContent-Length: %d\r\n\r\n%s" % (len(body), body))


async def receive_frames(channel, n: int, timeout: float = 20.0) -> list:
    """The next ``n`` messages of ``channel``, each a Frame, decoded (FramePayload)."""
    from quadcast.protocol.frame import decode_frame_payload
    from quadcast.protocol.messages import Frame
    frames = []
    while len(frames) < n:
        msg = await asyncio.wait_for(channel.recv(), timeout)
        assert isinstance(msg, Frame), msg
        frames.append(decode_frame_payload(msg.payload))
    return frames


def serving(frames=(), on_channel=None):
    """A server's session for a WebRtcListener: ``on_channel(channel)`` first (to look at the server's side), then
    Welcome to the client's Hello, ``frames`` sent, and every later message read until the client goes."""
    from quadcast.protocol.messages import Welcome

    async def serve(channel):
        if on_channel is not None:
            on_channel(channel)
        await channel.recv()
        await channel.send(Welcome(1, 30.0))
        for payload in frames:
            await channel.send_frame(payload)
        while await channel.recv() is not None:
            pass
    return serve


@contextlib.asynccontextmanager
async def client_of(serve, width: int = 160, height: int = 90):
    """A WebRtcListener running ``serve`` on a free port, and a client's channel to it past Hello and Welcome."""
    from quadcast.protocol.messages import PROTOCOL_VERSION, Bye, Hello
    from quadcast.transport.webrtc import WebRtcListener, open_webrtc_channel
    listener = WebRtcListener("127.0.0.1", 0, serve)
    await listener.start()
    try:
        channel = await open_webrtc_channel("127.0.0.1", listener.port, 1 << 24, timeout=20)
        try:
            await channel.send(Hello(PROTOCOL_VERSION, "quasar", width, height, 60.0))
            await asyncio.wait_for(channel.recv(), 20)
            yield channel
            await channel.send(Bye())
        finally:
            await channel.close()
    finally:
        await listener.close()


def assert_same_frames(sent, received) -> None:
    """``received`` (FramePayloads) are ``sent``: the same frames, quads byte for byte, pictures that decode in one
    stream to what the sent access units decode to."""
    import numpy as np

    from quadcast.codec.decoder import AtlasDecoder
    assert [f.frame_id for f in received] == [p.frame_id for p in sent]
    direct, one_stream = AtlasDecoder(), AtlasDecoder()
    for original, got in zip(sent, received):
        assert got.geometry == original.geometry
        np.testing.assert_array_equal(one_stream.decode(got.video, got.frame_id),
                                      direct.decode(original.video, original.frame_id))
