"""Who a server lets in, sans-I/O: its limits (:class:`ServerLimits`) and the bookkeeping that applies them
(:class:`Admission`). Every transport's listener asks the same :class:`Admission`, so the limits hold whatever
the client connects with (TCP, TLS, WebRTC signalling).

A connection is *pre-auth* from the moment it is accepted until its Hello is accepted (TLS handshake and Hello
included, all within ``handshake_timeout_s``); then it holds a *session* slot until it closes. The decisions:

- :meth:`Admission.open` -- a new connection from ``ip``: refused when ``max_preauth`` connections are already
  pre-auth, or ``max_per_ip`` connections (pre-auth or not) come from that address;
- :meth:`Ticket.admit` -- its Hello was accepted: refused with :attr:`ErrorCode.BUSY` and a retry-after when
  ``max_sessions`` sessions run;
- :meth:`Ticket.close` -- it ended (idempotent).

A refusal is a :class:`Refusal` (an :class:`ErrorCode`, a text naming the limit, and when to retry); the caller
tells the peer if it can and closes. The idle timeout (only pose traffic resets it) is the session core's
(:meth:`quadcast.protocol.session.ServerSession.idle_deadline`); it is configured here with the other limits.
"""
from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

from quadcast.protocol.messages import ErrorCode

__all__ = ["ServerLimits", "Refusal", "Ticket", "Admission", "AdmissionCounters"]


@dataclass(frozen=True)
class ServerLimits:
    """A server's limits, with their defaults (``quadcast server --help`` lists them)."""

    max_sessions: int = 4              # sessions running at once (each has a worker process)
    max_preauth: int = 32              # connections not yet past their Hello
    max_per_ip: int = 8                # connections from one address, whatever their state
    handshake_timeout_s: float = 10.0  # accept -> Hello accepted (TLS handshake included)
    idle_timeout_s: float = 20.0       # no pose traffic for this long ends a session
    retry_after_s: float = 5.0         # what a busy server tells a client to wait

    def __post_init__(self) -> None:
        for name in ("max_sessions", "max_preauth", "max_per_ip"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"--{name.replace('_', '-')}: expected an integer >= 1, got {v!r}")
        for name in ("handshake_timeout_s", "idle_timeout_s", "retry_after_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"--{name[:-2].replace('_', '-')}: expected a number of seconds > 0, got {v!r}")


@dataclass(frozen=True)
class Refusal:
    """Why a connection or a session was not let in: send ``ErrorMessage(code, text, retry_after_s)`` if the
    transport can, then close."""

    code: ErrorCode
    text: str
    retry_after_s: float = 0.0


@dataclass
class AdmissionCounters:
    """What an :class:`Admission` refused."""

    opened: int = 0
    refused_preauth: int = 0
    refused_per_ip: int = 0
    refused_busy: int = 0
    admitted: int = 0


class Ticket:
    """One connection's place in an :class:`Admission` (see the module docstring)."""

    def __init__(self, admission: "Admission", ip: str) -> None:
        self._admission, self.ip = admission, ip
        self.state = "preauth"          # -> "session" -> "closed", or "preauth" -> "closed"

    def admit(self) -> Refusal | None:
        """The connection's Hello was accepted: take a session slot, or be refused (server busy)."""
        return self._admission._admit(self)

    def close(self) -> None:
        """The connection ended (any state; idempotent)."""
        self._admission._close(self)


@dataclass
class Admission:
    """The live counts behind :class:`ServerLimits` (single-threaded: an event loop's)."""

    limits: ServerLimits = field(default_factory=ServerLimits)
    counters: AdmissionCounters = field(default_factory=AdmissionCounters)

    def __post_init__(self) -> None:
        self.preauth = 0
        self.sessions = 0
        self.per_ip: collections.Counter[str] = collections.Counter()

    def open(self, ip: str) -> Ticket | Refusal:
        """A connection from ``ip`` was accepted: its :class:`Ticket`, or the :class:`Refusal` to close it with."""
        lim, c = self.limits, self.counters
        c.opened += 1
        if self.preauth >= lim.max_preauth:
            c.refused_preauth += 1
            return Refusal(ErrorCode.BUSY, f"too many connections awaiting their handshake "
                                           f"({lim.max_preauth}); try again later", lim.retry_after_s)
        if self.per_ip[ip] >= lim.max_per_ip:
            c.refused_per_ip += 1
            return Refusal(ErrorCode.BUSY, f"too many connections from {ip} ({lim.max_per_ip})", lim.retry_after_s)
        self.preauth += 1
        self.per_ip[ip] += 1
        return Ticket(self, ip)

    def _admit(self, ticket: Ticket) -> Refusal | None:
        if ticket.state != "preauth":
            raise RuntimeError(f"Ticket.admit: the connection is {ticket.state}, not awaiting its handshake")
        lim = self.limits
        if self.sessions >= lim.max_sessions:
            self.counters.refused_busy += 1
            return Refusal(ErrorCode.BUSY, f"server busy ({lim.max_sessions} of {lim.max_sessions} sessions); "
                                           f"retry after {lim.retry_after_s:g} s", lim.retry_after_s)
        self.preauth -= 1
        self.sessions += 1
        self.counters.admitted += 1
        ticket.state = "session"
        return None

    def _close(self, ticket: Ticket) -> None:
        if ticket.state == "closed":
            return
        if ticket.state == "preauth":
            self.preauth -= 1
        else:
            self.sessions -= 1
        self.per_ip[ticket.ip] -= 1
        if self.per_ip[ticket.ip] <= 0:
            del self.per_ip[ticket.ip]
        ticket.state = "closed"
