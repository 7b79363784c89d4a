"""Limits on what a WebRTC client's RTCP can make the server do.

aiortc's video sender answers every sequence number of an RTCP NACK by sending that packet again, as often as it is
asked. One NACK item of four bytes names 17 packets, and items may repeat, so a client could make the server send
its RTP history again many times over per datagram (pylibsrtp bounds an SRTCP datagram at 1,500 bytes): 20
datagrams of 1.2 kB made it send 102,002 packets (about 120 MB) in 1-2 s (``/tmp/p61/nack_flood.py``), on the event
loop that serves every other session too. The client is authenticated by then (ICE and DTLS), so this is one
session's client harming the others, not a reflection.

:func:`limit_retransmissions` bounds it per session with a :class:`RetransmitBudget`: a packet is sent again at
most once per :data:`RESEND_INTERVAL_S`, and at most :data:`RESEND_PACKETS_PER_S` packets a second (bursts up to
:data:`RESEND_BURST`). Like the client's jitter buffer (:mod:`quadcast.transport.rtp_reassembly`) it sets a private
attribute of aiortc's, and a test checks that it is found.
"""
from __future__ import annotations

import logging
import time
from typing import Awaitable, Callable

__all__ = ["RESEND_INTERVAL_S", "RESEND_PACKETS_PER_S", "RESEND_BURST", "RetransmitBudget",
           "limit_retransmissions"]

log = logging.getLogger("quadcast.webrtc")

RESEND_INTERVAL_S = 0.05
"""A packet is sent again at most once in this time, however often it is asked for (aiortc's receiver asks for
every missing packet again each time it finds a new gap)."""

RESEND_PACKETS_PER_S = 2048
"""Packets a session may have sent again per second on average: a 1920x1080 stream of 10 frames a second of 1,000
packets each at 20% loss."""

RESEND_BURST = 4096
"""Packets a session may have sent again at once: the whole RTP history (a reference frame the kernel dropped)."""


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
            if self.refused & (self.refused - 1) == 0:      # 1, 2, 4, ...: a trace, not a flood of lines
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
