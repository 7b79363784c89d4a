"""Access units from RTP packets, for frames larger than aiortc's receiver can hold.

aiortc's video receiver puts every RTP packet into a ``JitterBuffer`` of 512 packets, which hands out an access unit
(the packets of one RTP timestamp, in sequence order) once a packet of a newer timestamp follows it without a gap.
Two things about it do not fit quadcast's frames:

- **Size.** A frame of more than 512 packets (about 600 kB: a 1920x1080 reference frame with its quads) overflows
  the buffer, which then drops the frame's first packets and hands out the rest: the frame is lost, every time.
- **Time.** On every packet it scans the buffer from its oldest packet, so a frame of n packets costs n²/2 steps
  on the client's event loop: 4-5 ms a 960x540 frame of 300 packets, 74 ms one of 1,300.

:class:`FrameReassembly` makes the same decisions in the same order (a differential test feeds both the same
packets), holds :data:`REASSEMBLY_PACKETS` packets, and remembers how far it has scanned. It also gives up on a frame
that a lost packet has blocked for :data:`GIVE_UP_S` while newer packets arrive (aiortc's waits until the buffer
overflows, which at this size would hold back seconds of frames): the frame is dropped and a picture loss is
reported, as aiortc does on an overflow. :func:`reassemble_in` puts one in place of a receiver's buffer; like the
access unit tap (:mod:`quadcast.transport.webrtc`) it sets a private attribute of aiortc's, and a test checks that
it is found.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

__all__ = ["REASSEMBLY_PACKETS", "GIVE_UP_S", "MAX_MISORDER", "ReassembledFrame", "FrameReassembly",
           "reassemble_in"]

log = logging.getLogger("quadcast.webrtc")

REASSEMBLY_PACKETS = 4096
"""Packets held (a power of two): a frame of up to about 4.9 MB at aiortc's 1,200-byte packets."""

GIVE_UP_S = 0.5
"""How long a frame may wait for a lost packet while newer packets arrive (a retransmission after a NACK takes a
round trip) before it is dropped."""

MAX_MISORDER = 100
"""A packet up to this many sequence numbers older than the oldest held is late and ignored; an older one means the
sender started again, and everything held is dropped (aiortc's rule)."""


@dataclass
class ReassembledFrame:
    """One access unit: what aiortc's receiver reads from its buffer (``data``; ``timestamp``, which it rewrites)."""
    data: bytes
    timestamp: int


class FrameReassembly:
    """Access units from an H.264 track's RTP packets (see the module docstring); ``add`` is aiortc's
    ``JitterBuffer.add``: a packet (``sequence_number``, ``timestamp``, and its depayloaded bytes in ``_data``) in,
    ``(picture_lost, frame or None)`` out."""

    def __init__(self, capacity: int = REASSEMBLY_PACKETS, give_up_s: float | None = GIVE_UP_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        if capacity <= 0 or capacity & (capacity - 1):
            raise ValueError(f"capacity must be a power of two, not {capacity}")
        self.capacity = capacity
        self.give_up_s = give_up_s
        self.clock = clock
        self.frames_abandoned = 0
        self._slots: list = [None] * capacity
        self._origin: int | None = None       # sequence number of the oldest slot
        self._scanned = 0                     # slots from the origin known to hold packets of _scan_ts, no gap
        self._scan_ts: int | None = None
        self._blocked: tuple[int, float] | None = None   # (origin, since when) while a gap holds the origin's frame

    # -- aiortc's JitterBuffer interface

    def add(self, packet) -> tuple[bool, ReassembledFrame | None]:
        seq = packet.sequence_number
        lost = False
        if self._origin is None:
            self._origin = seq
        delta = (seq - self._origin) & 0xFFFF
        misorder = (self._origin - seq) & 0xFFFF
        if misorder < delta:                  # older than the oldest slot
            if misorder < MAX_MISORDER:
                return False, None            # late: its frame went out or was dropped
            self.remove(self.capacity)        # the sender started again
            self._origin, delta, lost = seq, 0, True
        if delta >= self.capacity:
            if self.smart_remove(delta - self.capacity + 1):
                self._origin = seq
            delta = (seq - self._origin) & 0xFFFF
            lost = True
        if delta < self._scanned:             # a duplicate inside what was scanned: scan it again
            self._scanned, self._scan_ts = 0, None
        self._slots[seq % self.capacity] = packet
        frame = self._take_frame()
        if frame is None and self._give_up(delta):
            lost = True
            frame = self._take_frame()
        return lost, frame

    def remove(self, count: int) -> None:
        """Drop ``count`` slots from the oldest."""
        for _ in range(min(count, self.capacity)):
            self._slots[self._origin % self.capacity] = None
            self._origin = (self._origin + 1) & 0xFFFF
        self._moved()

    def smart_remove(self, count: int) -> bool:
        """Drop at least ``count`` slots from the oldest, and on to the start of a frame; True if that emptied every
        slot (aiortc's rule, so that no frame is handed out without its start)."""
        timestamp = None
        try:
            for i in range(self.capacity):
                pos = self._origin % self.capacity
                packet = self._slots[pos]
                if packet is not None:
                    if i >= count and timestamp != packet.timestamp:
                        return False
                    timestamp = packet.timestamp
                self._slots[pos] = None
                self._origin = (self._origin + 1) & 0xFFFF
            return True
        finally:
            self._moved()

    # -- the scan

    def _moved(self) -> None:
        self._scanned, self._scan_ts = 0, None

    def _take_frame(self) -> ReassembledFrame | None:
        """The oldest frame, if a packet of a newer one follows it without a gap (scanning on from where the last
        call stopped)."""
        cap, slots = self.capacity, self._slots
        while self._scanned < cap:
            packet = slots[(self._origin + self._scanned) % cap]
            if packet is None:
                return None
            if self._scan_ts is None:
                self._scan_ts = packet.timestamp
            elif packet.timestamp != self._scan_ts:
                count, first = self._scanned, self._origin
                data = b"".join(slots[(first + i) % cap]._data for i in range(count))
                frame = ReassembledFrame(data, self._scan_ts)
                self.remove(count)
                self._blocked = None
                return frame
            self._scanned += 1
        return None

    def _give_up(self, delta: int) -> bool:
        """Whether the oldest frame, held by a gap that a packet at ``delta`` from the origin lies beyond, has
        waited past ``give_up_s``; if so its packets and the gap are dropped up to the next frame's first packet."""
        if self.give_up_s is None or delta <= self._scanned:
            return False
        now = self.clock()
        if self._blocked is None or self._blocked[0] != self._origin:
            self._blocked = (self._origin, now)
            return False
        if now - self._blocked[1] < self.give_up_s:
            return False
        cap, gap_ts = self.capacity, self._scan_ts
        for i in range(self._scanned + 1, delta + 1):   # the first packet past the gap of another frame
            packet = self._slots[(self._origin + i) % cap]
            if packet is not None and (gap_ts is None or packet.timestamp != gap_ts):
                log.info("rtp: a frame (timestamp %s) waited %.2f s for a lost packet; dropped with %d slots",
                         gap_ts, now - self._blocked[1], i)
                self.remove(i)
                self._blocked = None
                self.frames_abandoned += 1
                return True
        return False


_JITTER_BUFFER = "_RTCRtpReceiver__jitter_buffer"


def reassemble_in(receiver, reassembly: FrameReassembly | None = None) -> bool:
    """Put ``reassembly`` (a new :class:`FrameReassembly` by default) in place of aiortc video ``receiver``'s jitter
    buffer, before any packet arrived. False (nothing changed) when this aiortc's receiver has no such buffer or it
    already holds packets."""
    try:
        from aiortc.jitterbuffer import JitterBuffer
    except ImportError:  # pragma: no cover - aiortc is a dependency
        return False
    current = getattr(receiver, _JITTER_BUFFER, None)
    if type(current) is not JitterBuffer or getattr(current, "_origin", 0) is not None:
        return False
    setattr(receiver, _JITTER_BUFFER, reassembly or FrameReassembly())
    return True
