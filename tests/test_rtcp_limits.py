"""RetransmitBudget: a WebRTC client's NACKs get a bounded number of packets sent again, on a fake clock and between
two real peers."""
from __future__ import annotations

import asyncio
import dataclasses
import os
import struct

import pytest

pytest.importorskip("aiortc")

from quadcast.protocol.messages import PROTOCOL_VERSION, Bye, Hello, Welcome  # noqa: E402
from quadcast.transport.rtcp_limits import RetransmitBudget, limit_retransmissions  # noqa: E402
from quadcast.transport.webrtc import WebRtcListener, open_webrtc_channel  # noqa: E402
from webrtc_peers import quasar_payloads, receive_frames  # noqa: E402


def _budget(**kw):
    now = [0.0]
    sent: list[int] = []

    async def retransmit(seq):
        sent.append(seq)
    return RetransmitBudget(retransmit, clock=lambda: now[0], **kw), sent, now


def test_a_packet_goes_out_again_once_per_interval():
    budget, sent, now = _budget(interval_s=0.05)

    async def asks():
        for _ in range(5):
            await budget(7)
        now[0] += 0.06
        await budget(7)
        await budget(8)
    asyncio.run(asks())
    assert sent == [7, 7, 8] and budget.refused == 4


def test_the_token_bucket_caps_bursts_and_refills_at_its_rate():
    budget, sent, now = _budget(per_s=100, burst=10, interval_s=0.0)

    async def asks():
        for seq in range(50):
            await budget(seq)
        now[0] += 0.2                   # 20 tokens' worth, but the bucket holds 10
        for seq in range(50, 100):
            await budget(seq)
    asyncio.run(asks())
    assert sent == list(range(10)) + list(range(50, 60))
    assert budget.refused == 80 and budget.passed == 20


def test_the_budget_forgets_old_packets():
    budget, sent, now = _budget(per_s=1e9, burst=8, interval_s=0.01)

    async def asks():
        for seq in range(1000):
            await budget(seq)
            now[0] += 0.001
    asyncio.run(asks())
    assert len(sent) == 1000 and len(budget._sent) <= 2 * 8 + 1


def test_limit_retransmissions_leaves_what_it_does_not_know_alone():
    assert limit_retransmissions(object()) is False

    class Sender:
        async def _retransmit(self, seq):
            pass
    sender = Sender()
    assert limit_retransmissions(sender) is True and isinstance(sender._retransmit, RetransmitBudget)
    assert limit_retransmissions(sender) is False      # not twice


class _Raw:
    def __init__(self, data: bytes) -> None:
        self.data = data

    def __bytes__(self) -> bytes:
        return self.data


def test_a_client_flooding_nacks_gets_a_bounded_number_of_packets_again():
    """The client asks 60 times a datagram, in 20 datagrams, for each of the last 1,020 packets the server sent
    (aiortc's own sender would send 102,000 packets again); the server's sender is behind a RetransmitBudget."""
    from aiortc.rtp import RTCP_RTPFB, pack_rtcp_packet
    sent = [dataclasses.replace(p, geometry=p.geometry + os.urandom(600_000)) for p in quasar_payloads(2)]
    counts = {}

    async def serve(channel):
        await channel.recv()
        await channel.send(Welcome(1, 30.0))
        sender = channel.pc.getTransceivers()[0].sender
        counts["budget"] = sender._retransmit
        for payload in sent:
            await channel.send_frame(payload)
        while await channel.recv() is not None:
            pass

    async def main():
        listener = WebRtcListener("127.0.0.1", 0, serve)
        await listener.start()
        try:
            ch = await open_webrtc_channel("127.0.0.1", listener.port, 1 << 24, timeout=20)
            await ch.send(Hello(PROTOCOL_VERSION, "quasar", 160, 90, 60.0))
            await asyncio.wait_for(ch.recv(), 20)
            await receive_frames(ch, len(sent), timeout=30)
            receiver = ch.pc.getTransceivers()[0].receiver
            media_ssrc = next(iter(receiver._RTCRtpReceiver__active_ssrc))
            top = receiver._RTCRtpReceiver__nack_generator.max_seq
            items = b"".join(struct.pack("!HH", (top - 17 * (i % 60) - 16) & 0xFFFF, 0xFFFF) for i in range(300))
            nack = pack_rtcp_packet(RTCP_RTPFB, 1, struct.pack("!LL", receiver._RTCRtpReceiver__rtcp_ssrc,
                                                                 media_ssrc) + items)
            budget = counts["budget"]
            start = asyncio.get_running_loop().time()
            for _ in range(20):
                await receiver._send_rtcp(_Raw(nack))
                await asyncio.sleep(0.01)
            await asyncio.sleep(1.0)
            elapsed = asyncio.get_running_loop().time() - start
            await ch.send(Bye())
            await ch.close()
            return budget, elapsed
        finally:
            await listener.close()

    budget, elapsed = asyncio.run(asyncio.wait_for(main(), 90))
    assert isinstance(budget, RetransmitBudget)
    assert budget.passed + budget.refused == 20 * 300 * 17          # every request reached the budget
    assert 1000 <= budget.passed <= budget.burst + budget.per_s * elapsed
