"""Sans-I/O wire formats of quadcast (numpy + zstandard only)."""

from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.quads import (
    FrameType,
    LayerKind,
    QuadFrame,
    QuadFrameStats,
    QuadLayer,
    QuadSet,
    decode_quad_frame,
    encode_quad_frame,
    pack_normals,
    packed_size_bits_per_quad,
    quad_frame_stats,
    unpack_normals,
)

__all__ = [
    "FrameType",
    "LayerKind",
    "ProtocolError",
    "QuadFrame",
    "QuadFrameStats",
    "QuadLayer",
    "QuadSet",
    "decode_quad_frame",
    "encode_quad_frame",
    "pack_normals",
    "packed_size_bits_per_quad",
    "quad_frame_stats",
    "unpack_normals",
]

from quadcast.protocol.frame import FramePayload, Method, PayloadType, decode_frame_payload, encode_frame_payload  # noqa: E402

__all__ += ["FramePayload", "Method", "PayloadType", "decode_frame_payload", "encode_frame_payload"]
