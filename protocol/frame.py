"""`FramePayload`: what one server frame of any method carries to the client, sans-I/O.

Every method (quasar, quadstream, meshwarp, atw) sends, per server frame, one H.264 access unit (`video`) and one
method-specific geometry blob (`geometry`: a quad blob, a compressed depth map, or empty), plus the pose and scene
time it was rendered for. `encode_frame_payload` / `decode_frame_payload` give it a validated binary form.

The header is the one place that says what a frame is: its :class:`FrameType` (a reference frame, or a residual
against the client's cached reference `reference_id`) and whether it is *self-contained* -- decodable whatever the
client received before (its video is an IDR and its geometry needs no earlier frame). The encoder that made the
frame sets the flag; clients and send queues read it, nobody parses H.264 for it. Both share one byte on the
wire: bits 0-6 the type, bit 7 the flag.

`FrameStats` holds what the server measured while making the frame (ms per stage, sizes, quad counts); it is not
sent.
"""
from __future__ import annotations

import enum
import struct
from dataclasses import dataclass, field

import numpy as np

from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.pose import check_position, check_quat, check_time

FRAME_MAGIC = b"QDCF"
FRAME_VERSION = 2
# magic, version, method, frame type | self-contained << 7, frame id, reference id, t, position (3 f8), quat (4 f8),
# video len, geometry len
_HEADER = struct.Struct("<4sHBBIId3d4dII")
DEFAULT_MAX_FRAME_BYTES = 64 * 1024 * 1024


class Method(enum.IntEnum):
    QUASAR = 0
    QUADSTREAM = 1
    MESHWARP = 2
    ATW = 3


_SELF_CONTAINED = 0x80


class FrameType(enum.IntEnum):
    """What a frame's geometry is (every frame of the baselines is a reference frame)."""

    REFERENCE = 0  # stands alone: replaces the client's cached state
    RESIDUAL = 1   # an update of the client's cached reference frame `reference_id`


@dataclass
class FrameStats:
    """What the server measured while making one frame (not sent)."""

    ms: dict[str, float] = field(default_factory=dict)   # wall-clock ms per pipeline stage
    quads: int = 0                                         # quad methods: quads in all layers
    quads_per_layer: dict[str, int] = field(default_factory=dict)
    offsets: int = 0                                       # rows of depth offsets (non-flattened quads)
    bits_per_quad_raw: float = 0.0                         # packed bits per quad before zstd, offsets excluded
    cache_quads: int = 0                                   # quasar: quads in the server's copy of the client cache


@dataclass
class FramePayload:
    method: Method
    frame_id: int
    frame_type: FrameType
    reference_id: int
    t: float                  # scene time (s) the frame was rendered at
    position: np.ndarray      # (3,) render pose
    quat: np.ndarray          # (4,) xyzw
    video: bytes
    geometry: bytes = b""
    self_contained: bool = False
    stats: FrameStats = field(default_factory=FrameStats)   # server-side figures; not sent

    @property
    def size_bytes(self) -> int:
        return _HEADER.size + len(self.video) + len(self.geometry)


def residual_to_reference_bytes(frames) -> float | None:
    """Mean bytes of a residual frame over mean bytes of a reference frame, from ``(FrameType, bytes)`` pairs
    (QUASAR §4: residual frames are 2-3x smaller); None without both kinds. `frames` may be any iterable (read
    once)."""
    frames = list(frames)
    ref = [n for kind, n in frames if kind == FrameType.REFERENCE]
    res = [n for kind, n in frames if kind == FrameType.RESIDUAL]
    return float(np.mean(res) / np.mean(ref)) if ref and res else None


def encode_frame_payload(p: FramePayload) -> bytes:
    kind = int(p.frame_type) | (_SELF_CONTAINED if p.self_contained else 0)
    head = _HEADER.pack(FRAME_MAGIC, FRAME_VERSION, int(p.method), kind, p.frame_id, p.reference_id,
                        float(p.t), *map(float, p.position), *map(float, p.quat), len(p.video), len(p.geometry))
    return head + bytes(p.video) + bytes(p.geometry)


def decode_frame_payload(data: bytes, max_bytes: int = DEFAULT_MAX_FRAME_BYTES) -> FramePayload:
    """Parse and validate; any defect raises ProtocolError naming it."""
    if len(data) > max_bytes:
        raise ProtocolError(f"frame payload: {len(data)} bytes exceeds the cap of {max_bytes}")
    if len(data) < _HEADER.size:
        raise ProtocolError(f"frame payload: truncated header ({len(data)} of {_HEADER.size} bytes)")
    magic, version, method, kind, frame_id, ref_id, t, *rest = _HEADER.unpack_from(data)
    pos, quat, (n_video, n_geom) = rest[:3], rest[3:7], rest[7:]
    if magic != FRAME_MAGIC:
        raise ProtocolError(f"frame payload: bad magic {magic!r}, expected {FRAME_MAGIC!r}")
    if version != FRAME_VERSION:
        raise ProtocolError(f"frame payload: version {version} is not supported (expected {FRAME_VERSION})")
    try:
        method, ftype = Method(method), FrameType(kind & ~_SELF_CONTAINED)
    except ValueError as exc:
        raise ProtocolError(f"frame payload: {exc}") from None
    try:  # the same bounds as a PoseUpdate's: the client renders and records this pose
        t, pos, quat = check_time("frame payload t", t), check_position("frame payload position", pos), \
            check_quat("frame payload quat", quat)
    except ValueError as exc:
        raise ProtocolError(str(exc)) from None
    if _HEADER.size + n_video + n_geom != len(data):
        raise ProtocolError(f"frame payload: header says {n_video} video + {n_geom} geometry bytes, "
                            f"message has {len(data) - _HEADER.size}")
    body = memoryview(data)[_HEADER.size:]
    return FramePayload(method, frame_id, ftype, ref_id, t, pos.copy(), quat.copy(),
                        bytes(body[:n_video]), bytes(body[n_video:]), bool(kind & _SELF_CONTAINED))


# -- the split form: a frame's video apart from the rest (WebRTC sends the video on a media track) -------------

_SPLIT = struct.Struct("<II")   # track index, video bytes
_VIDEO_LEN = struct.Struct("<II")
_VIDEO_LEN_AT = _HEADER.size - _VIDEO_LEN.size


def _lengths(data: bytes | memoryview, what: str) -> tuple[int, int]:
    if len(data) < _HEADER.size or bytes(data[:4]) != FRAME_MAGIC:
        raise ProtocolError(f"{what}: not a frame payload ({len(data)} bytes)")
    n_video, n_geom = _VIDEO_LEN.unpack_from(data, _VIDEO_LEN_AT)
    if _HEADER.size + n_video + n_geom != len(data):
        raise ProtocolError(f"{what}: header says {n_video} video + {n_geom} geometry bytes, "
                            f"message has {len(data) - _HEADER.size}")
    return n_video, n_geom


def split_video(data: bytes, index: int) -> tuple[bytes, bytes]:
    """An encoded frame (:func:`encode_frame_payload`) as ``(rest, video)``: ``rest`` is the frame without its
    video, prefixed by the video's ``index`` on its track and its length; ``video`` the access unit. Only the
    header's lengths are read."""
    view = memoryview(data)
    n_video, n_geom = _lengths(view, "split_video")
    head = bytearray(view[:_HEADER.size])
    _VIDEO_LEN.pack_into(head, _VIDEO_LEN_AT, 0, n_geom)
    rest = _SPLIT.pack(index, n_video) + bytes(head) + bytes(view[_HEADER.size + n_video:])
    return rest, bytes(view[_HEADER.size:_HEADER.size + n_video])


def split_index(rest: bytes) -> tuple[int, int]:
    """(track index, video bytes) of a frame's ``rest`` (:func:`split_video`); ProtocolError when malformed."""
    if len(rest) < _SPLIT.size + _HEADER.size:
        raise ProtocolError(f"split frame: {len(rest)} bytes, shorter than its prefix and header")
    index, n_video = _SPLIT.unpack_from(rest)
    _lengths(memoryview(rest)[_SPLIT.size:], "split frame")
    return index, n_video


def join_video(rest: bytes, video: bytes) -> bytes:
    """The encoded frame of a ``rest`` (:func:`split_video`) with ``video`` (which may differ from the original:
    a receiver that re-encoded the picture, or the access unit as reassembled from RTP)."""
    split_index(rest)
    head = bytearray(rest[_SPLIT.size:_SPLIT.size + _HEADER.size])
    n_geom = _VIDEO_LEN.unpack_from(head, _VIDEO_LEN_AT)[1]
    _VIDEO_LEN.pack_into(head, _VIDEO_LEN_AT, len(video), n_geom)
    return bytes(head) + bytes(video) + rest[_SPLIT.size + _HEADER.size:]


def peek_frame_id(data: bytes) -> int:
    """The frame id in an encoded frame's (or a split rest's header's) fixed header, unchecked."""
    return struct.unpack_from("<I", data, 8)[0]
