"""What the WebRTC tests share: QUASAR frames to send and to receive, and a raw HTTP request to a signalling
endpoint."""
from __future__ import annotations

import asyncio


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
