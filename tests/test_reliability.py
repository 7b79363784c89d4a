"""Issue 13: the live server under hostile and careless clients, in-process on loopback.

Each test runs a real :class:`LiveServer` (its admission, TLS, sessions and session core) whose sessions' workers
are instant fakes (no GL): a frame is a tiny ATW payload for the decided pose, made after the pose passed the
renderer's own check (:class:`quadcast.render.camera.Pose`). Clients are raw protocol clients or the real
:class:`LiveClient`'s connection logic.
"""
from __future__ import annotations

import asyncio
import contextlib
import os
import ssl
import struct

import numpy as np
import pytest

from quadcast.protocol.frame import FramePayload, FrameType, Method, encode_frame_payload
from quadcast.protocol.messages import (PROTOCOL_VERSION, ErrorCode, ErrorMessage, Frame, Hello, MessageDecoder,
                                        PoseUpdate, ReferenceRequest, Welcome, encode_message)
from quadcast.protocol.pose import MAX_POSITION_M
from quadcast.render.camera import Pose
from quadcast.server.app import LiveServer, ServerConfig
from quadcast.transport.channel import open_tcp_channel
from quadcast.transport.tls import client_context

TIMEOUT = 30.0


class _InstantWorker:
    """A session worker without GL: checks the pose as the renderer would, returns a tiny self-contained frame."""

    kind, pid, death = "fake", 0, None

    def __init__(self) -> None:
        self.died = asyncio.Event()
        self.frame_id = 0

    async def start(self, timeout: float) -> int:
        return 0

    async def encode(self, decision):
        pose = Pose(decision.position, decision.quat)    # raises for what a renderer cannot use
        self.frame_id += 1
        payload = FramePayload(Method.ATW, self.frame_id, FrameType.REFERENCE, 0, decision.display_t, pose.position,
                               pose.quat, b"\x00\x00\x00\x01", b"", True)
        return encode_frame_payload(payload), True

    async def close(self) -> None:
        pass


class _Server(LiveServer):
    def make_worker(self, name, spec):
        return _InstantWorker()


def _config(**kw) -> ServerConfig:
    return ServerConfig(**{"worker": "thread", "spare_workers": 0, "max_frame_hz": 1000.0, **kw})


@contextlib.asynccontextmanager
async def _serving(**kw):
    server = _Server(_config(**kw), make_server=None)
    await server.start()
    try:
        yield server
    finally:
        await server.close()


def _hello(token: str = "") -> Hello:
    return Hello(PROTOCOL_VERSION, "quasar", 320, 180, 60.0, token)


async def _raw(port: int, src: str | None = None):
    """A plain TCP connection to the server (from source address ``src``)."""
    return await asyncio.wait_for(asyncio.open_connection(
        "127.0.0.1", port, local_addr=(src, 0) if src else None), TIMEOUT)


async def _read_messages(reader, until=lambda m: False, timeout: float = TIMEOUT) -> list:
    """Messages from ``reader`` until EOF, or until ``until(message)``."""
    dec, out = MessageDecoder(), []
    try:
        async with asyncio.timeout(timeout):
            while True:
                data = await reader.read(65536)
                if not data:
                    return out
                for m in dec.feed(data):
                    out.append(m)
                    if until(m):
                        return out
    except (ConnectionError, TimeoutError):
        return out


# ---------------------------------------------------------------------------------------------- item 2

def _extreme_poses(t0: float = 1.0):
    """Poses at the edges of what the wire format accepts, sent as a hostile client would (tiny and huge time
    steps, jumps across the whole position range, quaternions of extreme norms)."""
    m = MAX_POSITION_M
    t, seq = t0, 0
    for position, quat, dt in [
        ([0, 1.6, 0], [0, 0, 0, 1], 0.0),
        ([m, m, m], [1e3, 0, 0, 0], 1e-3),                # the far corner, a quaternion of norm 1e3
        ([-m, -m, -m], [0, 1e-3, 0, 0], 1e-3),            # across the range in 1 ms (2e8 m/s)
        ([m, -m, m], [0.5, 0.5, 0.5, 0.5], 1e-9),         # too close in time: ignored
        ([0, 0, 0], [0, 0, 0, 1], 1e9),                   # a huge time step
        ([m, 0, 0], [0, 0, 1, 0], 1e-3),
        ([-m, 0, 0], [1, 0, 0, 0], 1e-3),
        ([0, 0, 0], [0, 0, 0, 1], -5.0),                  # back in time: ignored
        ([0, 0, m], [700, -700, 1, 0.001], 1e-3),
    ]:
        t += dt
        yield PoseUpdate(seq, t, position, quat)
        seq += 1


def test_extreme_but_valid_poses_never_end_a_session_and_absurd_ones_are_refused_at_decoding():
    async def main():
        async with _serving() as server:
            reader, writer = await _raw(server.port)
            writer.write(encode_message(_hello()))
            assert isinstance((await _read_messages(reader, lambda m: True))[0], Welcome)
            frames = []
            for pose in _extreme_poses():
                writer.write(encode_message(pose))
                await writer.drain()
                await asyncio.sleep(0.02)
            writer.write(encode_message(PoseUpdate(99, 1e9 + 10, [0, 1.6, 0], [0, 0, 0, 1])))
            got = await _read_messages(reader, lambda m: isinstance(m, Frame) and m.decode().t > 1e9 + 9)
            frames = [m.decode() for m in got if isinstance(m, Frame)]
            errors = [m for m in got if isinstance(m, ErrorMessage)]
            # then an absurd pose (the issue's): refused where it is decoded, naming the field
            body = struct.pack("<Qd3d4d", 100, 1e9 + 11, 0, 1.6, 0, 1e200, 1e200, 0, 1)
            writer.write(struct.pack("<IB", 1 + len(body), 3) + body)
            rest = await _read_messages(reader)
            writer.close()
            return frames, errors, rest, server.totals
    frames, errors, rest, totals = asyncio.run(main())
    assert not errors, errors
    assert len(frames) >= 3
    for f in frames:   # every rendered pose is finite, near the accepted range and a rotation
        assert np.all(np.isfinite(f.position)) and np.abs(f.position).max() <= MAX_POSITION_M + 1e3
        assert np.linalg.norm(f.quat) == pytest.approx(1.0)
    final = [m for m in rest if isinstance(m, ErrorMessage)]
    assert len(final) == 1 and final[0].code == ErrorCode.PROTOCOL
    assert "PoseUpdate.quat: expected a quaternion of norm <= 1000" in final[0].text


def test_core_decisions_stay_renderable_whatever_the_accepted_poses():
    """The session core, fed random poses from the whole accepted range (and random times), only ever decides
    poses the renderer and the wire format accept."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from quadcast.protocol.frame import decode_frame_payload
    from quadcast.protocol.session import ServerSession, ServerSessionConfig
    coord = st.floats(-MAX_POSITION_M, MAX_POSITION_M)
    quat = st.lists(st.floats(-1e3 / 2, 1e3 / 2), min_size=4, max_size=4)
    pose = st.tuples(st.floats(-1e10, 1e10), st.lists(coord, min_size=3, max_size=3), quat)

    @settings(max_examples=150, deadline=None)
    @given(poses=st.lists(pose, min_size=1, max_size=12), unclamped=st.booleans())
    def run(poses, unclamped):
        from quadcast.protocol.prediction import UNCLAMPED_ACCELERATION
        core = ServerSession(ServerSessionConfig(predictor=UNCLAMPED_ACCELERATION if unclamped else None))
        now = 0.0
        for t, p, q in poses:
            try:
                msg = PoseUpdate(0, t, p, q)           # what the decoder would accept
            except ValueError:
                continue
            now += 0.01
            decision = core.pose_received(now, msg.t_client, msg.position, msg.quat)
            if decision is None:
                continue
            pose_ = Pose(decision.position, decision.quat)
            frame = FramePayload(Method.ATW, 1, FrameType.REFERENCE, 0, decision.display_t, pose_.position,
                                 pose_.quat, b"", b"", True)
            decode_frame_payload(encode_frame_payload(frame))   # the client accepts the frame's pose
            core.frame_encoded(now, object(), True, 0.001)
    run()


# ---------------------------------------------------------------------------------------------- item 3

async def _capturing_relay(target_port: int, captured: bytearray):
    """A TCP relay to ``target_port`` that keeps every byte it forwards, both ways."""
    async def pipe(reader, writer):
        try:
            while data := await reader.read(65536):
                captured.extend(data)
                writer.write(data)
                await writer.drain()
        except (ConnectionError, OSError):
            pass
        finally:
            writer.close()

    async def on_client(reader, writer):
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", target_port)
        await asyncio.gather(pipe(reader, up_writer), pipe(up_reader, writer))

    return await asyncio.start_server(on_client, "127.0.0.1", 0)


def test_token_crosses_the_wire_encrypted_with_tls(tls_files):
    cert, key = tls_files
    token = "tok-SECRET-4f9a2c"

    async def session(port: int, ctx) -> tuple[object, bytes]:
        captured = bytearray()
        relay = await _capturing_relay(port, captured)
        try:
            channel = await open_tcp_channel("127.0.0.1", relay.sockets[0].getsockname()[1], 1 << 20, TIMEOUT,
                                             ssl=ctx)
            await channel.send(_hello(token))
            answer = await asyncio.wait_for(channel.recv(), TIMEOUT)
            await channel.close()
        finally:
            relay.close()
        return answer, bytes(captured)

    async def main():
        async with _serving(token=token, tls_cert=str(cert), tls_key=str(key)) as server:
            encrypted = await session(server.port, client_context(ca=cert))
            with pytest.raises(ssl.SSLCertVerificationError):     # the system CAs do not know a self-signed cert
                await open_tcp_channel("127.0.0.1", server.port, 1 << 20, TIMEOUT, ssl=client_context())
            insecure = await session(server.port, client_context(insecure=True))
            # a client speaking plaintext to the TLS port gets nowhere (and no session)
            reader, writer = await _raw(server.port)
            writer.write(encode_message(_hello(token)))
            plain_answer = await _read_messages(reader)
            writer.close()
        async with _serving(token=token) as server:            # the same without TLS, for contrast
            clear = await session(server.port, None)
        return encrypted, insecure, plain_answer, clear

    (answer, wire), (answer2, _), plain_answer, (clear_answer, clear_wire) = asyncio.run(main())
    assert isinstance(answer, Welcome) and isinstance(answer2, Welcome)
    assert token.encode() not in wire and b"quasar" not in wire and len(wire) > 500
    assert not any(isinstance(m, Welcome) for m in plain_answer)
    assert isinstance(clear_answer, Welcome) and token.encode() in clear_wire


def test_public_bind_with_token_needs_tls_or_explicit_consent(tls_files):
    cert, key = tls_files
    with pytest.raises(ValueError, match="--allow-plaintext-token"):
        ServerConfig(host="0.0.0.0", token="t")
    ServerConfig(host="0.0.0.0", token="t", tls_cert=str(cert), tls_key=str(key))
    ServerConfig(host="0.0.0.0", token="t", allow_plaintext_token=True)
    with pytest.raises(ValueError, match="--tls-cert .*nope"):
        ServerConfig(tls_cert="/nope/cert.pem").ssl_context()


# ---------------------------------------------------------------------------------------------- item 4

def test_offer_needs_the_token_peer_connections_are_capped_and_use_no_stun():
    from aiortc import RTCPeerConnection

    from quadcast.transport.webrtc import SignallingPolicy, WebRtcListener, _post_offer, ice_configuration

    async def served(channel):
        await asyncio.sleep(60)

    async def offer() -> dict:
        pc = RTCPeerConnection(ice_configuration())
        pc.createDataChannel("control")
        pc.addTransceiver("video", direction="recvonly")
        await pc.setLocalDescription(await pc.createOffer())
        desc = {"sdp": pc.localDescription.sdp, "type": "offer"}
        await pc.close()
        return desc

    async def post(port: int, token: str = "", headers: str = "") -> bytes:
        import json
        body = json.dumps(await offer()).encode()
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        auth = f"Authorization: Bearer {token}\r\n" if token else ""
        writer.write(f"POST /offer HTTP/1.1\r\n{auth}{headers}Content-Length: {len(body)}\r\n\r\n".encode() + body)
        data = await asyncio.wait_for(reader.read(), TIMEOUT)
        writer.close()
        return data

    async def main():
        listener = WebRtcListener("127.0.0.1", 0, served, policy=SignallingPolicy(token="s3cret",
                                                                                  max_peer_connections=1))
        await listener.start()
        try:
            port = listener.port
            missing = await post(port)
            wrong = await post(port, "guess")
            other_scheme = await post(port, headers="Authorization: Basic czNjcmV0\r\n")
            assert not listener._pcs                               # nothing was created for them
            ok = await post(port, "s3cret")
            configs = [pc._RTCPeerConnection__configuration for pc in listener._pcs]   # aiortc has no getter
            full = await post(port, "s3cret")                      # one peer connection is the cap
            with pytest.raises(PermissionError, match="401"):
                await _post_offer("127.0.0.1", port, await offer(), TIMEOUT)
            return missing, wrong, other_scheme, ok, configs, full
        finally:
            await listener.close()

    missing, wrong, other_scheme, ok, configs, full = asyncio.run(asyncio.wait_for(main(), 60))
    assert missing.startswith(b"HTTP/1.1 401") and b"WWW-Authenticate: Bearer" in missing
    assert other_scheme.startswith(b"HTTP/1.1 401")
    assert wrong.startswith(b"HTTP/1.1 403")
    assert ok.startswith(b"HTTP/1.1 200") and b'"answer"' in ok
    assert len(configs) == 1 and configs[0].iceServers == []     # no STUN server unless --stun
    assert full.startswith(b"HTTP/1.1 503") and b"Retry-After: 5" in full
    assert ice_configuration("stun:stun.example.org:3478").iceServers[0].urls == "stun:stun.example.org:3478"
    with pytest.raises(ValueError, match="--stun"):
        ice_configuration("http://example.org")


# ---------------------------------------------------------------------------------------------- item 5

def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def test_preauth_connections_are_capped_per_address_and_in_total_and_time_out():
    n = 300

    async def main():
        async with _serving(max_preauth=20, max_per_ip=10, handshake_timeout=1.5) as server:
            before = _open_fds()
            flood = [await _raw(server.port, "127.0.0.2") for _ in range(n)]       # one address, silent
            await asyncio.sleep(0.3)
            held_one_ip = server.admission.preauth
            spread = [await _raw(server.port, f"127.0.1.{i}") for i in range(1, 31)]  # 30 addresses
            await asyncio.sleep(0.3)
            held_total = server.admission.preauth
            server_fds = _open_fds() - before - len(flood) - len(spread)   # ours are one fd each
            # the refused ones were told and closed at once; the held ones end at the handshake timeout
            answers = await asyncio.gather(*(_read_messages(r, timeout=5.0) for r, _ in flood))
            refused = [a for a in answers if a and isinstance(a[0], ErrorMessage) and a[0].code == ErrorCode.BUSY]
            held = await asyncio.gather(*(_read_messages(r, timeout=5.0) for r, _ in flood[:0] + spread))
            for _, w in flood + spread:
                w.close()
            # a well-behaved client from another address gets in afterwards
            reader, writer = await _raw(server.port, "127.0.2.1")
            writer.write(encode_message(_hello()))
            welcome = (await _read_messages(reader, lambda m: True))[0]
            writer.close()
            await asyncio.sleep(0.2)
            return held_one_ip, held_total, server_fds, refused, held, welcome, server.admission

    held_one_ip, held_total, server_fds, refused, held, welcome, admission = asyncio.run(main())
    assert held_one_ip == 10                                  # per-address cap
    assert held_total == 20                                   # total pre-auth cap
    assert server_fds <= 20 + 5                               # the server holds no more sockets than that
    assert len(refused) >= n - 10 and "too many connections from 127.0.0.2" in refused[0][0].text
    timed_out = [a for a in held if a and isinstance(a[-1], ErrorMessage) and a[-1].code == ErrorCode.TIMEOUT]
    assert timed_out and "no Hello within 1.5 s" in timed_out[0][-1].text
    assert isinstance(welcome, Welcome)
    assert admission.preauth == 0 and admission.counters.refused_per_ip >= n - 10


# ---------------------------------------------------------------------------------------------- item 6

def test_idle_slot_holders_are_evicted_and_a_retrying_client_gets_in(tmp_path):
    from quadcast.client.app import ClientConfig, LiveClient

    async def slot_holder(port: int) -> list:
        """Says Hello, then only ever asks for references -- never a pose."""
        reader, writer = await _raw(port)
        writer.write(encode_message(_hello()))

        async def nag():
            with contextlib.suppress(ConnectionError, OSError):
                while True:
                    await asyncio.sleep(0.2)
                    writer.write(encode_message(ReferenceRequest("gimme")))
                    await writer.drain()
        task = asyncio.create_task(nag())
        got = await _read_messages(reader)
        task.cancel()
        writer.close()
        return got

    async def main():
        async with _serving(max_sessions=2, idle_timeout=1.5, retry_after=0.4) as server:
            holders = [asyncio.create_task(slot_holder(server.port)) for _ in range(2)]
            while server.active < 2:
                await asyncio.sleep(0.05)
            client = LiveClient(ClientConfig("127.0.0.1", server.port, out=str(tmp_path), retries=8,
                                             retry_delay=0.1, max_retry_delay=0.3), make_client=None)
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            channel = await client._connect_with_retries()
            waited = loop.time() - t0
            if channel is not None:
                await channel.close()
            return await asyncio.gather(*holders), channel, waited, server.admission.counters

    holders, channel, waited, counters = asyncio.run(asyncio.wait_for(main(), 60))
    for got in holders:
        assert isinstance(got[0], Welcome)
        assert isinstance(got[-1], ErrorMessage) and got[-1].code == ErrorCode.TIMEOUT
        assert "no pose received for 1.5 s" in got[-1].text
    assert channel is not None, "the retrying client was never admitted"
    assert counters.refused_busy >= 1                   # it was told "busy" first ...
    assert 0.4 <= waited < 10                           # ... and got in once the holders were evicted


# ---------------------------------------------------------------------------------------------- item 7

def test_amplifying_blobs_are_refused_by_the_clients_within_100_mib(tmp_path):
    import json
    import subprocess
    import sys
    from pathlib import Path
    probe = Path(__file__).with_name("amplification_probe.py")
    for step in ("gen", "measure"):
        run = subprocess.run([sys.executable, str(probe), step, str(tmp_path)], capture_output=True, text=True,
                             timeout=300)
        assert run.returncode == 0, run.stderr[-3000:]
    result = json.loads(run.stdout.strip().splitlines()[-1])
    print(result)
    errors = result["errors"]
    assert result["blob_bytes"]["depth"] < 64_000 and result["blob_bytes"]["quads"] < 64_000
    assert "depth blob: 16777216x1, expected the 320x180 asked for" in errors["depth blob 16777216x1 (meshwarp)"]
    assert "layer[0]: 4096x2048, expected the 320x180 asked for" in errors["quad blob 8 Mi quads (quasar)"]
    assert errors["H.264 4096x4096 (atw)"].startswith("VideoError")
    assert errors["H.264 4096x4096 (quasar)"].startswith("VideoError")
    assert result["peak_rss_growth_mib"] < 100


# ---------------------------------------------------------------------------------------------- item 1 (client)

def test_a_frame_of_empty_layers_is_applied_and_rendered(ctx):
    """Empty layers are normal (a pose facing the open sky): the client applies such a frame and renders it.
    (The server side of item 1 is server/quads.py's.)"""
    from quadcast.codec.encoder import AtlasEncoder, VideoSettings
    from quadcast.methods import make_client
    from quadcast.protocol.methods import MethodConfig
    from quadcast.protocol.quads import LayerKind, QuadFrame, QuadLayer, QuadSet, encode_quad_frame
    from quadcast.render.camera import Camera
    w, h = 64, 36
    cam = Camera.perspective(Pose([0, 1.6, 0]), w, h, 60.0).to_array()
    layers = [QuadLayer(kind, w, h, cam, (0, 0, w, h), QuadSet.empty()) for kind in (LayerKind.VISIBLE,
                                                                                      LayerKind.HIDDEN)]
    layers.append(QuadLayer(LayerKind.WIDE, w // 2, h // 2, cam, (0, h, w // 2, h // 2), QuadSet.empty()))
    encoder = AtlasEncoder(2 * w, h + h // 2, VideoSettings(preset="ultrafast"))
    video = encoder.encode(np.zeros((h + h // 2, 2 * w, 3), np.uint8), keyframe=True).data
    encoder.close()
    client = make_client("quasar", MethodConfig(width=w, height=h), ctx)
    try:
        client.receive(FramePayload(Method.QUASAR, 0, FrameType.REFERENCE, 0, 0.0, np.zeros(3),
                                    np.array([0, 0, 0, 1.0]), video, encode_quad_frame(QuadFrame(layers)), True))
        assert not client.needs_reference and client.stats["mesh_quads"] == 0
        assert client.render(Pose([0, 1.6, 0])).shape == (h, w, 3)
    finally:
        client.close()


# ---------------------------------------------------------------------------------------------- spare workers

def test_spare_workers_boot_beside_running_sessions_only_when_none_is_left(monkeypatch):
    """A session claims a booted spare worker process. While sessions run, the server boots a replacement only when
    it took the last spare (booting one takes seconds of the CPU the running sessions' frames need); the rest are
    booted once no session runs. Only those booted while no session runs warm up (every method served)."""
    import quadcast.server.app as app

    booted = []

    class FakeProcess:
        alive = True

        def __init__(self, factory, args, name):
            self.warm_up = [(spec.method, spec.width, spec.height) for spec in args[1]]
            booted.append(self)

        def close(self, timeout=None):
            pass

    monkeypatch.setattr(app, "ProcessWorker", FakeProcess)
    server = LiveServer(ServerConfig(worker="process", spare_workers=2, methods=("quasar", "atw")), make_server=None)
    server._spawn_spares()
    assert len(booted) == 2
    assert all(p.warm_up == [("quasar", 200, 112), ("atw", 200, 112)] for p in booted)
    server.admission.sessions = 1
    assert server.claim_process() is booted[0]
    assert len(booted) == 2 and list(server._spares) == [booted[1]]     # one spare left: nothing boots
    server.admission.sessions = 2
    assert server.claim_process() is booted[1]
    assert len(booted) == 3 and list(server._spares) == [booted[2]]     # the last one taken: one boots
    assert booted[2].warm_up == []                                      # beside running sessions: no warm-up
    server.session_ended(app.ServerCounters())
    assert len(booted) == 3                                             # a session still runs
    server.admission.sessions = 0
    server.session_ended(app.ServerCounters())
    assert len(booted) == 4 and len(server._spares) == 2                # none runs: back to two
    assert booted[3].warm_up and not booted[2].warm_up
    booted.clear()
    LiveServer(ServerConfig(worker="process", spare_workers=1, warm_up=False), make_server=None)._spawn_spares()
    assert [p.warm_up for p in booted] == [[]]
