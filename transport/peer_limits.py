"""Limits on what a WebRTC peer can make this side do, where aiortc sets none.

**Retransmissions.** aiortc's video sender answers every sequence number of an RTCP NACK by sending that packet
again, as often as it is asked. One NACK item of four bytes names 17 packets, and items may repeat, so a client
could make the server send its RTP history again many times over per datagram (pylibsrtp bounds an SRTCP datagram
at 1,500 bytes): 20 datagrams of 1.2 kB made it send 102,002 packets (about 120 MB) in 1-2 s
(``/tmp/p61/nack_flood.py``), on the event loop that serves every other session too. The client is authenticated by
then (ICE and DTLS), so this is one session's client harming the others, not a reflection.
:func:`limit_retransmissions` bounds it per session with a :class:`RetransmitBudget`: a packet is sent again at most
once per :data:`RESEND_INTERVAL_S`, and at most :data:`RESEND_PACKETS_PER_S` packets a second (bursts up to
:data:`RESEND_BURST`).

**SCTP's receive buffer.** aiortc's SCTP association advertises a receive window of 1 MiB but stores every DATA
chunk it gets, past the window too, until its message is complete: a peer that sends the first fragments of a
message that never ends, or chunks whose sequence numbers run ahead of a gap, makes it hold whatever it sends (20 MB
sent that way left the server holding 4.1 MB and a window of -3.0 MB after 2 s, ``/tmp/p61/sctp_flood.py``), and
each chunk ahead of a gap also sorts the set of all of them. :func:`limit_sctp_receive` drops, unacknowledged (so a
sender that keeps to the window sends it again), a chunk with no data, one that would overflow the window, and one
ahead of a gap once :data:`SCTP_MAX_MISORDERED` chunks are. Both sides of quadcast's WebRTC use it.

Each sets a private attribute of aiortc's, as the client's jitter buffer does
(:mod:`quadcast.transport.rtp_reassembly`); tests check that they are found.
"""
from __future__ import annotations

import logging
import time
from typing import Awaitable, Callable

__all__ = ["RESEND_INTERVAL_S", "RESEND_PACKETS_PER_S", "RESEND_BURST", "RetransmitBudget",
           "limit_retransmissions", "SCTP_MAX_MISORDERED", "limit_sctp_receive", "is_power_of_two"]

log = logging.getLogger("quadcast.webrtc")

RESEND_INTERVAL_S = 0.05
"""A packet is sent again at most once in this time, however often it is asked for (aiortc's receiver asks for
every missing packet again each time it finds a new gap)."""

RESEND_PACKETS_PER_S = 2048
"""Packets a session may have sent again per second on average: a 1920x1080 stream of 10 frames a second of 1,000
packets each at 20% loss."""

RESEND_BURST = 4096
"""Packets a session may have sent again at once: the whole RTP history (a reference frame the kernel dropped)."""

SCTP_MAX_MISORDERED = 1024
"""DATA chunks an SCTP association holds ahead of a gap (a window of 1 MiB holds about 900 full ones)."""


def is_power_of_two(count: int) -> bool:
    """Whether to log the ``count``-th time something happened: 1, 2, 4, 8, ... (a trace, not a flood of lines)."""
    return count & (count - 1) == 0


class RetransmitBudget:
    """Stands in for an aiortc ``RTCRtpSender._retransmit``: passes ``retransmit(seq)`` on unless ``seq`` went out
    again within ``interval_s`` or the token bucket (``per_s``, up to ``burst``) is empty; ``refused`` counts the
    rest."""

    def __init__(self, retransmit: Callable[[int], Awaitable[None]], per_s: float = RESEND_PACKETS_PER_S,
                 burst: float = RESEND_BURST, interval_s: float = RESEND_INTERVAL_S,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.retransmit = retransmit
        self.per_s, self.burst, self.interval_s, self.clock = per_s, burst, interval_s, clock
        self.tokens = float(burst)
        self.passed = self.refused = 0
        self._refilled = clock()
        self._sent: dict[int, float] = {}       # sequence number -> when it last went out again

    async def __call__(self, sequence_number: int) -> None:
        now = self.clock()
        self.tokens = min(self.burst, self.tokens + (now - self._refilled) * self.per_s)
        self._refilled = now
        last = self._sent.get(sequence_number)
        if self.tokens < 1.0 or (last is not None and now - last < self.interval_s):
            self.refused += 1
            if is_power_of_two(self.refused):
                log.info("webrtc: %d retransmissions refused (budget %.0f packets/s, one per %.2f s a packet)",
                         self.refused, self.per_s, self.interval_s)
            return
        self.tokens -= 1.0
        self.passed += 1
        self._sent[sequence_number] = now
        if len(self._sent) > 2 * self.burst:    # bounded: forget what is past the interval
            self._sent = {s: t for s, t in self._sent.items() if now - t < self.interval_s}
        await self.retransmit(sequence_number)


def limit_retransmissions(sender) -> bool:
    """Put a :class:`RetransmitBudget` in front of aiortc ``sender``'s retransmissions. False (nothing changed)
    where this aiortc's sender has no ``_retransmit``, or has one already."""
    retransmit = getattr(sender, "_retransmit", None)
    if not callable(retransmit) or isinstance(retransmit, RetransmitBudget):
        return False
    sender._retransmit = RetransmitBudget(retransmit)
    return True


_SCTP_STATE = ("_advertised_rwnd", "_sack_misordered", "_last_received_tsn")


def limit_sctp_receive(sctp) -> bool:
    """Put the receive limits (see the module docstring) in front of aiortc SCTP association ``sctp``'s DATA chunk
    handling. False (nothing changed) where this aiortc's association lacks what they read, or has them already."""
    receive = getattr(sctp, "_receive_data_chunk", None)
    if not callable(receive) or hasattr(receive, "dropped") or not all(hasattr(sctp, a) for a in _SCTP_STATE):
        return False
    dropped = [0]

    async def limited(chunk) -> None:
        size = len(getattr(chunk, "user_data", b""))
        next_tsn = (sctp._last_received_tsn + 1) & 0xFFFFFFFF
        if (size == 0 or size > sctp._advertised_rwnd
                or (chunk.tsn != next_tsn and len(sctp._sack_misordered) >= SCTP_MAX_MISORDERED)):
            dropped[0] += 1
            if is_power_of_two(dropped[0]):
                log.info("webrtc: %d SCTP DATA chunks dropped (the last %d bytes; receive window %d bytes, %d "
                         "chunks held past a gap)", dropped[0], size, sctp._advertised_rwnd,
                         len(sctp._sack_misordered))
            return
        await receive(chunk)
    limited.dropped = dropped
    sctp._receive_data_chunk = limited
    return True
