"""FrameReassembly: aiortc's jitter buffer decisions, for frames of any size, and a frame blocked by a loss dropped
in time."""
import random

import pytest
from aiortc.jitterbuffer import JitterBuffer
from aiortc.rtp import RtpPacket
from hypothesis import given, settings
from hypothesis import strategies as st

from quadcast.transport.rtp_reassembly import GIVE_UP_S, FrameReassembly, reassemble_in


def _packets(sizes, first_seq=0, ts_step=3000):
    """The RTP packets of frames of ``sizes`` packets each, in order; each packet's bytes name it."""
    out, seq = [], first_seq
    for f, n in enumerate(sizes):
        for _ in range(n):
            p = RtpPacket(payload_type=96, sequence_number=seq & 0xFFFF, timestamp=(f + 1) * ts_step)
            p._data = seq.to_bytes(4, "little")
            out.append(p)
            seq += 1
    return out


def _feed(buffer, packets):
    out = []
    for p in packets:
        lost, frame = buffer.add(p)
        out.append((lost, None if frame is None else (frame.data, frame.timestamp)))
    return out


@st.composite
def _arrivals(draw):
    """Packets of frames of 1-40 packets, then losses, duplicates, packets reusing a number, swaps, late packets
    and a restart of the sequence numbers, starting anywhere (wrap-around included)."""
    sizes = draw(st.lists(st.integers(1, 40), min_size=1, max_size=12))
    packets = _packets(sizes, first_seq=draw(st.sampled_from([0, 65500, 30000])))
    rng = random.Random(draw(st.integers(0, 2 ** 32)))
    out = []
    for p in packets:
        r = rng.random()
        if r < 0.05:
            continue                          # lost
        out.append(p)
        if r > 0.95:
            out.append(p)                     # duplicated
        elif r > 0.93:                        # its number again, another frame's (a confused or hostile sender)
            other = RtpPacket(payload_type=96, sequence_number=p.sequence_number, timestamp=p.timestamp + 3000)
            other._data = b"!!!!"
            out.insert(rng.randrange(len(out) + 1), other)
    for _ in range(draw(st.integers(0, 6))):  # swapped, near or far
        i, j = rng.randrange(len(out) or 1), rng.randrange(len(out) or 1)
        if out:
            out[i], out[j] = out[j], out[i]
    if draw(st.booleans()) and out:           # the sender starts again far away
        out += _packets([3, 2, 1], first_seq=(out[-1].sequence_number + 20000) & 0xFFFF)
    return out


@settings(max_examples=300, deadline=None)
@given(_arrivals(), st.sampled_from([16, 64, 512]))
def test_the_same_decisions_as_aiortcs_jitter_buffer(packets, capacity):
    ours = FrameReassembly(capacity, give_up_s=None)
    assert _feed(ours, packets) == _feed(JitterBuffer(capacity, is_video=True), packets)


def test_a_frame_larger_than_aiortcs_buffer_comes_out_whole():
    packets = _packets([3000, 1200, 1])
    got = [f for _, f in _feed(FrameReassembly(), packets) if f is not None]
    assert [len(data) // 4 for data, _ in got] == [3000, 1200]
    assert got[0][0] == b"".join(p._data for p in packets[:3000])
    # aiortc's own loses the start of the first frame: it overflows
    theirs = [f for _, f in _feed(JitterBuffer(512, is_video=True), packets) if f is not None]
    assert len(theirs[0][0]) // 4 < 3000


def test_a_frame_blocked_by_a_lost_packet_is_dropped_after_the_give_up_time():
    now = [0.0]
    buffer = FrameReassembly(give_up_s=GIVE_UP_S, clock=lambda: now[0])
    packets = _packets([10, 10, 10, 10, 1])
    lost_one = [p for p in packets if p.sequence_number != 5]     # frame 1 loses a packet for good
    results = []
    for p in lost_one:
        results.append(buffer.add(p))
        now[0] += 0.01                        # 41 packets over 0.4 s: less than the give-up time
    assert all(frame is None for _, frame in results) and buffer.frames_abandoned == 0
    now[0] += GIVE_UP_S
    late = RtpPacket(payload_type=96, sequence_number=41, timestamp=6 * 3000)
    late._data = b""
    lost, frame = buffer.add(late)
    assert lost and buffer.frames_abandoned == 1
    assert frame is not None and frame.timestamp == 2 * 3000 and frame.data == b"".join(p._data for p in packets[10:20])
    # the frames behind it follow, one a packet, and a retransmission that comes too late is ignored
    rest = [buffer.add(p)[1] for p in (packets[5], late, late)]
    assert [f.timestamp for f in rest if f is not None] == [3 * 3000, 4 * 3000]


def test_a_retransmission_within_the_give_up_time_completes_the_frame():
    now = [0.0]
    buffer = FrameReassembly(clock=lambda: now[0])
    packets = _packets([10, 10, 1])
    for p in packets:
        if p.sequence_number != 5:
            buffer.add(p)
    now[0] += GIVE_UP_S / 2
    lost, frame = buffer.add(packets[5])
    assert not lost and frame.data == b"".join(p._data for p in packets[:10])
    assert buffer.frames_abandoned == 0


def test_reassembly_replaces_only_a_fresh_aiortc_buffer():
    class Receiver:
        _RTCRtpReceiver__jitter_buffer = JitterBuffer(512, is_video=True)
    fresh = Receiver()
    assert reassemble_in(fresh) is True and isinstance(fresh._RTCRtpReceiver__jitter_buffer, FrameReassembly)
    busy = Receiver()
    busy._RTCRtpReceiver__jitter_buffer = JitterBuffer(512, is_video=True)
    busy._RTCRtpReceiver__jitter_buffer.add(_packets([1])[0])
    assert reassemble_in(busy) is False and isinstance(busy._RTCRtpReceiver__jitter_buffer, JitterBuffer)
    assert reassemble_in(object()) is False
    with pytest.raises(ValueError, match="power of two"):
        FrameReassembly(1000)
