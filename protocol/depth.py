"""A BC4-like codec for the depth maps MeshWarp streams next to its colour video, sans-I/O (numpy + zstd).

What is stored is *inverse* depth ``1/z`` (z = linear view depth in metres), not z: inverse depth is what a
perspective projection is linear in, and quantising it spends the levels where they matter, near the camera.

The map is split into 8x8 blocks (edge blocks padded with sky). Each block stores the minimum and maximum inverse
depth of its non-sky pixels as float32, and each pixel an 8-bit index: ``0..254`` interpolate linearly between the
block's min and max (255 levels instead of BC4's 8), ``255`` is reserved for sky (``z = inf``). The three planes
(mins, maxs, indices as a padded raster) are then zstd-compressed.

Error bound. Rounding to the nearest of 255 levels gives, per pixel, ``|1/z' - 1/z| <= (max - min) / 508`` with
max/min the block's inverse-depth extremes, hence a relative depth error
``|z' - z| / z <= (r - 1) / 508`` where ``r = z_far / z_near`` is the ratio of the block's farthest to its nearest
non-sky depth. A smooth surface (r <= 1.5) is therefore within 0.1 %; a block straddling a 1 m / 100 m
discontinuity can be off by up to ~20 % on its far side, like BC4. Sky is exact.

Blob layout (little-endian): header ``"QDDP"``, version u8, block size u8, flags u16 (0), width u32, height u32,
then one zstd frame (with its content size) of ``mins f32[nb] | maxs f32[nb] | indices u8[Hp*Wp]``, nb being the
block count and Hp x Wp the size padded to a multiple of 8.
"""
from __future__ import annotations

import struct

import numpy as np
import zstandard

from quadcast.protocol.compression import decompress_exact
from quadcast.protocol.errors import ProtocolError

__all__ = ["encode_depth", "decode_depth", "DEPTH_MAGIC", "DEPTH_VERSION", "BLOCK", "LEVELS", "SKY_CODE",
           "DEFAULT_MAX_DEPTH_PIXELS"]

DEPTH_MAGIC = b"QDDP"
DEPTH_VERSION = 1
BLOCK = 8                 # block edge in pixels
SKY_CODE = 255            # index reserved for "nothing hit" (z = inf)
LEVELS = SKY_CODE - 1     # indices 0..254: 255 levels, 254 steps between block min and max
DEFAULT_MAX_DEPTH_PIXELS = 4096 * 4096
MAX_FINITE_DEPTH = 1e30  # metres; larger finite depths are refused (use inf for sky)
_MIN_INV = 1e-31          # smallest inverse depth a block with geometry may hold (below 1 / MAX_FINITE_DEPTH)
_HEADER = struct.Struct("<4sBBHII")


def _padded(width: int, height: int) -> tuple[int, int]:
    return -(-height // BLOCK) * BLOCK, -(-width // BLOCK) * BLOCK


def _body_size(width: int, height: int) -> int:
    hp, wp = _padded(width, height)
    blocks = (hp // BLOCK) * (wp // BLOCK)
    return 8 * blocks + hp * wp


def _to_blocks(img: np.ndarray) -> np.ndarray:
    """(Hp, Wp) -> (Hp/8, Wp/8, 64)."""
    hp, wp = img.shape
    return img.reshape(hp // BLOCK, BLOCK, wp // BLOCK, BLOCK).transpose(0, 2, 1, 3).reshape(
        hp // BLOCK, wp // BLOCK, BLOCK * BLOCK)


def _from_blocks(blocks: np.ndarray) -> np.ndarray:
    bh, bw, _ = blocks.shape
    return blocks.reshape(bh, bw, BLOCK, BLOCK).transpose(0, 2, 1, 3).reshape(bh * BLOCK, bw * BLOCK)


def encode_depth(depth: np.ndarray, level: int = 3) -> bytes:
    """Compress a linear depth map (H, W) in metres, ``inf`` where nothing was hit, into a depth blob.

    Raises ValueError for a map that is not 2-D, empty, or holds NaN, -inf, zero or negative depths.
    """
    d = np.asarray(depth)
    if d.ndim != 2 or d.size == 0:
        raise ValueError(f"encode_depth: expected a non-empty (H, W) depth map, got shape {d.shape}")
    if not np.issubdtype(d.dtype, np.floating):
        raise ValueError(f"encode_depth: expected float depths in metres, got dtype {d.dtype}")
    if not 1 <= int(level) <= 22:
        raise ValueError(f"encode_depth: zstd level must be in 1..22, got {level}")
    height, width = d.shape
    if width > 0xFFFFFFFF or height > 0xFFFFFFFF:
        raise ValueError(f"encode_depth: {width}x{height} is too large")
    d = d.astype(np.float64)
    sky = np.isposinf(d)
    bad = ~sky & ~((d > 0) & (d <= MAX_FINITE_DEPTH))  # NaN, -inf, <= 0, absurdly far
    if bad.any():
        y, x = np.argwhere(bad)[0]
        raise ValueError(f"encode_depth: depth[{y}, {x}] = {d[y, x]}; depths must be in (0, {MAX_FINITE_DEPTH:g}] "
                         "metres or +inf (sky)")
    inv = np.where(sky, 0.0, 1.0 / np.where(sky, 1.0, d))
    if not np.all(np.isfinite(inv.astype(np.float32))):
        raise ValueError("encode_depth: a depth is so small that its inverse overflows float32")

    hp, wp = _padded(width, height)
    inv_p = np.zeros((hp, wp))
    sky_p = np.ones((hp, wp), bool)
    inv_p[:height, :width], sky_p[:height, :width] = inv, sky
    inv_b, sky_b = _to_blocks(inv_p), _to_blocks(sky_p)

    lo = np.where(sky_b, np.inf, inv_b).min(axis=-1)
    hi = np.where(sky_b, -np.inf, inv_b).max(axis=-1)
    all_sky = ~np.isfinite(lo)
    lo[all_sky] = hi[all_sky] = 0.0
    # float32 extremes that still bracket every value of the block, so indices never clip.
    lo32, hi32 = lo.astype(np.float32), hi.astype(np.float32)
    lo32 = np.where(lo32 > lo, np.nextafter(lo32, np.float32(-np.inf)), lo32).astype(np.float32)
    hi32 = np.where(hi32 < hi, np.nextafter(hi32, np.float32(np.inf)), hi32).astype(np.float32)
    lo32 = np.maximum(lo32, np.float32(0))

    span = (hi32.astype(np.float64) - lo32)[..., None]
    t = np.divide(inv_b - lo32[..., None], span, out=np.zeros_like(inv_b), where=span > 0)
    idx = np.clip(np.rint(t * LEVELS), 0, LEVELS).astype(np.uint8)
    idx[sky_b] = SKY_CODE

    body = lo32.tobytes() + hi32.tobytes() + _from_blocks(idx).tobytes()
    comp = zstandard.ZstdCompressor(level=int(level), write_content_size=True).compress(body)
    return _HEADER.pack(DEPTH_MAGIC, DEPTH_VERSION, BLOCK, 0, width, height) + comp


_CHUNK_PIXELS = 1 << 16
"""Most pixels decoded at a time (whole block rows; at most an eighth of the map): the float64 temporaries
(~40 bytes a pixel) stay a fraction of the output."""


def decode_depth(blob: bytes, max_pixels: int = DEFAULT_MAX_DEPTH_PIXELS,
                 size: tuple[int, int] | None = None) -> np.ndarray:
    """A depth blob -> float32 (H, W) linear depth in metres, ``inf`` for sky.

    ``size`` is the (width, height) the receiver asked for: a blob of another size is refused before anything
    is decompressed, as is one whose size padded to whole blocks exceeds `max_pixels`. Decoding then needs the
    output, the decompressed body (about a quarter of the output) and a bounded working set.

    Any defect (bad magic/version/block size, a size over `max_pixels` or other than `size`, a truncated or
    corrupt zstd frame, a decompressed size other than the header implies, trailing bytes, invalid block
    extremes) raises ProtocolError.
    """
    if not isinstance(blob, (bytes, bytearray, memoryview)):
        raise ProtocolError(f"depth blob: expected bytes, got {type(blob).__name__}")
    blob = memoryview(blob).cast("B")
    if len(blob) < _HEADER.size:
        raise ProtocolError(f"depth blob: truncated header ({len(blob)} of {_HEADER.size} bytes)")
    magic, version, block, flags, width, height = _HEADER.unpack_from(blob)
    if magic != DEPTH_MAGIC:
        raise ProtocolError(f"depth blob: bad magic {magic!r}, expected {DEPTH_MAGIC!r}")
    if version != DEPTH_VERSION:
        raise ProtocolError(f"depth blob: version {version} is not supported (expected {DEPTH_VERSION})")
    if block != BLOCK:
        raise ProtocolError(f"depth blob: block size {block}, expected {BLOCK}")
    if flags != 0:
        raise ProtocolError(f"depth blob: flags {flags:#x}, expected 0")
    if width == 0 or height == 0:
        raise ProtocolError(f"depth blob: empty size {width}x{height}")
    if size is not None and (width, height) != tuple(size):
        raise ProtocolError(f"depth blob: {width}x{height}, expected the {size[0]}x{size[1]} asked for")
    hp, wp = _padded(width, height)
    if width * height > max_pixels or hp * wp > max_pixels:
        raise ProtocolError(f"depth blob: {width}x{height} (padded to {wp}x{hp}) exceeds the cap of {max_pixels} "
                            f"pixels")

    body = decompress_exact(blob[_HEADER.size:], _body_size(width, height), f"depth blob ({width}x{height})")

    bh, bw = hp // BLOCK, wp // BLOCK
    nb = bh * bw
    lo_all = np.frombuffer(body, np.float32, nb, 0).reshape(bh, bw)
    hi_all = np.frombuffer(body, np.float32, nb, 4 * nb).reshape(bh, bw)
    blocks = np.frombuffer(body, np.uint8, hp * wp, 8 * nb).reshape(bh, BLOCK, bw, BLOCK)   # a view
    out = np.empty((height, width), np.float32)
    rows = max(1, min(_CHUNK_PIXELS, hp * wp // 8) // (BLOCK * wp))     # block rows per chunk
    for r0 in range(0, bh, rows):
        r1 = min(bh, r0 + rows)
        with np.errstate(invalid="ignore"):  # signalling NaNs in a corrupt blob: rejected just below
            lo, hi = lo_all[r0:r1].astype(np.float64), hi_all[r0:r1].astype(np.float64)
        idx = blocks[r0:r1]
        sky = idx == SKY_CODE
        has_geometry = ~sky.all(axis=(1, 3))
        ok = np.isfinite(lo) & np.isfinite(hi) & (lo <= hi) & (lo >= 0) & (~has_geometry | (lo >= _MIN_INV))
        if not ok.all():
            by, bx = np.argwhere(~ok)[0]
            raise ProtocolError(f"depth blob: block ({r0 + by}, {bx}) has invalid inverse-depth range "
                                f"[{lo[by, bx]}, {hi[by, bx]}]")
        inv = lo[:, None, :, None] + idx * ((hi - lo) / LEVELS)[:, None, :, None]
        with np.errstate(divide="ignore"):
            depth = np.where(sky, np.inf, 1.0 / np.where(sky, 1.0, inv))
        y0, y1 = r0 * BLOCK, min(height, r1 * BLOCK)
        out[y0:y1] = depth.reshape(-1, wp)[:y1 - y0, :width]
    return out
