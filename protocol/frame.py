"""`FramePayload`: what one server frame of any method carries to the client, sans-I/O.

Every method (quasar, quadstream, meshwarp, atw) sends, per server frame, one H.264 access unit (`video`) and one
method-specific geometry blob (`geometry`: a quad blob, a compressed depth map, or empty), plus the pose and scene
time it was rendered for. `encode_frame_payload` / `decode_frame_payload` give it a validated binary form.
"""
from __future__ import annotations

import enum
import math
import struct
from dataclasses import dataclass, field

import numpy as np

from quadcast.protocol.errors import ProtocolError

FRAME_MAGIC = b"QDCF"
FRAME_VERSION = 1
# magic, version, method, frame type, frame id, reference id, t, position (3 f8), quat (4 f8), video len, geometry len
_HEADER = struct.Struct("<4sHBBIId3d4dII")
DEFAULT_MAX_FRAME_BYTES = 64 * 1024 * 1024


class Method(enum.IntEnum):
    QUASAR = 0
    QUADSTREAM = 1
    MESHWARP = 2
    ATW = 3


class PayloadType(enum.IntEnum):
    REFERENCE = 0  # self-contained (every frame of the baselines)
    RESIDUAL = 1   # needs the client's cached reference frame `reference_id`


@dataclass
class FramePayload:
    method: Method
    frame_id: int
    frame_type: PayloadType
    reference_id: int
    t: float                  # scene time (s) the frame was rendered at
    position: np.ndarray      # (3,) render pose
    quat: np.ndarray          # (4,) xyzw
    video: bytes
    geometry: bytes = b""
    stats: dict = field(default_factory=dict)  # server-side figures; not sent

    @property
    def size_bytes(self) -> int:
        return _HEADER.size + len(self.video) + len(self.geometry)


def encode_frame_payload(p: FramePayload) -> bytes:
    head = _HEADER.pack(FRAME_MAGIC, FRAME_VERSION, int(p.method), int(p.frame_type), p.frame_id, p.reference_id,
                        float(p.t), *map(float, p.position), *map(float, p.quat), len(p.video), len(p.geometry))
    return head + bytes(p.video) + bytes(p.geometry)


def decode_frame_payload(data: bytes, max_bytes: int = DEFAULT_MAX_FRAME_BYTES) -> FramePayload:
    """Parse and validate; any defect raises ProtocolError naming it."""
    if len(data) > max_bytes:
        raise ProtocolError(f"frame payload: {len(data)} bytes exceeds the cap of {max_bytes}")
    if len(data) < _HEADER.size:
        raise ProtocolError(f"frame payload: truncated header ({len(data)} of {_HEADER.size} bytes)")
    magic, version, method, ftype, frame_id, ref_id, t, *rest = _HEADER.unpack_from(data)
    pos, quat, (n_video, n_geom) = rest[:3], rest[3:7], rest[7:]
    if magic != FRAME_MAGIC:
        raise ProtocolError(f"frame payload: bad magic {magic!r}, expected {FRAME_MAGIC!r}")
    if version != FRAME_VERSION:
        raise ProtocolError(f"frame payload: version {version} is not supported (expected {FRAME_VERSION})")
    try:
        method, ftype = Method(method), PayloadType(ftype)
    except ValueError as exc:
        raise ProtocolError(f"frame payload: {exc}") from None
    if not all(math.isfinite(v) for v in (t, *pos, *quat)) or sum(q * q for q in quat) < 1e-12:
        raise ProtocolError("frame payload: non-finite time/pose or zero quaternion")
    if _HEADER.size + n_video + n_geom != len(data):
        raise ProtocolError(f"frame payload: header says {n_video} video + {n_geom} geometry bytes, "
                            f"message has {len(data) - _HEADER.size}")
    body = memoryview(data)[_HEADER.size:]
    return FramePayload(method, frame_id, ftype, ref_id, t, np.array(pos), np.array(quat),
                        bytes(body[:n_video]), bytes(body[n_video:]))
