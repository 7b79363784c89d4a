"""WebRTC transport (sim/webrtc.py): two local aiortc peers deliver decodable video and quads, and the live
server serves a client over it."""
from __future__ import annotations

import asyncio
import json
import queue
import re

import numpy as np
import pytest

pytest.importorskip("aiortc")

from quadcast.codec.decoder import AtlasDecoder  # noqa: E402
from quadcast.codec.nal import contains_idr  # noqa: E402
from quadcast.protocol.frame import decode_frame_payload  # noqa: E402
from quadcast.protocol.messages import (PROTOCOL_VERSION, Bye, Frame, Hello, PoseUpdate, ReferenceRequest,  # noqa: E402
                               Welcome)
from quadcast.protocol.quads import decode_quad_frame  # noqa: E402
from quadcast.transport.webrtc import WebRtcListener, open_webrtc_channel  # noqa: E402
from webrtc_peers import (assert_same_frames, client_of, http_request, post_offer_body,  # noqa: E402
                          quasar_payloads, receive_frames, serving)

W, H = 160, 90


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0 ** 2 / max(mse, 1e-12))


@pytest.mark.parametrize("tapped, in_band", [(True, True), (True, False), (False, False)],
                         ids=["frames-in-access-units", "access-units-and-data-channel", "re-encoded"])
def test_two_local_peers_deliver_decodable_video_and_quads(tapped, in_band, monkeypatch):
    import quadcast.transport.webrtc as webrtc
    if not tapped:      # as on an aiortc whose receiver has no decoder queue to stand in for
        monkeypatch.setattr(webrtc, "tap_access_units", lambda receiver, deliver: False)
    if tapped and not in_band:      # as with a server that does not know the offer's "frames" field
        accept = webrtc.WebRtcListener._accept

        async def older_server(self, offer, peer):
            return await accept(self, {k: v for k, v in offer.items() if k != "frames"}, peer)
        monkeypatch.setattr(webrtc.WebRtcListener, "_accept", older_server)
    sent = quasar_payloads(4)
    got_poses: list = []
    got_requests: list = []

    server_in_band: list = []
    server_bytes_out: list = []

    async def serve(channel):
        server_in_band.append(channel.frames_in_band)
        hello = await channel.recv()
        assert isinstance(hello, Hello)
        await channel.send(Welcome(1, 30.0))
        for payload in sent:
            await channel.send_frame(payload)
        server_bytes_out.append(channel.bytes_out)
        while True:
            msg = await channel.recv()
            if msg is None or isinstance(msg, Bye):
                return
            (got_poses if isinstance(msg, PoseUpdate) else got_requests).append(msg)

    async def main():
        listener = WebRtcListener("127.0.0.1", 0, serve)
        await listener.start()
        try:
            ch = await open_webrtc_channel("127.0.0.1", listener.port, 1 << 24, timeout=20)
            await ch.send(Hello(PROTOCOL_VERSION, "quasar", W, H, 60.0))
            welcome = await asyncio.wait_for(ch.recv(), 20)
            for k in range(3):
                await ch.send(PoseUpdate(k, k / 30, [0, 1.6, 0], [0, 0, 0, 1]))
            await ch.send(ReferenceRequest("test"))
            sockets = webrtc.enlarge_socket_buffers(ch.pc)
            frames = await receive_frames(ch, len(sent))
            await ch.send(Bye())
            await asyncio.sleep(0.3)
            await ch.close()
            return welcome, frames, ch.bytes_in, (ch.access_units_tapped, ch.frames_in_band), sockets
        finally:
            await listener.close()

    welcome, frames, bytes_in, modes, sockets = asyncio.run(asyncio.wait_for(main(), 90))
    assert modes == (tapped, in_band) and server_in_band == [in_band]
    # the peer connection's UDP sockets and aiortc's RTP history were found where they are looked for
    import aiortc.rtcrtpreceiver
    import aiortc.rtcrtpsender
    assert sockets >= 1
    assert aiortc.rtcrtpsender.RTP_HISTORY_SIZE == aiortc.rtcrtpreceiver.RTP_HISTORY_SIZE == webrtc.RTP_HISTORY_PACKETS
    assert welcome == Welcome(1, 30.0)
    assert [f.frame_id for f in frames] == [p.frame_id for p in sent]
    assert bytes_in >= sum(len(p.geometry) for p in sent)
    # each frame's bytes counted once (an SEI and a delimiter add a little), whichever way its parts went
    size = sum(p.size_bytes for p in sent)
    assert size <= server_bytes_out[0] <= size * 1.01 + 100 * len(sent)
    for original, received in zip(sent, frames):
        # quads arrive byte for byte on the data channel and decode
        assert received.geometry == original.geometry
        # the header arrives as sent (type, reference, self-contained flag, pose)
        assert (received.frame_type, received.reference_id, received.self_contained) == (
            original.frame_type, original.reference_id, original.self_contained)
        assert decode_quad_frame(received.geometry).quad_count > 0
        np.testing.assert_allclose(received.position, original.position)
        # the server's access unit as it was sent, or its picture coded again as a standalone IDR
        assert contains_idr(received.video) == (original.self_contained or not tapped)
    direct = AtlasDecoder()
    reference = [direct.decode(p.video, p.frame_id) for p in sent]
    one_stream = AtlasDecoder()
    for ref_img, received in zip(reference, frames):
        if tapped:      # the receiver's access units decode in one stream to the very same pictures
            np.testing.assert_array_equal(one_stream.decode(received.video, received.frame_id), ref_img)
        else:
            img = AtlasDecoder().decode(received.video, received.frame_id)
            assert img.shape == ref_img.shape
            assert _psnr(img, ref_img) > 30.0
    assert len(got_poses) >= 1
    assert got_requests == [ReferenceRequest("test")]


def test_signalling_rejects_bad_requests():
    async def serve(channel):  # never reached
        raise AssertionError("no channel expected")

    async def main():
        listener = WebRtcListener("127.0.0.1", 0, serve)
        await listener.start()
        try:
            bad_json = await post_offer_body(listener.port, b'{"type": "offer", "sdp": 5}')
            wrong_path = await http_request(listener.port, b"GET / HTTP/1.1\r\n\r\n")
            huge = await http_request(listener.port,
                                      b"POST /offer HTTP/1.1\r\nContent-Length: 99999999\r\n\r\n")
            bad_sdp = await post_offer_body(listener.port,
                                            json.dumps({"type": "offer", "sdp": "v=0\r\nnot sdp"}).encode())
            return bad_json, wrong_path, huge, bad_sdp
        finally:
            await listener.close()

    bad_json, wrong_path, huge, bad_sdp = asyncio.run(asyncio.wait_for(main(), 60))
    assert bad_json.startswith(b"HTTP/1.1 400") and b"sdp" in bad_json
    assert wrong_path.startswith(b"HTTP/1.1 404")
    assert huge.startswith(b"HTTP/1.1 400") and b"cap" in huge
    assert bad_sdp.startswith(b"HTTP/1.1 400")


def test_live_server_and_client_processes_over_webrtc(tmp_path):
    from quadcast.cli.demo import LISTENING, Child, quadcast_argv
    server = Child("server", quadcast_argv("server", "--port", 0, "--transport", "webrtc", "-v"),
                   tmp_path / "server.log")
    try:
        port = int(server.wait_for(LISTENING, 120).group(2))
        out = tmp_path / "client"
        client = Child("client", quadcast_argv("client", "--connect", f"127.0.0.1:{port}", "--transport", "webrtc",
                                               "--size", "320x180", "--trace", "builtin:walk", "--duration", 4,
                                               "--no-score", "--out", out), tmp_path / "client.log")
        try:
            client.wait_for(r"first frame applied", 120)
            assert client.wait(120) == 0, client.stderr_tail()
            print("\n".join(client.lines))
        finally:
            client.stop()
    finally:
        server.stop()
    rec = json.loads((out / "recording.json").read_text())
    run = rec["summary"]
    assert run["transport"] == "webrtc" and run["reconnects"] == 0, run
    assert run["frames_applied"] >= 1, run
    # RTP over loopback UDP can lose a picture under load: the client must then have asked for a reference
    assert run["frames_rejected"] == 0 or run["reference_requests"] >= 1, run
    assert run["bytes_socket"] > 0 and run["mbps"] > 0
    shown = [f for f in rec["frames"] if f["frame_id"] >= 0]
    assert shown and all((out / f["image"]).exists() for f in shown)
    from PIL import Image
    img = np.asarray(Image.open(out / shown[-1]["image"]))
    assert img.shape == (180, 320, 3) and img.std() > 5     # a rendered picture, not a black frame
    assert re.search(r"session 1 \(.*\): quasar 320x180", (tmp_path / "server.log").read_text())


def test_the_access_unit_tap_leaves_a_receiver_it_does_not_know_alone():
    from quadcast.transport.webrtc import tap_access_units

    class Started:      # an aiortc receiver whose decoder thread already runs
        _RTCRtpReceiver__decoder_queue = queue.Queue()
        _RTCRtpReceiver__decoder_thread = object()

    assert tap_access_units(object(), lambda t, data: None) is False
    started = Started()
    assert tap_access_units(started, lambda t, data: None) is False
    assert type(started._RTCRtpReceiver__decoder_queue) is queue.Queue


class _Emitter:
    """Stands in for an aiortc peer connection or data channel: takes event handlers and never calls them."""

    connectionState = "connected"

    def on(self, event, handler=None):
        return handler if handler is not None else (lambda fn: fn)


def _split_frames(n: int):
    """n small frames as the server's channel splits them: (track index, rest, access unit)."""
    from quadcast.protocol.frame import FramePayload, FrameType, Method, encode_frame_payload, split_video
    out = []
    for i in range(n):
        payload = FramePayload(Method.QUASAR, i, FrameType.RESIDUAL, 0, i / 30, np.zeros(3), np.array([0, 0, 0, 1.0]),
                               video=bytes([i % 251]) * (500 + i), geometry=b"g" * 300)
        rest, video = split_video(encode_frame_payload(payload), i)
        out.append((i, rest, video))
    return out


def test_frames_whose_data_channel_lags_the_video_track_are_still_paired():
    """Under loss SCTP delivers the frames' data late while the RTP pictures keep coming: a second of pictures
    ahead (more than the old count cap of 32) must still find their frames."""
    from quadcast.protocol.messages import encode_message
    from quadcast.transport.webrtc import CHANNELS, TICKS_PER_FRAME, WebRtcChannel

    async def main():
        ch = WebRtcChannel(_Emitter(), {name: _Emitter() for name in CHANNELS}, 1 << 20)
        frames = _split_frames(48)
        for index, _, video in frames:
            ch._on_access_unit(index * TICKS_PER_FRAME, video)
        for _, rest, _ in frames:
            ch._on_message("frames", encode_message(Frame(rest)))
        out = []
        while not ch._incoming.empty():
            out.append(decode_frame_payload((await ch.recv()).payload))
        return out, ch.frames_unpaired

    out, unpaired = asyncio.run(main())
    assert unpaired == 0
    assert [p.frame_id for p in out] == list(range(48))
    assert all(p.video == bytes([p.frame_id % 251]) * (500 + p.frame_id) for p in out)


def test_frames_larger_than_aiortcs_jitter_buffer_arrive_whole():
    """A frame of about 1,000 RTP packets (aiortc's own receiver holds 512, and lost every such frame): the client's
    FrameReassembly hands it out whole, quads (in the access unit) and picture."""
    import dataclasses
    import os

    from quadcast.transport.rtp_reassembly import FrameReassembly
    sent = [dataclasses.replace(p, geometry=p.geometry + os.urandom(1_200_000) * (i == 0))
            for i, p in enumerate(quasar_payloads(3))]
    server_sends = []

    async def main():
        serve = serving(sent, lambda channel: server_sends.append(
            channel.pc.getTransceivers()[0].sender.transport._send_rtp))
        async with client_of(serve) as ch:
            buffers = [type(t.receiver._RTCRtpReceiver__jitter_buffer) for t in ch.pc.getTransceivers()]
            return buffers, ch.frames_in_band, await receive_frames(ch, len(sent), timeout=30)

    buffers, in_band, frames = asyncio.run(asyncio.wait_for(main(), 90))
    assert buffers == [FrameReassembly] and in_band
    assert server_sends[0].sent[0] >= 900        # the server's packets went through pace_rtp_sending
    assert_same_frames(sent, frames)


def test_sending_a_frames_packets_lets_the_event_loop_run_other_work():
    from quadcast.transport.webrtc import pace_rtp_sending

    class Transport:
        async def _send_rtp(self, data):
            pass
    transport = Transport()
    assert pace_rtp_sending(transport, every=32) is True
    assert pace_rtp_sending(transport) is False          # not twice
    assert pace_rtp_sending(object()) is False

    async def main():
        ticks = []

        async def other_session():
            while True:
                ticks.append(len(ticks))
                await asyncio.sleep(0)
        other = asyncio.ensure_future(other_session())
        await asyncio.sleep(0)
        before = len(ticks)
        for _ in range(1000):                    # a 1920x1080 frame's packets, sent back to back
            await transport._send_rtp(b"packet")
        other.cancel()
        return len(ticks) - before
    assert asyncio.run(main()) >= 1000 // 32


def test_a_paced_peer_connection_sends_no_faster_than_its_rate():
    """``--pace 8mbit``: 20 packets of 1,000 bytes take 19 ms of the loop's time from first to last (each 1 ms at
    that rate; the pacer does not sleep for less than a millisecond, so a packet may leave that much early);
    unpaced they go at once. A bad rate is refused."""
    from quadcast.transport.webrtc import pace_rtp_sending

    class Transport:
        def __init__(self):
            self.times = []

        async def _send_rtp(self, data):
            self.times.append(asyncio.get_running_loop().time())

    async def send(pace):
        transport = Transport()
        pace_rtp_sending(transport, pace_mbit=pace)
        for _ in range(20):
            await transport._send_rtp(b"x" * 1000)
        return transport.times[-1] - transport.times[0]

    assert asyncio.run(send(8.0)) >= 0.018 - 1e-6
    assert asyncio.run(send(None)) < 0.018
    with pytest.raises(ValueError, match="pace must be a rate > 0"):
        pace_rtp_sending(Transport(), pace_mbit=0.0)
    with pytest.raises(ValueError, match="pace must be a rate > 0"):      # when the server starts, not per offer
        WebRtcListener("127.0.0.1", 0, lambda channel: None, pace_mbit=float("nan"))
