"""Quad proxies and their wire format: 80-bit packed quads in a columnar zstd blob.

A *quad* (QUASAR §3.4.2) stands in for a ``2**s x 2**s`` block of pixels of a
rendered layer whose top-left pixel is ``(x, y)`` (``y`` counted from the top
row).  Geometrically it is a plane in the layer camera's view space (OpenGL
convention: the camera looks down -Z, +Y is up) given by a unit normal and the
linear view depth (distance along -Z) of the plane at the block centre.  A
non-flattened quad also carries 16 float16 depth offsets (4 sub-quads x 4
corners).

Packing, 80 bits per quad (offsets are stored separately, 16 x float16 each):

* one ``uint32`` word: ``flattened`` (bit 31) | ``alpha`` (bit 30) |
  ``size_log2`` (bits 24..29) | ``x`` (bits 12..23) | ``y`` (bits 0..11);
* the normal as two ``uint8`` spherical angles (see :func:`pack_normals`);
* the depth as a little-endian ``float32`` (the servers round it to 12 mantissa bits before
  packing, :func:`round_mantissa`: the format does not change, zstd drops the zeroed low bytes).

Blob layout produced by :func:`encode_quad_frame` (all little-endian):

* fixed header :data:`HEADER_STRUCT`: magic ``b"QDCQ"``, version (u16),
  flags (u8, reserved, must be 0), layer count (u8, <= 16), uncompressed
  payload size (u32).  Which frame the blob belongs to, its type and its
  reference are the frame payload header's (:mod:`quadcast.protocol.frame`),
  said once there (version 3; version 2 repeated them here);
* per layer :data:`LAYER_STRUCT`: kind (u8), width (u16), height (u16),
  atlas rect (4 x u16), camera (16 x f32), quad count (u32), offset count (u32);
* exactly one zstd frame (declaring its content size) whose content is the
  columns of all quads of all layers, grouped by field: all words, then all
  theta codes, all phi codes, all depths, then all offsets.  Multi-byte columns
  (words, depths, offsets) are stored as byte planes: all first bytes, then all
  second bytes, ... -- a reversible shuffle that puts the slowly-varying high
  bytes (x, y, size, exponent) side by side, which zstd compresses 30-40% better
  (version 2).  The uncompressed size is therefore ``10 * quads + 32 *
  offset_rows`` bytes.  The encoder ends a zstd block at each column boundary so
  each field gets its own entropy tables.

This module is sans-I/O: numpy and zstandard only.
"""

from __future__ import annotations

import enum
import math
import operator
import struct
from dataclasses import dataclass
from typing import Any, NamedTuple, Sequence

import numpy as np
import zstandard

from quadcast.protocol.compression import decompress_exact
from quadcast.protocol.errors import ProtocolError

__all__ = [
    "BLOB_MAGIC",
    "BLOB_VERSION",
    "DEFAULT_MAX_PAYLOAD_BYTES",
    "DEFAULT_MAX_QUADS",
    "HEADER_STRUCT",
    "LAYER_STRUCT",
    "MAX_COORD",
    "MAX_LAYERS",
    "MAX_SIZE_LOG2",
    "NORMAL_MAX_ANGULAR_ERROR",
    "OFFSETS_PER_QUAD",
    "PACKED_BITS_PER_QUAD",
    "LayerKind",
    "QuadFrame",
    "QuadFrameStats",
    "QuadLayer",
    "QuadSet",
    "QuadWordFields",
    "decode_quad_frame",
    "encode_quad_frame",
    "pack_normals",
    "pack_quad_words",
    "packed_size_bits_per_quad",
    "quad_frame_stats",
    "round_mantissa",
    "unpack_normals",
    "unpack_quad_words",
]

# --------------------------------------------------------------------------
# Constants
# --------------------------------------------------------------------------

MAX_COORD = 4096
"""Exclusive upper bound of a quad's ``x`` and ``y`` (12-bit fields)."""

MAX_SIZE_LOG2 = 11
"""Largest allowed ``size_log2`` (a 2048 x 2048 pixel block)."""

OFFSETS_PER_QUAD = 16
"""Depth offsets carried by one non-flattened quad (4 sub-quads x 4 corners)."""

PACKED_BITS_PER_QUAD = 80
"""Raw packed size of one quad, offsets excluded: 32 + 8 + 8 + 32 bits."""

MAX_LAYERS = 16
"""Largest number of layers in one :class:`QuadFrame`."""

BLOB_MAGIC = b"QDCQ"
BLOB_VERSION = 3

HEADER_STRUCT = struct.Struct("<4sHBBI")
"""Blob header: magic, version, flags, layer count, payload size."""

LAYER_STRUCT = struct.Struct("<BHH4H16fII")
"""Per-layer header: kind, width, height, atlas rect (x, y, w, h), camera[16], quad count, offset count."""

DEFAULT_MAX_QUADS = 1 << 23
"""Default cap on the total quad count of a decoded frame (8 Mi quads)."""

_WORD_BYTES, _THETA_BYTES, _PHI_BYTES, _DEPTH_BYTES = 4, 1, 1, 4
_QUAD_BYTES = _WORD_BYTES + _THETA_BYTES + _PHI_BYTES + _DEPTH_BYTES
_OFFSET_ROW_BYTES = OFFSETS_PER_QUAD * 2

DEFAULT_MAX_PAYLOAD_BYTES = DEFAULT_MAX_QUADS * (_QUAD_BYTES + _OFFSET_ROW_BYTES)
"""Default cap on the uncompressed payload (every quad non-flattened at :data:`DEFAULT_MAX_QUADS`)."""

_FLATTENED_BIT = np.uint32(1 << 31)
_ALPHA_BIT = np.uint32(1 << 30)
_SIZE_SHIFT = 24
_SIZE_MASK = 0x3F
_X_SHIFT = 12
_COORD_MASK = 0xFFF

_THETA_STEPS = 255  # theta in [0, pi]: code k <-> k * pi / 255 (both poles exact)
_PHI_STEPS = 256  # phi in [-pi, pi): code k <-> -pi + k * 2 pi / 256 (wraps around)

NORMAL_MAX_ANGULAR_ERROR = 2.0 * math.asin(
    math.sqrt(
        math.sin(math.pi / (4 * _THETA_STEPS)) ** 2 + math.sin(math.pi / (2 * _PHI_STEPS)) ** 2
    )
) + 1e-6
"""Largest angle (radians, ~0.01373 = 0.787 deg) between a unit normal and its packed round trip.

Rounding to nearest leaves ``|d theta| <= pi/510`` and ``|d phi| <= pi/256``;
by the haversine formula ``hav(err) = hav(d theta) + sin(t) sin(t') hav(d phi)
<= hav(pi/510) + hav(pi/256)``.  ``1e-6`` covers float32 output rounding.
"""

_NORMAL_UNIT_TOLERANCE = 1e-3
_MAX_ZSTD_WINDOW = 1 << 27


class LayerKind(enum.IntEnum):
    """Which rendered layer a :class:`QuadLayer` approximates."""

    VISIBLE = 0
    HIDDEN = 1
    WIDE = 2
    UPDATED = 3
    REVEALED = 4
    FAR = 5        # a face of the far-field cube map (server/farfield.py)


_LAYER_KIND_VALUES = frozenset(int(k) for k in LayerKind)
FULL_SIZE_KINDS = frozenset({LayerKind.VISIBLE, LayerKind.UPDATED, LayerKind.REVEALED})
"""Layers of the view itself, always at the size the client asked for."""


# --------------------------------------------------------------------------
# Column validation helpers (raise ValueError naming the field)
# --------------------------------------------------------------------------


def _column(name: str, values: Any, n: int | None) -> np.ndarray:
    arr = np.asarray(values)
    if arr.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D array, got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name}: expected length {n} (len(x)), got {arr.shape[0]}")
    return arr


def _uint_column(name: str, values: Any, dtype: type, max_value: int, n: int | None) -> np.ndarray:
    arr = _column(name, values, n)
    if arr.size == 0:
        return np.zeros(0, dtype=dtype)
    if arr.dtype.kind not in "iu":
        raise ValueError(f"{name}: expected integers, got dtype {arr.dtype}")
    bad = np.flatnonzero((arr < 0) | (arr > max_value))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{name}[{i}]: expected 0..{max_value}, got {arr[i]}")
    return arr.astype(dtype, copy=True)


def _bool_column(name: str, values: Any, n: int) -> np.ndarray:
    arr = _column(name, values, n)
    if arr.size == 0 or arr.dtype.kind == "b":
        return arr.astype(bool, copy=True)
    if arr.dtype.kind not in "iu":
        raise ValueError(f"{name}: expected booleans, got dtype {arr.dtype}")
    bad = np.flatnonzero((arr != 0) & (arr != 1))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"{name}[{i}]: expected a boolean (0 or 1), got {arr[i]}")
    return arr.astype(bool)


def _real_array(name: str, values: Any, dtype: type) -> np.ndarray:
    arr = np.asarray(values)
    if arr.size and arr.dtype.kind not in "iuf":
        raise ValueError(f"{name}: expected real numbers, got dtype {arr.dtype}")
    with np.errstate(over="ignore", invalid="ignore"):
        return arr.astype(dtype, copy=True)


def _first_nonfinite(arr: np.ndarray) -> tuple[int, ...] | None:
    bad = np.argwhere(~np.isfinite(arr))
    return tuple(int(v) for v in bad[0]) if bad.size else None


def _index_str(idx: tuple[int, ...]) -> str:
    return ",".join(str(i) for i in idx)


# --------------------------------------------------------------------------
# QuadSet
# --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class QuadSet:
    """A column store of N quads (one row per quad), plus offsets of the non-flattened ones.

    Columns (all length N): ``x``, ``y`` (uint16, < 4096; top-left pixel of the
    block, ``y`` from the top row), ``size_log2`` (uint8, 0..11), ``flattened``
    and ``alpha`` (bool), ``normal`` (float32 (N, 3), unit, view space),
    ``depth`` (float32, finite linear view depth at the block centre).
    ``offsets`` is float16 (M, 16) with M = number of non-flattened quads, row
    ``k`` belonging to the k-th non-flattened quad in quad order.

    Inputs are converted to these dtypes (copied); out-of-range or inconsistent
    inputs raise :class:`ValueError` naming the column and the first bad row.
    """

    x: np.ndarray
    y: np.ndarray
    size_log2: np.ndarray
    flattened: np.ndarray
    alpha: np.ndarray
    normal: np.ndarray
    depth: np.ndarray
    offsets: np.ndarray

    def __post_init__(self) -> None:
        x = _uint_column("QuadSet.x", self.x, np.uint16, MAX_COORD - 1, None)
        n = x.shape[0]
        y = _uint_column("QuadSet.y", self.y, np.uint16, MAX_COORD - 1, n)
        size_log2 = _uint_column("QuadSet.size_log2", self.size_log2, np.uint8, MAX_SIZE_LOG2, n)
        flattened = _bool_column("QuadSet.flattened", self.flattened, n)
        alpha = _bool_column("QuadSet.alpha", self.alpha, n)

        normal = _real_array("QuadSet.normal", self.normal, np.float32)
        if normal.size == 0 and n == 0:
            normal = normal.reshape(0, 3)
        if normal.shape != (n, 3):
            raise ValueError(f"QuadSet.normal: expected shape ({n}, 3), got {normal.shape}")
        bad = _first_nonfinite(normal)
        if bad is not None:
            raise ValueError(f"QuadSet.normal[{_index_str(bad)}]: expected finite, got {normal[bad]}")
        norms = np.linalg.norm(normal.astype(np.float64), axis=1)
        off_unit = np.flatnonzero(np.abs(norms - 1.0) > _NORMAL_UNIT_TOLERANCE)
        if off_unit.size:
            i = int(off_unit[0])
            raise ValueError(
                f"QuadSet.normal[{i}]: expected a unit vector (|n| within {_NORMAL_UNIT_TOLERANCE} of 1), "
                f"got |n| = {norms[i]:.6g}"
            )

        depth = _real_array("QuadSet.depth", self.depth, np.float32)
        if depth.ndim != 1 or depth.shape[0] != n:
            raise ValueError(f"QuadSet.depth: expected shape ({n},), got {depth.shape}")
        bad = _first_nonfinite(depth)
        if bad is not None:
            raise ValueError(f"QuadSet.depth[{bad[0]}]: expected a finite float32, got {depth[bad]}")

        m = int(n - np.count_nonzero(flattened))
        offsets = _real_array("QuadSet.offsets", self.offsets, np.float16)
        if offsets.size == 0 and m == 0:
            offsets = offsets.reshape(0, OFFSETS_PER_QUAD)
        if offsets.shape != (m, OFFSETS_PER_QUAD):
            raise ValueError(
                f"QuadSet.offsets: expected shape ({m}, {OFFSETS_PER_QUAD}) "
                f"(one row per non-flattened quad), got {offsets.shape}"
            )
        bad = _first_nonfinite(offsets)
        if bad is not None:
            raise ValueError(
                f"QuadSet.offsets[{_index_str(bad)}]: expected a finite float16 (|v| <= 65504), "
                f"got {offsets[bad]}"
            )

        for name, value in (
            ("x", x), ("y", y), ("size_log2", size_log2), ("flattened", flattened),
            ("alpha", alpha), ("normal", normal), ("depth", depth), ("offsets", offsets),
        ):
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return int(self.x.shape[0])

    def __repr__(self) -> str:
        return f"QuadSet(n={len(self)}, non_flattened={self.non_flattened_count})"

    @property
    def non_flattened_count(self) -> int:
        """Number of quads that carry offsets (rows of :attr:`offsets`)."""
        return int(self.offsets.shape[0])

    @property
    def offset_index(self) -> np.ndarray:
        """int64 (N,): row of :attr:`offsets` belonging to each quad, -1 for flattened quads."""
        index = np.cumsum(~self.flattened, dtype=np.int64) - 1
        index[self.flattened] = -1
        return index

    @classmethod
    def _decoded(cls, **columns: np.ndarray) -> QuadSet:
        """A QuadSet over columns already checked: made by the blob decoder (no copies: decoding a frame costs
        its output, not twice that), or taken from valid QuadSets (`concatenate`, `select`)."""
        obj = object.__new__(cls)
        for name, value in columns.items():
            object.__setattr__(obj, name, value)
        return obj

    @classmethod
    def empty(cls) -> QuadSet:
        """A QuadSet holding no quads."""
        return cls(
            x=np.zeros(0, np.uint16),
            y=np.zeros(0, np.uint16),
            size_log2=np.zeros(0, np.uint8),
            flattened=np.zeros(0, bool),
            alpha=np.zeros(0, bool),
            normal=np.zeros((0, 3), np.float32),
            depth=np.zeros(0, np.float32),
            offsets=np.zeros((0, OFFSETS_PER_QUAD), np.float16),
        )

    @classmethod
    def concatenate(cls, sets: Sequence[QuadSet]) -> QuadSet:
        """The quads of ``sets`` one after another (offsets follow the same order)."""
        sets = list(sets)
        for i, s in enumerate(sets):
            if not isinstance(s, QuadSet):
                raise TypeError(f"QuadSet.concatenate: item {i} is {type(s).__name__}, expected QuadSet")
        if not sets:
            return cls.empty()
        return cls._decoded(
            x=np.concatenate([s.x for s in sets]),
            y=np.concatenate([s.y for s in sets]),
            size_log2=np.concatenate([s.size_log2 for s in sets]),
            flattened=np.concatenate([s.flattened for s in sets]),
            alpha=np.concatenate([s.alpha for s in sets]),
            normal=np.concatenate([s.normal for s in sets]),
            depth=np.concatenate([s.depth for s in sets]),
            offsets=np.concatenate([s.offsets for s in sets]),
        )

    def with_depth_bits(self, bits: int) -> QuadSet:
        """The same quads with their depths rounded to ``bits`` mantissa bits (:func:`round_mantissa`)."""
        columns = {name: getattr(self, name) for name in ("x", "y", "size_log2", "flattened", "alpha", "normal",
                                                          "offsets")}
        return QuadSet._decoded(depth=round_mantissa(self.depth, bits), **columns)

    def select(self, mask: Any) -> QuadSet:
        """The quads picked by a boolean mask of length N or by an integer index array.

        Offsets of the kept non-flattened quads are carried along in the new order.
        """
        sel = np.asarray(mask)
        if sel.dtype.kind == "b":
            if sel.shape != (len(self),):
                raise ValueError(f"QuadSet.select: boolean mask must have shape ({len(self)},), got {sel.shape}")
            idx = np.flatnonzero(sel)
        elif sel.size == 0 or sel.dtype.kind in "iu":
            if sel.ndim != 1:
                raise ValueError(f"QuadSet.select: index array must be 1-D, got shape {sel.shape}")
            idx = sel.astype(np.int64)
            if idx.size and (idx.min() < -len(self) or idx.max() >= len(self)):
                raise IndexError(f"QuadSet.select: index out of range for {len(self)} quads")
        else:
            raise ValueError(f"QuadSet.select: expected a boolean mask or integer indices, got dtype {sel.dtype}")
        rows = self.offset_index[idx]
        return QuadSet._decoded(
            x=self.x[idx],
            y=self.y[idx],
            size_log2=self.size_log2[idx],
            flattened=self.flattened[idx],
            alpha=self.alpha[idx],
            normal=self.normal[idx],
            depth=self.depth[idx],
            offsets=self.offsets[rows[rows >= 0]],
        )


# --------------------------------------------------------------------------
# Bit packing
# --------------------------------------------------------------------------


class QuadWordFields(NamedTuple):
    """The fields unpacked from uint32 quad words (no range validation)."""

    x: np.ndarray  # uint16
    y: np.ndarray  # uint16
    size_log2: np.ndarray  # uint8, 0..63 (values > 11 are invalid quads)
    flattened: np.ndarray  # bool
    alpha: np.ndarray  # bool


def pack_quad_words(quads: QuadSet) -> np.ndarray:
    """uint32 (N,): flattened (bit 31) | alpha (bit 30) | size_log2 << 24 | x << 12 | y."""
    words = quads.y.astype(np.uint32)
    words |= quads.x.astype(np.uint32) << np.uint32(_X_SHIFT)
    words |= quads.size_log2.astype(np.uint32) << np.uint32(_SIZE_SHIFT)
    words |= np.where(quads.alpha, _ALPHA_BIT, np.uint32(0))
    words |= np.where(quads.flattened, _FLATTENED_BIT, np.uint32(0))
    return words


def unpack_quad_words(words: Any) -> QuadWordFields:
    """Split uint32 quad words into their fields (inverse of :func:`pack_quad_words`)."""
    w = np.asarray(words)
    if w.dtype != np.uint32:
        raise ValueError(f"unpack_quad_words: expected uint32 words, got dtype {w.dtype}")
    return QuadWordFields(
        x=((w >> np.uint32(_X_SHIFT)) & np.uint32(_COORD_MASK)).astype(np.uint16),
        y=(w & np.uint32(_COORD_MASK)).astype(np.uint16),
        size_log2=((w >> np.uint32(_SIZE_SHIFT)) & np.uint32(_SIZE_MASK)).astype(np.uint8),
        flattened=(w & _FLATTENED_BIT) != 0,
        alpha=(w & _ALPHA_BIT) != 0,
    )


def pack_normals(normals: Any) -> tuple[np.ndarray, np.ndarray]:
    """Quantise normals (N, 3) to two uint8 spherical angles ``(theta_code, phi_code)``.

    ``theta`` is the polar angle from +Z in [0, pi], coded ``round(theta * 255 / pi)``;
    ``phi = atan2(y, x)`` in [-pi, pi), coded ``round((phi + pi) * 256 / (2 pi)) mod 256``.
    Inputs are normalised first (zero or non-finite vectors raise ValueError).
    The round trip is within :data:`NORMAL_MAX_ANGULAR_ERROR` (~0.0137 rad).
    """
    n = np.asarray(normals, dtype=np.float64)
    if n.ndim != 2 or n.shape[1] != 3:
        raise ValueError(f"pack_normals: expected shape (N, 3), got {n.shape}")
    norms = np.linalg.norm(n, axis=1)
    bad = np.flatnonzero(~np.isfinite(norms) | (norms == 0.0))
    if bad.size:
        i = int(bad[0])
        raise ValueError(f"pack_normals: normal[{i}] must be finite and non-zero, got {n[i]}")
    n = n / norms[:, None]
    theta = np.arccos(np.clip(n[:, 2], -1.0, 1.0))
    phi = np.arctan2(n[:, 1], n[:, 0])
    theta_code = np.clip(np.rint(theta * (_THETA_STEPS / math.pi)), 0, _THETA_STEPS).astype(np.uint8)
    phi_code = (np.rint((phi + math.pi) * (_PHI_STEPS / (2.0 * math.pi))).astype(np.int64) % _PHI_STEPS).astype(
        np.uint8
    )
    return theta_code, phi_code


_NORMAL_TABLE: np.ndarray | None = None


def _normal_table() -> np.ndarray:
    """float32 (256 * 256, 3): the unit normal of every (theta code << 8 | phi code), computed once in float64."""
    global _NORMAL_TABLE
    if _NORMAL_TABLE is None:
        theta = np.arange(256, dtype=np.float64)[:, None] * (math.pi / _THETA_STEPS)
        phi = np.arange(256, dtype=np.float64)[None, :] * (2.0 * math.pi / _PHI_STEPS) - math.pi
        sin_t = np.sin(theta)
        table = np.stack(np.broadcast_arrays(sin_t * np.cos(phi), sin_t * np.sin(phi), np.cos(theta)), axis=-1)
        _NORMAL_TABLE = np.ascontiguousarray(table.reshape(-1, 3).astype(np.float32))
    return _NORMAL_TABLE


def unpack_normals(theta_code: Any, phi_code: Any) -> np.ndarray:
    """Unit normals float32 (N, 3) from the uint8 angle codes of :func:`pack_normals` (a table look-up: no
    float64 temporaries, so decoding a frame needs little more memory than its output)."""
    t = np.asarray(theta_code)
    p = np.asarray(phi_code)
    if t.dtype != np.uint8 or p.dtype != np.uint8 or t.shape != p.shape or t.ndim != 1:
        raise ValueError(
            f"unpack_normals: expected two uint8 arrays of equal 1-D shape, "
            f"got {t.dtype}{t.shape} and {p.dtype}{p.shape}"
        )
    index = t.astype(np.uint16) << np.uint16(8)
    index |= p
    return _normal_table()[index]


# --------------------------------------------------------------------------
# Layers and frames
# --------------------------------------------------------------------------


def _u_int(name: str, value: Any, lo: int, hi: int) -> int:
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name}: expected an integer, got bool {value}")
    try:
        v = operator.index(value)
    except TypeError:
        raise ValueError(f"{name}: expected an integer, got {type(value).__name__} {value!r}") from None
    if not lo <= v <= hi:
        raise ValueError(f"{name}: expected {lo}..{hi}, got {v}")
    return v


@dataclass(frozen=True, eq=False)
class QuadLayer:
    """The quads approximating one rendered layer, with the camera and atlas placement of its image.

    ``width`` x ``height`` is the layer image size in pixels; every quad has
    ``x < width`` and ``y < height``.  ``camera`` is 16 float32 carried opaquely
    (3 position, 4 quaternion xyzw, 6 frustum l r b t n f, 3 spare) but must be
    finite.  ``atlas_rect`` is ``(x, y, w, h)`` (uint16 each) of the layer's
    colour in the video atlas.
    """

    kind: LayerKind
    width: int
    height: int
    camera: np.ndarray
    atlas_rect: tuple[int, int, int, int]
    quads: QuadSet

    def __post_init__(self) -> None:
        try:
            kind = LayerKind(self.kind)
        except ValueError:
            raise ValueError(
                f"QuadLayer.kind: expected one of {[int(k) for k in LayerKind]}, got {self.kind!r}"
            ) from None
        width = _u_int("QuadLayer.width", self.width, 1, 0xFFFF)
        height = _u_int("QuadLayer.height", self.height, 1, 0xFFFF)
        camera = _real_array("QuadLayer.camera", self.camera, np.float32).reshape(-1)
        if camera.shape != (16,):
            raise ValueError(f"QuadLayer.camera: expected 16 floats, got {camera.size}")
        bad = _first_nonfinite(camera)
        if bad is not None:
            raise ValueError(f"QuadLayer.camera[{bad[0]}]: expected finite, got {camera[bad]}")
        rect = tuple(self.atlas_rect)
        if len(rect) != 4:
            raise ValueError(f"QuadLayer.atlas_rect: expected (x, y, w, h), got {len(rect)} values")
        rect = tuple(_u_int(f"QuadLayer.atlas_rect[{i}]", v, 0, 0xFFFF) for i, v in enumerate(rect))
        if not isinstance(self.quads, QuadSet):
            raise ValueError(f"QuadLayer.quads: expected a QuadSet, got {type(self.quads).__name__}")
        if len(self.quads) > width * height:      # what decode_quad_frame refuses, never written
            raise ValueError(f"QuadLayer.quads: {len(self.quads)} quads in a {width}x{height} layer "
                             f"(at most one per pixel)")
        for axis, limit, column in (("x", width, self.quads.x), ("y", height, self.quads.y)):
            bad_rows = np.flatnonzero(column >= limit)
            if bad_rows.size:
                i = int(bad_rows[0])
                raise ValueError(
                    f"QuadLayer.quads.{axis}[{i}]: expected < layer "
                    f"{'width' if axis == 'x' else 'height'} {limit}, got {column[i]}"
                )
        object.__setattr__(self, "kind", kind)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)
        object.__setattr__(self, "camera", camera)
        object.__setattr__(self, "atlas_rect", rect)


@dataclass(frozen=True, eq=False)
class QuadFrame:
    """The quads of one server frame: up to 16 layers (the frame's id, type and reference are its payload's)."""

    layers: list[QuadLayer]

    def __post_init__(self) -> None:
        layers = list(self.layers)
        if len(layers) > MAX_LAYERS:
            raise ValueError(f"QuadFrame.layers: expected at most {MAX_LAYERS} layers, got {len(layers)}")
        for i, layer in enumerate(layers):
            if not isinstance(layer, QuadLayer):
                raise ValueError(f"QuadFrame.layers[{i}]: expected a QuadLayer, got {type(layer).__name__}")
        object.__setattr__(self, "layers", layers)

    @property
    def quad_count(self) -> int:
        """Total quads over all layers."""
        return sum(len(layer.quads) for layer in self.layers)

    @property
    def offset_count(self) -> int:
        """Total offset rows (non-flattened quads) over all layers."""
        return sum(layer.quads.non_flattened_count for layer in self.layers)


# --------------------------------------------------------------------------
# Encoding
# --------------------------------------------------------------------------


def round_mantissa(values: Any, bits: int) -> np.ndarray:
    """float32 ``values`` rounded to the nearest float32 with only the top ``bits`` (1..23) of the 23 mantissa bits
    set: a relative error of at most ``2 ** -(bits + 1)``, and byte planes whose low bytes are zero. A value that
    would round past the largest float32 keeps its own."""
    bits = _u_int("depth_bits", bits, 1, 23)
    out = np.array(values, dtype="<f4", order="C")        # a copy: the caller's array is never changed
    if bits == 23 or out.size == 0:
        return out
    drop = 23 - bits
    u = out.view("<u4").astype(np.uint64)
    rounded = (((u + (1 << (drop - 1))) >> drop) << drop).astype("<u4").view("<f4")
    return np.where(np.isfinite(rounded), rounded, out)


def _packed_columns(frame: QuadFrame, depth_bits: int | None = None) -> list[np.ndarray]:
    """The five little-endian payload columns: words, theta, phi, depth, offsets (all layers); depths rounded to
    ``depth_bits`` mantissa bits when given (:func:`round_mantissa`)."""
    quads = QuadSet.concatenate([layer.quads for layer in frame.layers])
    theta, phi = pack_normals(quads.normal) if len(quads) else (np.zeros(0, np.uint8), np.zeros(0, np.uint8))
    depth = quads.depth.astype("<f4") if depth_bits is None else round_mantissa(quads.depth, depth_bits)
    return [
        pack_quad_words(quads).astype("<u4"),
        theta,
        phi,
        depth,
        quads.offsets.astype("<f2"),
    ]


def packed_size_bits_per_quad(frame: QuadFrame) -> float:
    """Raw packed bits per quad before zstd, offsets excluded (always :data:`PACKED_BITS_PER_QUAD`).

    Measured from the actual packed columns; a frame without quads reports the nominal value.
    """
    words, theta, phi, depth, _ = _packed_columns(frame)
    n = words.shape[0]
    if n == 0:
        return float(PACKED_BITS_PER_QUAD)
    return 8.0 * (words.nbytes + theta.nbytes + phi.nbytes + depth.nbytes) / n


def _byte_planes(column: np.ndarray) -> bytes:
    """A little-endian column as its byte planes (byte 0 of every item, then byte 1, ...)."""
    if column.dtype.itemsize == 1:
        return column.tobytes()
    return np.ascontiguousarray(column.view(np.uint8).reshape(-1, column.dtype.itemsize).T).tobytes()


def _check_level(level: Any) -> int:
    return _u_int("level", level, -(1 << 17), zstandard.MAX_COMPRESSION_LEVEL)


def _encode_parts(frame: QuadFrame, level: int, depth_bits: int | None) -> tuple[bytes, bytes, int]:
    if not isinstance(frame, QuadFrame):
        raise TypeError(f"encode_quad_frame: expected a QuadFrame, got {type(frame).__name__}")
    level = _check_level(level)
    columns = [_byte_planes(column) for column in _packed_columns(frame, depth_bits)]
    raw_size = sum(len(column) for column in columns)
    if raw_size > 0xFFFFFFFF:
        raise ValueError(f"encode_quad_frame: payload of {raw_size} bytes does not fit the u32 size field")
    header = [
        HEADER_STRUCT.pack(BLOB_MAGIC, BLOB_VERSION, 0, len(frame.layers), raw_size)
    ]
    for layer in frame.layers:
        header.append(
            LAYER_STRUCT.pack(
                int(layer.kind), layer.width, layer.height, *layer.atlas_rect,
                *layer.camera.tolist(), len(layer.quads), layer.quads.non_flattened_count,
            )
        )
    # One zstd frame; each column ends a zstd block so every field gets its own entropy tables
    # (about 13% smaller than a single block on smooth quad fields).
    compressor = zstandard.ZstdCompressor(level=level, write_content_size=True, write_checksum=True)
    stream = compressor.compressobj(size=raw_size)
    parts = []
    for column in columns:
        if column:
            parts.append(stream.compress(column))
            parts.append(stream.flush(zstandard.COMPRESSOBJ_FLUSH_BLOCK))
    parts.append(stream.flush(zstandard.COMPRESSOBJ_FLUSH_FINISH))
    return b"".join(header), b"".join(parts), raw_size


def encode_quad_frame(frame: QuadFrame, level: int = 3, depth_bits: int | None = None) -> bytes:
    """Serialise ``frame`` to the columnar zstd quad blob (layout in the module docstring). ``depth_bits``: keep
    only that many of the depths' 23 mantissa bits (rounded; None keeps them all). The blob is the same format
    either way: the low bytes of float32 view depths are rendering noise that zstd cannot compress, and rounding
    them to zero (12 bits: at most 0.012% of the depth) makes a frame's blob about a quarter smaller."""
    header, payload, _ = _encode_parts(frame, level, depth_bits)
    return header + payload


@dataclass(frozen=True)
class QuadFrameStats:
    """Sizes of one encoded quad frame."""

    quad_count: int
    offset_count: int
    header_bytes: int
    raw_payload_bytes: int
    compressed_payload_bytes: int
    packed_bits_per_quad: float

    @property
    def total_bytes(self) -> int:
        """Size of the whole blob."""
        return self.header_bytes + self.compressed_payload_bytes


def quad_frame_stats(frame: QuadFrame, level: int = 3, depth_bits: int | None = None) -> QuadFrameStats:
    """Encode ``frame`` and report its sizes."""
    header, payload, raw_size = _encode_parts(frame, level, depth_bits)
    return QuadFrameStats(
        quad_count=frame.quad_count,
        offset_count=frame.offset_count,
        header_bytes=len(header),
        raw_payload_bytes=raw_size,
        compressed_payload_bytes=len(payload),
        packed_bits_per_quad=packed_size_bits_per_quad(frame),
    )


# --------------------------------------------------------------------------
# Decoding
# --------------------------------------------------------------------------


def decode_quad_frame(
    data: bytes | bytearray | memoryview,
    *,
    max_quads: int = DEFAULT_MAX_QUADS,
    max_bytes: int = DEFAULT_MAX_PAYLOAD_BYTES,
    size: tuple[int, int] | None = None,
) -> QuadFrame:
    """Parse a blob made by :func:`encode_quad_frame`.

    ``max_quads`` caps the total quad count over all layers and ``max_bytes``
    the uncompressed payload size; ``size`` is the (width, height) the
    receiver asked for: the layers of the view itself (visible, updated,
    revealed) must then be that size, the others (hidden layers and the wide
    view, sent at reduced size) at most that size. A layer never holds more quads than
    it has pixels. All of it is checked from the headers before anything is
    decompressed or allocated, and decoding then needs about its output's
    memory (plus the decompressed payload).  Any malformed, truncated,
    inconsistent or over-limit input raises :class:`ProtocolError`.
    """
    try:
        view = memoryview(data).cast("B")
    except TypeError:
        raise ProtocolError(f"blob: expected bytes-like data, got {type(data).__name__}") from None
    if len(view) < HEADER_STRUCT.size:
        raise ProtocolError(f"truncated blob: header needs {HEADER_STRUCT.size} bytes, got {len(view)}")
    magic, version, flags, layer_count, payload_size = HEADER_STRUCT.unpack_from(view, 0)
    if magic != BLOB_MAGIC:
        raise ProtocolError(f"header.magic: expected {BLOB_MAGIC!r}, got {bytes(magic)!r}")
    if version != BLOB_VERSION:
        raise ProtocolError(f"header.version: expected {BLOB_VERSION}, got {version}")
    if flags != 0:
        raise ProtocolError(f"header.flags: expected 0 (no flags are defined), got {flags:#04x}")
    if layer_count > MAX_LAYERS:
        raise ProtocolError(f"header.layer_count: expected at most {MAX_LAYERS}, got {layer_count}")
    layers_end = HEADER_STRUCT.size + layer_count * LAYER_STRUCT.size
    if len(view) < layers_end:
        raise ProtocolError(
            f"truncated blob: {layer_count} layer headers need {layers_end} bytes, got {len(view)}"
        )

    layer_fields = []
    total_quads = total_offsets = 0
    for i in range(layer_count):
        fields = LAYER_STRUCT.unpack_from(view, HEADER_STRUCT.size + i * LAYER_STRUCT.size)
        kind, width, height = fields[0], fields[1], fields[2]
        quad_count, offset_count = fields[-2], fields[-1]
        if kind not in _LAYER_KIND_VALUES:
            raise ProtocolError(f"layer[{i}].kind: expected one of {[int(k) for k in LayerKind]}, got {kind}")
        if width == 0 or height == 0:
            raise ProtocolError(f"layer[{i}]: expected a non-empty image, got {width}x{height}")
        if size is not None:
            w, h = size
            if kind in FULL_SIZE_KINDS and (width, height) != (w, h):
                raise ProtocolError(f"layer[{i}]: {width}x{height}, expected the {w}x{h} asked for")
            if not (width <= w and height <= h):
                raise ProtocolError(f"layer[{i}]: a {LayerKind(kind).name.lower()} layer of {width}x{height}, "
                                    f"larger than the {w}x{h} asked for")
        if quad_count > width * height:
            raise ProtocolError(f"layer[{i}].quad_count: {quad_count} quads in a {width}x{height} layer "
                                f"(at most one per pixel)")
        if offset_count > quad_count:
            raise ProtocolError(
                f"layer[{i}].offset_count: expected <= quad count {quad_count}, got {offset_count}"
            )
        total_quads += quad_count
        total_offsets += offset_count
        if total_quads > max_quads:
            raise ProtocolError(
                f"layer[{i}].quad_count: total quads {total_quads} exceeds max_quads {max_quads}"
            )
        layer_fields.append(fields)

    expected = total_quads * _QUAD_BYTES + total_offsets * _OFFSET_ROW_BYTES
    if payload_size != expected:
        raise ProtocolError(
            f"header.payload_size: expected {expected} (from layer counts), got {payload_size}"
        )
    if expected > max_bytes:
        raise ProtocolError(f"header.payload_size: {expected} bytes exceeds max_bytes {max_bytes}")

    raw = decompress_exact(view[layers_end:], expected, "payload")

    pos = 0

    def take(dtype: str, count: int) -> np.ndarray:
        """The next column: `count` items stored as byte planes (see :func:`_byte_planes`)."""
        nonlocal pos
        item = np.dtype(dtype).itemsize
        planes = np.frombuffer(raw, dtype=np.uint8, count=count * item, offset=pos)
        pos += planes.nbytes
        return np.ascontiguousarray(planes.reshape(item, count).T).view(dtype).reshape(count)

    words = take("<u4", total_quads)
    theta = take("u1", total_quads)
    phi = take("u1", total_quads)
    depth = take("<f4", total_quads).astype(np.float32, copy=False)
    offsets = take("<f2", total_offsets * OFFSETS_PER_QUAD).astype(np.float16, copy=False).reshape(
        -1, OFFSETS_PER_QUAD)
    raw = None   # the columns are read: drop this reference to the decompressed payload
    fields_all = unpack_quad_words(words)
    del words
    normals = unpack_normals(theta, phi)
    del theta, phi

    layers: list[QuadLayer] = []
    q0 = o0 = 0
    for i, fields in enumerate(layer_fields):
        kind, width, height = fields[0], fields[1], fields[2]
        rect = fields[3:7]
        camera = np.array(fields[7:23], dtype=np.float32)
        quad_count, offset_count = fields[-2], fields[-1]
        q1, o1 = q0 + quad_count, o0 + offset_count
        sl = slice(q0, q1)
        size_log2 = fields_all.size_log2[sl]
        bad = np.flatnonzero(size_log2 > MAX_SIZE_LOG2)
        if bad.size:
            raise ProtocolError(
                f"layer[{i}].quads.size_log2[{int(bad[0])}]: expected 0..{MAX_SIZE_LOG2}, got {size_log2[bad[0]]}"
            )
        flattened = fields_all.flattened[sl]
        non_flattened = int(quad_count - np.count_nonzero(flattened))
        if non_flattened != offset_count:
            raise ProtocolError(
                f"layer[{i}].offset_count: expected {non_flattened} (non-flattened quads), got {offset_count}"
            )
        # What QuadSet checks of its inputs, on views of the decoded columns (normals are unit by construction).
        bad_depth = _first_nonfinite(depth[sl])
        if bad_depth is not None:
            raise ProtocolError(f"layer[{i}]: QuadSet.depth[{bad_depth[0]}]: expected a finite float32, "
                                f"got {depth[sl][bad_depth]}")
        bad_offset = _first_nonfinite(offsets[o0:o1])
        if bad_offset is not None:
            raise ProtocolError(f"layer[{i}]: QuadSet.offsets[{_index_str(bad_offset)}]: expected a finite float16 "
                                f"(|v| <= 65504), got {offsets[o0:o1][bad_offset]}")
        quads = QuadSet._decoded(x=fields_all.x[sl], y=fields_all.y[sl], size_log2=size_log2, flattened=flattened,
                                 alpha=fields_all.alpha[sl], normal=normals[sl], depth=depth[sl],
                                 offsets=offsets[o0:o1])
        try:
            layers.append(
                QuadLayer(kind=LayerKind(kind), width=width, height=height, camera=camera, atlas_rect=rect, quads=quads)
            )
        except ValueError as exc:
            raise ProtocolError(f"layer[{i}]: {exc}") from None
        q0, o0 = q1, o1

    return QuadFrame(layers=layers)
