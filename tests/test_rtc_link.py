"""`quadcast link --webrtc` (sim/rtc_proxy.py): the signalling goes through the link with its ICE candidates
replaced by the link's UDP stand-ins, and every datagram between the peers crosses the link's models."""
from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

pytest.importorskip("aiortc")

from quadcast.protocol.frame import decode_frame_payload  # noqa: E402
from quadcast.protocol.messages import PROTOCOL_VERSION, Bye, Hello, Welcome  # noqa: E402
from quadcast.sim.proxy import parse_link_args  # noqa: E402
from quadcast.sim.rtc_proxy import RtcLinkProxy, candidate_addresses, rewrite_candidates  # noqa: E402
from quadcast.transport.webrtc import SignallingPolicy, WebRtcListener, open_webrtc_channel  # noqa: E402
from webrtc_peers import (assert_same_frames, http_request, post_offer_body, quasar_payloads,  # noqa: E402
                          receive_frames)

SDP = "\r\n".join([
    "v=0",
    "m=application 50000 UDP/DTLS/SCTP webrtc-datachannel",
    "c=IN IP4 192.0.2.2",
    "a=mid:0",
    "a=candidate:f9 1 udp 2130706431 192.0.2.2 50000 typ host",
    "a=candidate:d0 1 udp 2130706431 fd00::2 50001 typ host",
    "a=candidate:aa 1 udp 1694498815 198.51.100.7 61000 typ srflx raddr 192.0.2.2 rport 50000",
    "a=candidate:f9 1 udp 2130706431 192.0.2.2 50000 typ host",
    "a=end-of-candidates",
    "a=ice-ufrag:HCSa",
    "",
])


def test_candidates_are_replaced_by_their_stand_ins_and_the_rest_left_out():
    assert candidate_addresses(SDP) == [("192.0.2.2", 50000), ("198.51.100.7", 61000)]
    out = rewrite_candidates(SDP, {("192.0.2.2", 50000): ("127.0.0.1", 40001)})
    candidates = [line for line in out.split("\r\n") if line.startswith("a=candidate:")]
    assert candidates == ["a=candidate:f9 1 udp 2130706431 127.0.0.1 40001 typ host"] * 2
    # everything else is as it was
    assert [line for line in out.split("\r\n") if not line.startswith("a=candidate:")] == \
        [line for line in SDP.split("\r\n") if not line.startswith("a=candidate:")]
    with pytest.raises(ValueError, match="malformed ICE candidate"):
        candidate_addresses("a=candidate:x 1 udp 5 192.0.2.2 notaport typ host\r\n")


def test_a_webrtc_session_runs_through_the_link_and_its_delay():
    sent = quasar_payloads(6)
    delay_ms = 40

    async def serve(channel):
        await channel.recv()
        await channel.send(Welcome(1, 30.0))
        for payload in sent:
            await channel.send_frame(payload)
        while (msg := await channel.recv()) is not None and not isinstance(msg, Bye):
            pass

    async def main():
        listener = WebRtcListener("127.0.0.1", 0, serve, policy=SignallingPolicy(token="secret"))
        await listener.start()
        link = RtcLinkProxy("127.0.0.1", 0, "127.0.0.1", listener.port,
                            up=parse_link_args(f"{delay_ms}ms", seed=1), down=parse_link_args(f"{delay_ms}ms", seed=2))
        await link.start()
        try:
            with pytest.raises(PermissionError):      # the server's refusal comes back through the link
                await open_webrtc_channel("127.0.0.1", link.port, 1 << 24, timeout=20, token="wrong")
            ch = await open_webrtc_channel("127.0.0.1", link.port, 1 << 24, timeout=20, token="secret")
            t0 = time.monotonic()
            await ch.send(Hello(PROTOCOL_VERSION, "quasar", 160, 90, 60.0, token="secret"))
            welcome = await asyncio.wait_for(ch.recv(), 20)
            round_trip = time.monotonic() - t0
            frames = await receive_frames(ch, len(sent))
            await ch.send(Bye())
            await asyncio.sleep(0.2)
            await ch.close()
            return welcome, round_trip, frames, link.stats
        finally:
            await link.close()
            await listener.close()

    welcome, round_trip, frames, stats = asyncio.run(asyncio.wait_for(main(), 120))
    assert welcome == Welcome(1, 30.0)
    assert round_trip >= 2 * delay_ms / 1000
    assert stats.connections_accepted == 2 and stats.upstream_failures == 0
    assert stats.up.messages_forwarded > 0 and stats.down.messages_forwarded > 0
    assert stats.down.bytes_forwarded > sum(p.size_bytes for p in sent)     # the frames crossed the link
    assert_same_frames(sent, frames)


def test_the_link_refuses_a_bad_offer_without_asking_the_server():
    asked = []

    async def serve(channel):  # never reached
        asked.append(channel)

    async def main():
        listener = WebRtcListener("127.0.0.1", 0, serve)
        await listener.start()
        link = RtcLinkProxy("127.0.0.1", 0, "127.0.0.1", listener.port, up=parse_link_args(), down=parse_link_args(),
                            max_candidates=2)
        await link.start()
        try:
            bad_json = await post_offer_body(link.port, b'{"type": "offer", "sdp": 5}')
            wrong_path = await http_request(link.port, b"GET / HTTP/1.1\r\n\r\n")
            many = "\r\n".join(f"a=candidate:{i} 1 udp 1 192.0.2.{i} 5000 typ host" for i in range(1, 4))
            body = ('{"type": "offer", "sdp": "v=0\\r\\n%s\\r\\n"}' % many.replace("\r\n", "\\r\\n")).encode()
            too_many = await post_offer_body(link.port, body)
            return bad_json, wrong_path, too_many, link.stats
        finally:
            await link.close()
            await listener.close()

    bad_json, wrong_path, too_many, stats = asyncio.run(asyncio.wait_for(main(), 60))
    assert bad_json.startswith(b"HTTP/1.1 400") and b"sdp" in bad_json
    assert wrong_path.startswith(b"HTTP/1.1 400") and b"POST /offer" in wrong_path
    assert too_many.startswith(b"HTTP/1.1 400") and b"3 candidate addresses (cap 2)" in too_many
    assert stats.framing_errors == 3 and stats.connections_open == 0 and not asked


def test_frames_cross_a_lossy_link_whole_or_not_at_all():
    """3% of datagrams lost each way: WebRTC's NACKs recover most frames, each frame that arrives is the one sent
    (its quads and its picture), in order, and the stream does not stall."""
    sent = quasar_payloads(30)

    async def serve(channel):
        await channel.recv()
        await channel.send(Welcome(1, 30.0))
        for payload in sent:
            await channel.send_frame(payload)
            await asyncio.sleep(1 / 30)
        while (msg := await channel.recv()) is not None and not isinstance(msg, Bye):
            pass

    async def main():
        listener = WebRtcListener("127.0.0.1", 0, serve)
        await listener.start()
        link = RtcLinkProxy("127.0.0.1", 0, "127.0.0.1", listener.port, up=parse_link_args("15ms", loss="3%", seed=3),
                            down=parse_link_args("15ms", loss="3%", seed=4))
        await link.start()
        try:
            ch = await open_webrtc_channel("127.0.0.1", link.port, 1 << 24, timeout=20)
            await ch.send(Hello(PROTOCOL_VERSION, "quasar", 160, 90, 60.0))
            await asyncio.wait_for(ch.recv(), 20)
            frames = []
            while not frames or frames[-1].frame_id != sent[-1].frame_id:
                try:
                    msg = await asyncio.wait_for(ch.recv(), 5)
                except asyncio.TimeoutError:
                    break
                frames.append(decode_frame_payload(msg.payload))
            await ch.send(Bye())
            await asyncio.sleep(0.2)
            await ch.close()
            return frames, link.stats
        finally:
            await link.close()
            await listener.close()

    frames, stats = asyncio.run(asyncio.wait_for(main(), 120))
    assert stats.down.dropped_loss > 0
    ids = [f.frame_id for f in frames]
    assert ids == sorted(set(ids)) and len(ids) >= len(sent) // 2, ids
    by_id = {p.frame_id: p for p in sent}
    from quadcast.codec.decoder import AtlasDecoder
    for got in frames:
        assert got.geometry == by_id[got.frame_id].geometry
        if got.self_contained:      # an IDR decodes on its own to the very picture sent
            np.testing.assert_array_equal(AtlasDecoder().decode(got.video), AtlasDecoder().decode(
                by_id[got.frame_id].video))
