"""What a WebRTC peer can make the other side do: a client's NACKs get a bounded number of packets sent again, and a
peer's SCTP data is held only up to the receive window (on stand-ins and between two real peers)."""
from __future__ import annotations

import asyncio
import dataclasses
import os
import struct

import pytest

pytest.importorskip("aiortc")

from quadcast.protocol.messages import PoseUpdate, ReferenceRequest  # noqa: E402
from quadcast.transport.peer_limits import (SCTP_MAX_MISORDERED, RetransmitBudget,  # noqa: E402
                                           limit_retransmissions, limit_sctp_receive)
from webrtc_peers import client_of, quasar_payloads, receive_frames, serving  # noqa: E402


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
    senders = []

    async def main():
        serve = serving(sent, lambda channel: senders.append(channel.pc.getTransceivers()[0].sender))
        async with client_of(serve) as ch:
            await receive_frames(ch, len(sent), timeout=30)
            receiver = ch.pc.getTransceivers()[0].receiver
            media_ssrc = next(iter(receiver._RTCRtpReceiver__active_ssrc))
            top = receiver._RTCRtpReceiver__nack_generator.max_seq
            items = b"".join(struct.pack("!HH", (top - 17 * (i % 60) - 16) & 0xFFFF, 0xFFFF) for i in range(300))
            nack = pack_rtcp_packet(RTCP_RTPFB, 1, struct.pack("!LL", receiver._RTCRtpReceiver__rtcp_ssrc,
                                                                 media_ssrc) + items)
            start = asyncio.get_running_loop().time()
            for _ in range(20):
                await receiver._send_rtcp(_Raw(nack))
                await asyncio.sleep(0.01)
            await asyncio.sleep(1.0)
            return asyncio.get_running_loop().time() - start

    elapsed = asyncio.run(asyncio.wait_for(main(), 90))
    budget = senders[0]._retransmit
    assert isinstance(budget, RetransmitBudget)
    assert 10 * 300 * 17 <= budget.passed + budget.refused <= 20 * 300 * 17    # the requests reached the budget
    assert 1000 <= budget.passed <= budget.burst + budget.per_s * elapsed


class _Association:
    """Stands in for aiortc's SCTP association: what the limits read, and a receive that takes every chunk as
    aiortc's does (the window shrinks by each chunk's data; a chunk past the next expected TSN is held)."""

    def __init__(self, window: int = 10_000) -> None:
        self._advertised_rwnd = window
        self._sack_misordered: set[int] = set()
        self._last_received_tsn = 99
        self.taken: list[int] = []

    async def _receive_data_chunk(self, chunk) -> None:
        self.taken.append(chunk.tsn)
        self._advertised_rwnd -= len(chunk.user_data)
        if chunk.tsn == self._last_received_tsn + 1:
            self._last_received_tsn = chunk.tsn
        else:
            self._sack_misordered.add(chunk.tsn)


def _chunk(tsn: int, size: int = 1000):
    from aiortc.rtcsctptransport import DataChunk
    c = DataChunk()
    c.tsn, c.stream_id, c.stream_seq, c.protocol, c.user_data = tsn, 1, 0, 51, b"x" * size
    return c


def test_sctp_chunks_past_the_window_or_empty_are_dropped():
    sctp = _Association(window=3_500)
    assert limit_sctp_receive(sctp) is True and limit_sctp_receive(sctp) is False    # not twice

    async def send():
        for tsn in range(100, 106):
            await sctp._receive_data_chunk(_chunk(tsn))
        await sctp._receive_data_chunk(_chunk(106, size=0))
    asyncio.run(send())
    assert sctp.taken == [100, 101, 102] and sctp._receive_data_chunk.dropped == [4]


def test_sctp_chunks_ahead_of_a_gap_are_capped_but_the_gap_can_still_be_filled():
    sctp = _Association(window=1 << 40)
    limit_sctp_receive(sctp)

    async def send():
        for tsn in range(101, 101 + 2 * SCTP_MAX_MISORDERED):    # 100 is missing
            await sctp._receive_data_chunk(_chunk(tsn, size=10))
        await sctp._receive_data_chunk(_chunk(100, size=10))
    asyncio.run(send())
    assert len(sctp._sack_misordered) == SCTP_MAX_MISORDERED and sctp.taken[-1] == 100
    assert limit_sctp_receive(object()) is False


def test_a_peer_sending_a_message_that_never_ends_is_held_to_the_window():
    """The client sends the server 5 MB of fragments of one message, never its last: aiortc's association alone
    would keep all that arrives; with the limit it holds at most its 1 MiB window."""
    from aiortc.rtcsctptransport import SCTP_DATA_FIRST_FRAG, DataChunk
    servers = []

    async def main():
        async with client_of(serving(on_channel=lambda channel: servers.append(channel.pc.sctp))) as ch:
            sctp, sid = ch.pc.sctp, ch.dc["control"].id
            tsn = sctp._local_tsn
            for i in range(5000):
                c = DataChunk(flags=SCTP_DATA_FIRST_FRAG if i == 0 else 0)
                c.tsn, c.stream_id, c.stream_seq, c.protocol, c.user_data = tsn, sid, 60000, 51, b"x" * 1000
                tsn = (tsn + 1) & 0xFFFFFFFF
                await sctp._send_chunk(c)
                if i % 50 == 0:
                    await asyncio.sleep(0.002)     # what the loopback's buffers take
            await asyncio.sleep(0.5)
            server = servers[0]
            data = sum(len(c.user_data) for s in server._inbound_streams.values() for c in s.reassembly)
            return data, server._advertised_rwnd, getattr(server._receive_data_chunk, "dropped", [0])[0]

    data, window, dropped = asyncio.run(asyncio.wait_for(main(), 90))
    assert data <= 1 << 20 and window >= 0 and dropped > 0


def test_data_channels_the_protocol_does_not_have_are_closed_by_the_server():
    """A client opening 200 more data channels (unknown labels, and "control" again): the server's association keeps
    only the protocol's three, and the session goes on."""
    servers = []

    async def main():
        async with client_of(serving(on_channel=lambda channel: servers.append(channel.pc.sctp))) as ch:
            for i in range(200):
                ch.pc.createDataChannel("control" if i == 0 else f"extra{i}")
            await asyncio.sleep(1.5)
            kept = len(servers[0]._data_channels)
            await ch.send(ReferenceRequest("still there?"))
            await ch.send(PoseUpdate(0, 0.0, [0, 1.6, 0], [0, 0, 0, 1]))
            return kept, ch.pc.connectionState

    kept, state = asyncio.run(asyncio.wait_for(main(), 90))
    assert kept == 3 and state == "connected"
