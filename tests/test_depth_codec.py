"""Tests for the BC4-like inverse-depth codec (protocol.depth)."""
from __future__ import annotations

import struct

import numpy as np
import pytest
import zstandard
from hypothesis import given, settings
from hypothesis import strategies as st

from quadcast.protocol.depth import BLOCK, LEVELS, decode_depth, encode_depth
from quadcast.protocol.errors import ProtocolError


def scene_depth(h: int = 45, w: int = 70, seed: int = 0) -> np.ndarray:
    """A tilted floor, a near box with sharp edges, and sky on top: smooth areas plus discontinuities."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    depth = 2.0 + 40.0 * (1.0 - y / h) ** 3 + 0.01 * rng.random((h, w))
    depth[:h // 4] = np.inf
    depth[h // 3: 2 * h // 3, w // 5: w // 2] = 0.7 + 0.002 * x[h // 3: 2 * h // 3, w // 5: w // 2]
    return depth.astype(np.float32)


def block_ratio(depth: np.ndarray) -> np.ndarray:
    """Per pixel: z_far / z_near over the non-sky pixels of its 8x8 block (1 for sky)."""
    h, w = depth.shape
    out = np.ones((h, w))
    for by in range(0, h, BLOCK):
        for bx in range(0, w, BLOCK):
            blk = depth[by:by + BLOCK, bx:bx + BLOCK].astype(np.float64)
            fin = blk[np.isfinite(blk)]
            if fin.size:
                out[by:by + BLOCK, bx:bx + BLOCK] = fin.max() / fin.min()
    return out


def check_bound(depth: np.ndarray, decoded: np.ndarray) -> None:
    assert decoded.shape == depth.shape and decoded.dtype == np.float32
    sky = np.isinf(depth)
    np.testing.assert_array_equal(np.isinf(decoded), sky)
    rel = np.abs(decoded[~sky].astype(np.float64) - depth[~sky]) / depth[~sky]
    bound = (block_ratio(depth)[~sky] - 1.0) / (2 * LEVELS)
    assert np.all(rel <= bound * (1 + 1e-4) + 2e-7), float((rel - bound).max())


def test_round_trip_error_bound_and_sky():
    depth = scene_depth()
    decoded = decode_depth(encode_depth(depth))
    check_bound(depth, decoded)
    # Smooth blocks are far below 1 %; the documented bound is not vacuous.
    smooth = (block_ratio(depth) < 1.5) & np.isfinite(depth)
    fin = np.isfinite(depth)
    rel = np.zeros(depth.shape)
    rel[fin] = np.abs(decoded[fin] - depth[fin]) / depth[fin]
    assert rel[smooth].max() < 1e-3
    assert rel[fin].max() > 1e-5  # really lossy (8-bit indices), so the test can fail


def test_compresses_and_constant_is_exact():
    depth = scene_depth(90, 160)
    blob = encode_depth(depth)
    assert len(blob) < depth.nbytes / 3
    flat = np.full((16, 24), 3.25, np.float32)
    np.testing.assert_allclose(decode_depth(encode_depth(flat)), flat, rtol=1e-6)
    sky = np.full((9, 9), np.inf, np.float32)
    assert np.all(np.isinf(decode_depth(encode_depth(sky))))


@settings(max_examples=40, deadline=None)
@given(h=st.integers(1, 20), w=st.integers(1, 20), seed=st.integers(0, 2 ** 16),
       near=st.floats(0.05, 5.0), span=st.floats(1.0, 200.0), sky_frac=st.floats(0.0, 1.0))
def test_round_trip_bound_random(h, w, seed, near, span, sky_frac):
    rng = np.random.default_rng(seed)
    depth = (near * span ** rng.random((h, w))).astype(np.float32)
    depth[rng.random((h, w)) < sky_frac] = np.inf
    check_bound(depth, decode_depth(encode_depth(depth, level=1)))


@pytest.mark.parametrize("bad", [np.zeros((4, 4)), -np.ones((4, 4)), np.full((4, 4), np.nan),
                                 np.full((4, 4), -np.inf), np.full((4, 4), 1e31), np.ones((4, 4, 1)), np.ones((0, 4)),
                                 np.ones((4, 4), np.int32)])
def test_encode_rejects_bad_maps(bad):
    with pytest.raises(ValueError):
        encode_depth(bad)


def test_truncated_and_corrupt_blobs_raise_protocol_error():
    blob = encode_depth(scene_depth())
    for n in (0, 3, 15, 16, 20, len(blob) - 1):
        with pytest.raises(ProtocolError):
            decode_depth(blob[:n])
    with pytest.raises(ProtocolError, match="magic"):
        decode_depth(b"XXXX" + blob[4:])
    with pytest.raises(ProtocolError, match="version"):
        decode_depth(blob[:4] + b"\x09" + blob[5:])
    with pytest.raises(ProtocolError, match="trailing"):
        decode_depth(blob + b"\x00")
    with pytest.raises(ProtocolError):  # header size disagrees with the body
        decode_depth(blob[:8] + struct.pack("<II", 80, 45) + blob[16:])
    rng = np.random.default_rng(3)
    for _ in range(30):  # random byte flips in the zstd frame: ProtocolError or a valid map, never anything else
        b = bytearray(blob)
        i = int(rng.integers(16, len(b)))
        b[i] ^= int(rng.integers(1, 256))
        try:
            out = decode_depth(bytes(b))
        except ProtocolError:
            continue
        assert out.shape == (45, 70) and not np.isnan(out).any() and (out > 0).all()
    with pytest.raises(ProtocolError):
        decode_depth("not bytes")  # type: ignore[arg-type]


def test_oversized_and_bomb_blobs_rejected():
    blob = encode_depth(scene_depth())
    with pytest.raises(ProtocolError, match="cap"):
        decode_depth(blob, max_pixels=45 * 70 - 1)
    # A header claiming a huge map is refused before any decompression.
    huge = struct.pack("<4sBBHII", b"QDDP", 1, 8, 0, 100_000, 100_000) + blob[16:]
    with pytest.raises(ProtocolError, match="cap"):
        decode_depth(huge)
    # A zstd frame whose declared size differs from what the header implies is refused.
    body = zstandard.ZstdCompressor().compress(bytes(10_000_000))
    with pytest.raises(ProtocolError, match="declares"):
        decode_depth(blob[:16] + body)
    no_size = zstandard.ZstdCompressor(write_content_size=False).compress(bytes(100))
    with pytest.raises(ProtocolError):
        decode_depth(blob[:16] + no_size)


def test_invalid_block_range_rejected():
    h, w = 8, 8
    body = np.float32([-1.0]).tobytes() + np.float32([2.0]).tobytes() + bytes(64)
    blob = struct.pack("<4sBBHII", b"QDDP", 1, 8, 0, w, h) + zstandard.ZstdCompressor().compress(body)
    with pytest.raises(ProtocolError, match="block"):
        decode_depth(blob)
    body = np.float32([np.nan]).tobytes() + np.float32([2.0]).tobytes() + bytes(64)
    blob = struct.pack("<4sBBHII", b"QDDP", 1, 8, 0, w, h) + zstandard.ZstdCompressor().compress(body)
    with pytest.raises(ProtocolError, match="block"):
        decode_depth(blob)
