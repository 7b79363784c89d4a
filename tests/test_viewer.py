"""The server's browser side without a browser: the viewer's HTTP routes on the server's own port, and a session
over the WebSocket speaking the same wire messages as TCP, driven by the same session core (an in-process
LiveServer with a thread worker, 64x48 frames)."""
from __future__ import annotations

import asyncio
import json

import numpy as np
import pytest
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosedError, InvalidStatus

from quadcast.methods import make_server
from quadcast.protocol.frame import FrameType, decode_frame_payload
from quadcast.protocol.messages import (PROTOCOL_VERSION, ErrorCode, ErrorMessage, Frame, Hello, MessageDecoder,
                                        PoseUpdate, Welcome, encode_message)
from quadcast.protocol.quads import decode_quad_frame
from quadcast.render.traces import resolve_trace
from quadcast.server.app import LiveServer, ServerConfig
from quadcast.server.web import VIEWER_DIR, static_file, starts_http
from quadcast.transport.channel import open_tcp_channel

W, H = 64, 48


def run(coro):
    return asyncio.run(asyncio.wait_for(coro, 120))


async def started(**overrides) -> LiveServer:
    cfg = ServerConfig(port=0, worker="thread", spare_workers=0, **overrides)
    server = LiveServer(cfg, make_server)
    await server.start()
    return server


async def http(port: int, request: bytes) -> tuple[int, dict, bytes]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(request)
    await writer.drain()
    data = await reader.read()          # the server closes after one response
    writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    lines = head.decode().split("\r\n")
    headers = dict(line.split(": ", 1) for line in lines[1:])
    return int(lines[0].split()[1]), headers, body


def get(path: str) -> bytes:
    return f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n".encode()


def test_first_bytes_tell_http_from_the_binary_protocol():
    assert starts_http(b"GET /") and starts_http(b"POST") and not starts_http(b"GE")
    hello = encode_message(Hello(PROTOCOL_VERSION, "quasar", W, H, 60.0))
    assert not starts_http(hello[:4])
    assert int.from_bytes(b"GET ", "little") > ServerConfig().max_message_bytes   # never a valid length


def test_viewer_routes_serve_the_page_its_data_and_nothing_else():
    async def main():
        server = await started(token="t0k")
        try:
            port = server.port
            status, headers, body = await http(port, get("/"))
            assert status == 200 and headers["Content-Type"].startswith("text/html")
            assert b'src="/js/main.js"' in body and headers["Cache-Control"] == "no-store"
            status, headers, body = await http(port, get("/js/main.js"))
            assert status == 200 and headers["Content-Type"].startswith("text/javascript")
            # the expansion shader is served with render/quad.glsl (and camera.glsl) included, not referenced
            status, _, body = await http(port, get("/shaders/quad_expand.vert.glsl"))
            text = body.decode()
            assert status == 200 and text.startswith("#version 300 es") and "\n#include" not in text
            assert "float ray_plane_t(" in text and "vec3 view_ray(" in text
            status, _, body = await http(port, get("/node_modules/fzstd/esm/index.mjs"))
            assert status == 200 and b"export" in body
            status, _, body = await http(port, get("/config.json"))
            config = json.loads(body)
            assert status == 200 and config["methods"] == ["quasar"] and config["token_required"] is True
            assert "t0k" not in body.decode() and config["max_size"] == [1920, 1080] and len(config["start"]["quat"]) == 4
            status, _, body = await http(port, get("/trace/builtin:walk"))
            trace, walk = json.loads(body), resolve_trace("builtin:walk")
            assert status == 200 and np.allclose(trace["positions"], walk.positions) and np.allclose(trace["quats"], walk.quats)
            for path in ("/trace/%2Fetc%2Fpasswd", "/trace/builtin:nope", "/../pyproject.toml", "/%2e%2e/web.py",
                         "/js/../../web.py", "/node_modules/fzstd/package.json", "/.hidden", "/app.py", "/nothing.js"):
                status, _, body = await http(port, get(path))
                assert status == 404, (path, status, body)
            status, _, _ = await http(port, b"POST /config.json HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\n\r\n")
            assert status == 405
            status, _, _ = await http(port, b"GET / HTTP/1.1\r\n" + b"X: y\r\n" * 300 + b"\r\n")
            assert status == 431                                   # websockets' header cap
        finally:
            await server.close()
    run(main())


def test_static_files_resolve_only_inside_the_viewer_folder():
    assert static_file("/")[1].startswith("text/html")
    assert static_file("/js/wire.js") is not None and static_file("/package.json") is None
    assert static_file("/js/%2e%2e/index.html") is None
    assert all(p.is_relative_to(VIEWER_DIR) for p in VIEWER_DIR.rglob("*.js") if "node_modules" not in p.parts)


def test_a_websocket_session_is_a_session_like_any_other():
    """Hello -> Welcome, poses -> frames the Python client can decode, over /ws; a binary TCP client on the same
    port still works; a wrong token gets the same ErrorMessage as over TCP."""
    async def main():
        server = await started(token="t0k")
        try:
            url = f"ws://127.0.0.1:{server.port}/ws"
            async with connect(url, max_size=None) as ws:
                await ws.send(encode_message(Hello(PROTOCOL_VERSION, "quasar", W, H, 60.0, "t0k")))
                dec = MessageDecoder()
                assert dec.feed(await ws.recv()) == [Welcome(1, 30.0)]
                frames = []
                for seq in range(40):
                    await ws.send(encode_message(PoseUpdate(seq, seq / 30, [0.0, 1.6, 6.0 - seq * 0.01],
                                                            [0.0, 0.0, 0.0, 1.0])))
                    try:
                        while True:
                            msg = await asyncio.wait_for(ws.recv(), 0.05)
                            [m] = dec.feed(msg)                 # one wire message per WebSocket message
                            frames.append(m)
                    except asyncio.TimeoutError:
                        pass
                    if len(frames) >= 3:
                        break
                deadline = asyncio.get_running_loop().time() + 60
                while len(frames) < 3 and asyncio.get_running_loop().time() < deadline:
                    frames.extend(dec.feed(await asyncio.wait_for(ws.recv(), 60)))
                assert len(frames) >= 3 and all(isinstance(f, Frame) for f in frames)
                payloads = [decode_frame_payload(f.payload) for f in frames]
                assert payloads[0].frame_type == FrameType.REFERENCE and payloads[0].self_contained
                assert [p.frame_id for p in payloads] == list(range(len(payloads)))
                assert decode_quad_frame(payloads[0].geometry).quad_count > 0

            channel = await open_tcp_channel("127.0.0.1", server.port, 1 << 26)
            await channel.send(Hello(PROTOCOL_VERSION, "quasar", W, H, 60.0, "t0k"))
            assert isinstance(await asyncio.wait_for(channel.recv(), 60), Welcome)
            await channel.close()

            async with connect(url) as ws:
                await ws.send(encode_message(Hello(PROTOCOL_VERSION, "quasar", W, H, 60.0, "wrong")))
                [err] = MessageDecoder().feed(await ws.recv())
                assert isinstance(err, ErrorMessage) and err.code == ErrorCode.UNAUTHORIZED
        finally:
            await server.close()
    run(main())


def test_websocket_rejects_other_origins_text_and_oversized_messages():
    async def main():
        server = await started()
        try:
            url = f"ws://127.0.0.1:{server.port}/ws"
            with pytest.raises(InvalidStatus) as info:
                async with connect(url, origin="http://evil.example"):
                    pass
            assert info.value.response.status_code == 403
            async with connect(url, origin=f"http://127.0.0.1:{server.port}") as ws:
                await ws.send("hello")                       # the protocol is binary
                [err] = MessageDecoder().feed(await ws.recv())
                assert isinstance(err, ErrorMessage) and err.code == ErrorCode.PROTOCOL and "text" in err.text
            async with connect(url) as ws:                  # a length prefix over the 64 KiB cap on client messages
                await ws.send((1 << 20).to_bytes(4, "little") + b"\x01")
                [err] = MessageDecoder().feed(await ws.recv())
                assert isinstance(err, ErrorMessage) and err.code == ErrorCode.PROTOCOL and "cap" in err.text
            async with connect(url) as ws:                  # a WebSocket frame over it: closed at once (1009)
                await ws.send(bytes(200_000))
                with pytest.raises(ConnectionClosedError) as closed:
                    await ws.recv()
                assert closed.value.rcvd.code == 1009
            status, _, _ = await http(server.port, get("/ws"))   # no upgrade headers
            assert status in (400, 426)
        finally:
            await server.close()
    run(main())


@pytest.mark.parametrize("stage", ["quad_expand", "quad_mesh", "quad_mesh_refresh"])
def test_served_shaders_compile_as_glsl_es(ctx, stage):
    """The viewer's shaders as the server serves them (the Python client's shared bodies included) compile as
    GLSL ES 3.00 -- Mesa's desktop GL takes ES 3.00 shaders too -- and the mesh's keep the uniforms renderer.js
    sets."""
    vertex, _ = static_file(f"/shaders/{stage}.vert.glsl")
    fragment, _ = static_file(f"/shaders/{stage}.frag.glsl")
    assert vertex.startswith(b"#version 300 es") and fragment.startswith(b"#version 300 es")
    prog = ctx.program(vertex_shader=vertex.decode(), fragment_shader=fragment.decode())
    mesh = ("u_proj", "u_layer_to_view", "u_depth_scale", "u_max_depth", "u_atlas", "u_uv_rect")
    expected = {"quad_expand": (), "quad_mesh": mesh,
                "quad_mesh_refresh": (*mesh, "u_layer_to_current", "u_current_rect", "u_current_uv_rect")}
    for name in expected[stage]:
        assert prog.get(name, None) is not None, name
