"""The live quadcast wire protocol, sans-I/O (h11 / aioquic style): typed messages and a byte-stream decoder.

Nothing here touches sockets: :func:`encode_message` turns a message into bytes to write, and a
:class:`MessageDecoder` turns whatever bytes arrived (in any chunking) back into messages.

Framing (all little-endian)::

    u32 length      # bytes that follow: 1 (type) + len(body); 1 <= length <= max_message_bytes
    u8  type        # MessageType
    ... body        # struct-packed fields; a string is u16 byte length + utf-8

Bodies, per type:

=================  ===  ==========================================================================
message            id   body
=================  ===  ==========================================================================
Hello              1    version u16, width u32, height u32, fovy_deg f64, method str, token str
Welcome            2    session_id u64, server_hz f64
PoseUpdate         3    seq u64, t_client f64, position 3 x f64, quat 4 x f64 (xyzw)[, gaze 2 x f64 (x_deg,
                        y_deg) -- only when the client tracks it]; bounded, see below
Frame              4    the rest of the message: an encoded :class:`quadcast.protocol.frame.FramePayload`
ReferenceRequest   5    reason str
ErrorMessage       6    code u16, text str[, retry_after_ms u32 -- only when non-zero (ErrorCode.BUSY)]
Bye                7    (empty)
ReceiveReport      8    count u16, then per frame: frame_id u32, bytes u32, t_arrive f64 (client clock, s)
=================  ===  ==========================================================================

A PoseUpdate is accepted only if it can be rendered (:mod:`quadcast.protocol.pose`): coordinates within
+-1e5 m, a quaternion whose norm is in [1e-3, 1e3], a time within +-1e10 s, a gaze (where the viewer looks: its
angles from the view axis, to the right and up) within +-89 degrees; anything else is a ProtocolError naming the
field. A PoseUpdate without a gaze is the one a client that does not track the eyes sends (the browser viewer, unless
its gaze follows the pointer).

Typical session: client sends ``Hello``; server answers ``Welcome`` (or ``ErrorMessage`` and closes); then the
client streams ``PoseUpdate`` s and the server ``Frame`` s; a client that lost its reference state sends
``ReferenceRequest``; either side ends with ``Bye``. A client may report when each frame arrived and how big it was
(``ReceiveReport``, on the clock its poses carry): the server's rate controller estimates the link from them
(:mod:`quadcast.protocol.rate`); a server may ignore them and a client need not send them (the Python client and
the browser viewer do).

Example::

    >>> dec = MessageDecoder()
    >>> wire = encode_message(Welcome(session_id=7, server_hz=30.0)) + encode_message(Bye())
    >>> dec.feed(wire[:3]), dec.feed(wire[3:])
    ([], [Welcome(session_id=7, server_hz=30.0), Bye()])
"""
from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass
from typing import Union

import numpy as np

from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import DEFAULT_MAX_FRAME_BYTES, FramePayload, decode_frame_payload, encode_frame_payload
from quadcast.protocol.pose import check_gaze, check_position, check_quat, check_time

__all__ = [
    "PROTOCOL_VERSION",
    "DEFAULT_MAX_MESSAGE_BYTES",
    "LENGTH_PREFIX",
    "MAX_STRING_BYTES",
    "MessageType",
    "ErrorCode",
    "Hello",
    "Welcome",
    "PoseUpdate",
    "Frame",
    "ReferenceRequest",
    "ErrorMessage",
    "Bye",
    "ReceiveReport",
    "Message",
    "encode_message",
    "decode_message_body",
    "MessageSplitter",
    "MessageDecoder",
]

PROTOCOL_VERSION = 1
"""The version a client puts in :class:`Hello` (the decoder accepts any; the server decides)."""

DEFAULT_MAX_MESSAGE_BYTES = 64 * 1024 * 1024
"""Default cap on a message's length field (type byte + body)."""

LENGTH_PREFIX = struct.Struct("<I")
"""The u32 little-endian length that starts every message."""

MAX_STRING_BYTES = 0xFFFF
"""Largest utf-8 encoding of a string field (u16 length prefix)."""

_U16_MAX, _U32_MAX, _U64_MAX = 0xFFFF, 0xFFFF_FFFF, 0xFFFF_FFFF_FFFF_FFFF


class MessageType(enum.IntEnum):
    """The u8 type code after the length prefix."""

    HELLO = 1
    WELCOME = 2
    POSE_UPDATE = 3
    FRAME = 4
    REFERENCE_REQUEST = 5
    ERROR = 6
    BYE = 7
    RECEIVE_REPORT = 8


class ErrorCode(enum.IntEnum):
    """Well-known :class:`ErrorMessage` codes (any u16 is allowed on the wire)."""

    PROTOCOL = 1             # a message did not parse / was unexpected
    UNSUPPORTED_VERSION = 2  # Hello.version not supported
    UNKNOWN_METHOD = 3       # Hello.method not served
    BAD_REQUEST = 4          # e.g. a resolution the server cannot render
    UNAUTHORIZED = 5         # Hello.token rejected
    INTERNAL = 6             # server-side failure
    BUSY = 7                 # no room now (sessions or connections): try again after ErrorMessage.retry_after_s
    TIMEOUT = 8              # no Hello in time, or no pose traffic for the idle timeout


# --------------------------------------------------------------------------
# Field validation (ValueError naming the field; the decoder re-raises it as ProtocolError)
# --------------------------------------------------------------------------


def _check_int(name: str, value, max_value: int, min_value: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    value = int(value)
    if not (min_value <= value <= max_value):
        raise ValueError(f"{name}: expected {min_value}..{max_value}, got {value}")
    return value


def _check_float(name: str, value, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name}: expected a real number, got {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise ValueError(f"{name}: expected a finite number, got {value!r}")
    if positive and value <= 0.0:
        raise ValueError(f"{name}: expected > 0, got {value!r}")
    return value


def _check_str(name: str, value) -> str:
    if not isinstance(value, str):
        raise ValueError(f"{name}: expected a str, got {type(value).__name__}")
    try:
        n = len(value.encode("utf-8"))
    except UnicodeEncodeError as exc:  # lone surrogates
        raise ValueError(f"{name}: not encodable as utf-8 ({exc.reason})") from None
    if n > MAX_STRING_BYTES:
        raise ValueError(f"{name}: {n} utf-8 bytes exceeds the limit of {MAX_STRING_BYTES}")
    return value


# --------------------------------------------------------------------------
# Messages
# --------------------------------------------------------------------------


@dataclass(frozen=True)
class Hello:
    """Client -> server, first message: protocol version, streaming method name, viewport and field of view."""

    version: int
    method: str
    width: int
    height: int
    fovy_deg: float
    token: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "version", _check_int("Hello.version", self.version, _U16_MAX))
        object.__setattr__(self, "method", _check_str("Hello.method", self.method))
        object.__setattr__(self, "width", _check_int("Hello.width", self.width, _U32_MAX, 1))
        object.__setattr__(self, "height", _check_int("Hello.height", self.height, _U32_MAX, 1))
        fovy = _check_float("Hello.fovy_deg", self.fovy_deg)
        if not (0.0 < fovy < 180.0):
            raise ValueError(f"Hello.fovy_deg: expected 0 < fovy_deg < 180, got {fovy!r}")
        object.__setattr__(self, "fovy_deg", fovy)
        object.__setattr__(self, "token", _check_str("Hello.token", self.token))


@dataclass(frozen=True)
class Welcome:
    """Server -> client answer to :class:`Hello`: the session id and the server's frame rate (Hz)."""

    session_id: int
    server_hz: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "session_id", _check_int("Welcome.session_id", self.session_id, _U64_MAX))
        object.__setattr__(self, "server_hz", _check_float("Welcome.server_hz", self.server_hz, positive=True))


@dataclass(frozen=True, eq=False)
class PoseUpdate:
    """Client -> server: the client's head pose (world position, xyzw quaternion) at client time ``t_client`` (s),
    and where the viewer looked then (``gaze``: degrees from the view axis, to the right and up; None: not tracked).

    ``position`` and ``quat`` are read-only float64 arrays of shape (3,) and (4,); the quaternion is sent as given
    (not normalized). All are bounded so that any accepted pose renders (:mod:`quadcast.protocol.pose`).
    """

    seq: int
    t_client: float
    position: np.ndarray
    quat: np.ndarray
    gaze: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "seq", _check_int("PoseUpdate.seq", self.seq, _U64_MAX))
        object.__setattr__(self, "t_client", check_time("PoseUpdate.t_client", self.t_client))
        object.__setattr__(self, "position", check_position("PoseUpdate.position", self.position))
        object.__setattr__(self, "quat", check_quat("PoseUpdate.quat", self.quat))
        if self.gaze is not None:
            object.__setattr__(self, "gaze", check_gaze("PoseUpdate.gaze", self.gaze))

    @classmethod
    def from_pose(cls, seq: int, t_client: float, pose, gaze=None) -> "PoseUpdate":
        """Build from anything with ``.position`` (3,) and ``.quat`` (4,) (e.g. :class:`quadcast.render.camera.Pose`)."""
        return cls(seq, t_client, pose.position, pose.quat, gaze)

    def __eq__(self, other) -> bool:
        if not isinstance(other, PoseUpdate):
            return NotImplemented
        return (self.seq == other.seq and self.t_client == other.t_client and self.gaze == other.gaze
                and np.array_equal(self.position, other.position) and np.array_equal(self.quat, other.quat))

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True)
class Frame:
    """Server -> client: one encoded :class:`quadcast.protocol.frame.FramePayload` (opaque bytes at this layer)."""

    payload: bytes

    def __post_init__(self) -> None:
        if not isinstance(self.payload, (bytes, bytearray, memoryview)):
            raise ValueError(f"Frame.payload: expected bytes, got {type(self.payload).__name__}")
        object.__setattr__(self, "payload", bytes(self.payload))

    @classmethod
    def from_payload(cls, payload: FramePayload) -> "Frame":
        """Wrap a :class:`FramePayload` (encoded with :func:`quadcast.protocol.frame.encode_frame_payload`)."""
        return cls(encode_frame_payload(payload))

    def decode(self, max_bytes: int = DEFAULT_MAX_FRAME_BYTES) -> FramePayload:
        """Parse the payload; a malformed one raises :class:`ProtocolError`."""
        return decode_frame_payload(self.payload, max_bytes=max_bytes)

    def __repr__(self) -> str:  # payloads are large: don't dump them
        return f"Frame(payload=<{len(self.payload)} bytes>)"


@dataclass(frozen=True)
class ReferenceRequest:
    """Client -> server: the client lost its reference state (``reason`` says why); send a self-contained frame."""

    reason: str = ""

    def __post_init__(self) -> None:
        object.__setattr__(self, "reason", _check_str("ReferenceRequest.reason", self.reason))


@dataclass(frozen=True)
class ErrorMessage:
    """Either direction: a fatal error (``code``: an :class:`ErrorCode` or any u16) before the sender closes.

    ``retry_after_s`` (with :attr:`ErrorCode.BUSY`): when to try again, in seconds (whole milliseconds on the wire;
    0 = not said, and then the field is not sent)."""

    code: int
    text: str = ""
    retry_after_s: float = 0.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "code", _check_int("ErrorMessage.code", self.code, _U16_MAX))
        object.__setattr__(self, "text", _check_str("ErrorMessage.text", self.text))
        after = _check_float("ErrorMessage.retry_after_s", self.retry_after_s)
        if not 0.0 <= after <= _U32_MAX / 1e3:
            raise ValueError(f"ErrorMessage.retry_after_s: expected 0..{_U32_MAX / 1e3:g} s, got {after!r}")
        object.__setattr__(self, "retry_after_s", round(after * 1e3) / 1e3)


@dataclass(frozen=True)
class Bye:
    """Either direction: orderly end of the session."""


MAX_REPORT_ENTRIES = 256
"""Most frames one :class:`ReceiveReport` may describe."""


@dataclass(frozen=True)
class ReceiveReport:
    """Client -> server: frames that arrived, as ``(frame_id, bytes, t_arrive)`` entries -- the frame's id, the
    size of its payload (the Frame message's body) and when its last byte arrived, on the client's clock (the one
    :class:`PoseUpdate` times are on). At most :data:`MAX_REPORT_ENTRIES` entries."""

    entries: tuple

    def __post_init__(self) -> None:
        entries = self.entries
        if not isinstance(entries, (tuple, list)):
            raise ValueError(f"ReceiveReport.entries: expected a sequence, got {type(entries).__name__}")
        if len(entries) > MAX_REPORT_ENTRIES:
            raise ValueError(f"ReceiveReport.entries: {len(entries)} entries, at most {MAX_REPORT_ENTRIES}")
        out = []
        for i, e in enumerate(entries):
            if not isinstance(e, (tuple, list)) or len(e) != 3:
                raise ValueError(f"ReceiveReport.entries[{i}]: expected (frame_id, bytes, t_arrive), got {e!r}")
            out.append((_check_int(f"ReceiveReport.entries[{i}].frame_id", e[0], _U32_MAX),
                        _check_int(f"ReceiveReport.entries[{i}].bytes", e[1], _U32_MAX),
                        check_time(f"ReceiveReport.entries[{i}].t_arrive", e[2])))
        object.__setattr__(self, "entries", tuple(out))


Message = Union[Hello, Welcome, PoseUpdate, Frame, ReferenceRequest, ErrorMessage, Bye, ReceiveReport]

_TYPE_OF = {Hello: MessageType.HELLO, Welcome: MessageType.WELCOME, PoseUpdate: MessageType.POSE_UPDATE,
            Frame: MessageType.FRAME, ReferenceRequest: MessageType.REFERENCE_REQUEST,
            ErrorMessage: MessageType.ERROR, Bye: MessageType.BYE, ReceiveReport: MessageType.RECEIVE_REPORT}

_NAME_OF = {t: cls.__name__ for cls, t in _TYPE_OF.items()}

# --------------------------------------------------------------------------
# Encoding
# --------------------------------------------------------------------------

_HELLO = struct.Struct("<HIId")
_WELCOME = struct.Struct("<Qd")
_POSE = struct.Struct("<Qd3d4d")
_GAZE = struct.Struct("<2d")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_REPORT_ENTRY = struct.Struct("<IId")


def _pack_str(s: str) -> bytes:
    b = s.encode("utf-8")
    return _U16.pack(len(b)) + b


def _body(msg: Message) -> bytes:
    if isinstance(msg, Hello):
        return (_HELLO.pack(msg.version, msg.width, msg.height, msg.fovy_deg)
                + _pack_str(msg.method) + _pack_str(msg.token))
    if isinstance(msg, Welcome):
        return _WELCOME.pack(msg.session_id, msg.server_hz)
    if isinstance(msg, PoseUpdate):
        body = _POSE.pack(msg.seq, msg.t_client, *msg.position.tolist(), *msg.quat.tolist())
        return body if msg.gaze is None else body + _GAZE.pack(*msg.gaze)
    if isinstance(msg, Frame):
        return msg.payload
    if isinstance(msg, ReferenceRequest):
        return _pack_str(msg.reason)
    if isinstance(msg, ErrorMessage):
        after = _U32.pack(round(msg.retry_after_s * 1e3)) if msg.retry_after_s > 0 else b""
        return _U16.pack(msg.code) + _pack_str(msg.text) + after
    if isinstance(msg, ReceiveReport):
        return _U16.pack(len(msg.entries)) + b"".join(_REPORT_ENTRY.pack(*e) for e in msg.entries)
    return b""  # Bye


def encode_message(msg: Message) -> bytes:
    """The wire bytes of one message: u32 length + u8 type + body."""
    mtype = _TYPE_OF.get(type(msg))
    if mtype is None:
        raise TypeError(f"encode_message: expected one of {', '.join(t.__name__ for t in _TYPE_OF)}, "
                        f"got {type(msg).__name__}")
    body = _body(msg)
    length = 1 + len(body)
    if length > _U32_MAX:
        raise ValueError(f"encode_message: {type(msg).__name__} body of {len(body)} bytes does not fit a u32 length")
    return b"".join((LENGTH_PREFIX.pack(length), bytes((mtype,)), body))


# --------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------


class _BodyReader:
    """Reads fields off one message body; every defect is a ProtocolError naming the message and field."""

    def __init__(self, name: str, body: memoryview) -> None:
        self.name, self.body, self.pos = name, body, 0

    def unpack(self, fmt: struct.Struct, field: str) -> tuple:
        if self.pos + fmt.size > len(self.body):
            raise ProtocolError(f"{self.name}: body truncated reading {field} "
                                f"(needs {fmt.size} bytes at offset {self.pos}, body has {len(self.body)})")
        values = fmt.unpack_from(self.body, self.pos)
        self.pos += fmt.size
        return values

    def string(self, field: str) -> str:
        (n,) = self.unpack(_U16, f"{field} length")
        if self.pos + n > len(self.body):
            raise ProtocolError(f"{self.name}: {field} says {n} bytes, only {len(self.body) - self.pos} remain")
        raw = bytes(self.body[self.pos:self.pos + n])
        self.pos += n
        try:
            return raw.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise ProtocolError(f"{self.name}.{field}: invalid utf-8 at byte {exc.start}") from None

    def rest(self) -> bytes:
        out = bytes(self.body[self.pos:])
        self.pos = len(self.body)
        return out

    def end(self) -> None:
        if self.pos != len(self.body):
            raise ProtocolError(f"{self.name}: {len(self.body) - self.pos} unexpected trailing bytes "
                                f"(body is {len(self.body)} bytes, expected {self.pos})")


def decode_message_body(mtype: int, body: bytes | memoryview) -> Message:
    """Parse one message given its type code and body (the bytes after the type byte).

    Raises :class:`ProtocolError` for an unknown type, a wrong body size, bad utf-8, a non-finite float,
    a zero quaternion or any other invalid field, and for nothing else.
    """
    try:
        t = MessageType(mtype)
    except ValueError:
        raise ProtocolError(f"message type: unknown code {mtype} (known: "
                            f"{', '.join(f'{m.value}={m.name}' for m in MessageType)})") from None
    r = _BodyReader(_NAME_OF[t], memoryview(body))
    try:
        if t is MessageType.HELLO:
            version, width, height, fovy = r.unpack(_HELLO, "version/width/height/fovy_deg")
            method, token = r.string("method"), r.string("token")
            r.end()
            return Hello(version, method, width, height, fovy, token)
        if t is MessageType.WELCOME:
            session_id, hz = r.unpack(_WELCOME, "session_id/server_hz")
            r.end()
            return Welcome(session_id, hz)
        if t is MessageType.POSE_UPDATE:
            seq, t_client, *v = r.unpack(_POSE, "seq/t_client/position/quat")
            gaze = r.unpack(_GAZE, "gaze") if r.pos < len(r.body) else None
            r.end()
            return PoseUpdate(seq, t_client, v[:3], v[3:], gaze)
        if t is MessageType.FRAME:
            return Frame(r.rest())
        if t is MessageType.REFERENCE_REQUEST:
            reason = r.string("reason")
            r.end()
            return ReferenceRequest(reason)
        if t is MessageType.ERROR:
            (code,) = r.unpack(_U16, "code")
            text = r.string("text")
            after_ms = r.unpack(_U32, "retry_after_ms")[0] if r.pos < len(r.body) else None
            r.end()
            if after_ms == 0:
                raise ProtocolError("ErrorMessage.retry_after_ms: 0 is said by leaving the field out")
            return ErrorMessage(code, text, (after_ms or 0) / 1e3)
        if t is MessageType.RECEIVE_REPORT:
            (count,) = r.unpack(_U16, "count")
            if count > MAX_REPORT_ENTRIES:
                raise ProtocolError(f"ReceiveReport.count: {count} entries, at most {MAX_REPORT_ENTRIES}")
            entries = tuple(r.unpack(_REPORT_ENTRY, f"entries[{i}]") for i in range(count))
            r.end()
            return ReceiveReport(entries)
        r.end()
        return Bye()
    except ProtocolError:
        raise
    except ValueError as exc:  # a field validator of the dataclass
        raise ProtocolError(str(exc)) from None


class MessageSplitter:
    """Splits a byte stream into whole framed messages without parsing their bodies (what a proxy needs).

    :meth:`feed` returns each complete message's wire bytes (length prefix included). It checks only the framing:
    a length of 0 or above ``max_message_bytes`` raises :class:`ProtocolError`, *before* any of that message's
    body is buffered, so at most ``4 + max_message_bytes`` bytes are ever held. After an error the splitter is
    :attr:`failed` and refuses further input (the connection is to be closed).
    """

    def __init__(self, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> None:
        self.max_message_bytes = _check_int("max_message_bytes", max_message_bytes, _U32_MAX, 1)
        self._buf = bytearray()   # the current message: prefix + as much of the rest as has arrived
        self._need = 0            # total wire size of the current message, 0 while its prefix is incomplete
        self._failed: ProtocolError | None = None

    @property
    def failed(self) -> bool:
        """True once a framing error was raised; the splitter then rejects all input."""
        return self._failed is not None

    @property
    def buffered(self) -> int:
        """Bytes of an incomplete message currently held."""
        return len(self._buf)

    def _fail(self, exc: ProtocolError) -> ProtocolError:
        self._failed = exc
        self._buf = bytearray()
        return exc

    def feed_raw(self, data: bytes | bytearray | memoryview) -> list[bytes]:
        """Consume ``data``; return the complete messages' wire bytes, in order."""
        if self._failed is not None:
            raise ProtocolError(f"stream already failed ({self._failed}); no more input accepted")
        view = memoryview(data).cast("B")
        out: list[bytes] = []
        pos, n = 0, len(view)
        while pos < n:
            if self._need == 0:
                take = min(LENGTH_PREFIX.size - len(self._buf), n - pos)
                self._buf += view[pos:pos + take]
                pos += take
                if len(self._buf) < LENGTH_PREFIX.size:
                    break
                (length,) = LENGTH_PREFIX.unpack(self._buf)
                if length == 0:
                    raise self._fail(ProtocolError("message length: 0, expected at least 1 (the type byte)"))
                if length > self.max_message_bytes:
                    raise self._fail(ProtocolError(
                        f"message length: {length} bytes exceeds the cap of {self.max_message_bytes}"))
                self._need = LENGTH_PREFIX.size + length
            take = min(self._need - len(self._buf), n - pos)
            self._buf += view[pos:pos + take]
            pos += take
            if len(self._buf) == self._need:
                out.append(bytes(self._buf))
                self._buf, self._need = bytearray(), 0
        return out

    feed = feed_raw


class MessageDecoder:
    """Incremental decoder: bytes in (any chunking, even one byte at a time), typed messages out.

    ``feed(data)`` returns the messages completed by ``data``, in order. Any defect (length of 0 or above
    ``max_message_bytes`` -- checked before the body is buffered --, unknown type, malformed body) raises
    :class:`ProtocolError` naming it and makes the decoder :attr:`failed`: every later ``feed`` raises too,
    as the connection is to be closed. Messages completed earlier in the same ``feed`` call are discarded then.
    """

    def __init__(self, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES) -> None:
        self._splitter = MessageSplitter(max_message_bytes)
        self._failed: ProtocolError | None = None

    @property
    def max_message_bytes(self) -> int:
        return self._splitter.max_message_bytes

    @property
    def failed(self) -> bool:
        """True once :meth:`feed` raised; the decoder then rejects all input."""
        return self._failed is not None

    @property
    def buffered(self) -> int:
        """Bytes of an incomplete message currently held."""
        return self._splitter.buffered

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message]:
        if self._failed is not None:
            raise ProtocolError(f"decoder already failed ({self._failed}); no more input accepted")
        try:
            out = []
            for raw in self._splitter.feed_raw(data):
                view = memoryview(raw)
                out.append(decode_message_body(view[LENGTH_PREFIX.size], view[LENGTH_PREFIX.size + 1:]))
            return out
        except ProtocolError as exc:
            self._failed = exc
            raise
