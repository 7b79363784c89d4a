"""Tests for protocol.quads: 80-bit quad packing and the columnar zstd quad blob."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
import zstandard
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.quads import (
    BLOB_VERSION,
    HEADER_STRUCT,
    LAYER_STRUCT,
    MAX_SIZE_LOG2,
    NORMAL_MAX_ANGULAR_ERROR,
    OFFSETS_PER_QUAD,
    PACKED_BITS_PER_QUAD,
    LayerKind,
    QuadFrame,
    QuadLayer,
    QuadSet,
    decode_quad_frame,
    encode_quad_frame,
    pack_normals,
    pack_quad_words,
    packed_size_bits_per_quad,
    quad_frame_stats,
    round_mantissa,
    unpack_normals,
    unpack_quad_words,
)

DETERMINISTIC = settings(derandomize=True, deadline=None, database=None, max_examples=60,
                         suppress_health_check=[HealthCheck.filter_too_much, HealthCheck.too_slow])


# ---------------------------------------------------------------------------
# Builders
# ---------------------------------------------------------------------------


def angle_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle (radians) between unit rows of a and b, accurate for small angles."""
    a = np.asarray(a, np.float64)
    b = np.asarray(b, np.float64)
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1))


def random_quads(rng: np.random.Generator, n: int, width: int, height: int) -> QuadSet:
    flattened = rng.random(n) < 0.5
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return QuadSet(
        x=rng.integers(0, width, n),
        y=rng.integers(0, height, n),
        size_log2=rng.integers(0, MAX_SIZE_LOG2 + 1, n),
        flattened=flattened,
        alpha=rng.random(n) < 0.3,
        normal=normal,
        depth=rng.uniform(0.1, 50.0, n),
        offsets=rng.normal(scale=0.05, size=(int((~flattened).sum()), OFFSETS_PER_QUAD)),
    )


def small_frame(seed: int = 0) -> QuadFrame:
    rng = np.random.default_rng(seed)
    layers = [
        QuadLayer(LayerKind.VISIBLE, 64, 48, np.arange(16), (0, 0, 64, 48), random_quads(rng, 5, 64, 48)),
        QuadLayer(LayerKind.HIDDEN, 32, 32, np.ones(16), (64, 0, 32, 32), random_quads(rng, 3, 32, 32)),
    ]
    return QuadFrame(layers=layers)


def split_blob(blob: bytes, layer_count: int) -> tuple[bytes, bytes]:
    """(headers, decompressed payload) of a valid blob."""
    cut = HEADER_STRUCT.size + layer_count * LAYER_STRUCT.size
    return blob[:cut], zstandard.ZstdDecompressor().decompress(blob[cut:])


def rebuild_blob(headers: bytes, raw: bytes) -> bytes:
    """A blob with the given headers and a freshly compressed (possibly tampered) payload."""
    return headers + zstandard.ZstdCompressor(level=3).compress(raw)


def make_header(*, magic=b"QDCQ", version=BLOB_VERSION, flags=0, layer_count=1, payload_size=0) -> bytes:
    return HEADER_STRUCT.pack(magic, version, flags, layer_count, payload_size)


def make_layer(*, kind=0, width=64, height=64, quads=0, offsets=0) -> bytes:
    return LAYER_STRUCT.pack(kind, width, height, 0, 0, width, height, *([0.0] * 16), quads, offsets)


def assert_frames_equal(a: QuadFrame, b: QuadFrame) -> None:
    assert len(a.layers) == len(b.layers)
    for la, lb in zip(a.layers, b.layers):
        assert (la.kind, la.width, la.height, la.atlas_rect) == (lb.kind, lb.width, lb.height, lb.atlas_rect)
        np.testing.assert_array_equal(la.camera.view(np.uint32), lb.camera.view(np.uint32))
        qa, qb = la.quads, lb.quads
        for name in ("x", "y", "size_log2", "flattened", "alpha"):
            np.testing.assert_array_equal(getattr(qa, name), getattr(qb, name), err_msg=name)
            assert getattr(qb, name).dtype == getattr(qa, name).dtype
        np.testing.assert_array_equal(qa.depth.view(np.uint32), qb.depth.view(np.uint32))
        np.testing.assert_array_equal(qa.offsets.view(np.uint16), qb.offsets.view(np.uint16))
        if len(qa):
            assert angle_between(qa.normal, qb.normal).max() <= NORMAL_MAX_ANGULAR_ERROR


# ---------------------------------------------------------------------------
# Hypothesis strategies
# ---------------------------------------------------------------------------


@st.composite
def quad_sets(draw, width: int, height: int, max_n: int = 24) -> QuadSet:
    n = draw(st.integers(0, max_n))
    flattened = draw(hnp.arrays(bool, n))
    raw_normal = draw(hnp.arrays(np.float64, (n, 3), elements=st.floats(-1.0, 1.0)))
    norms = np.linalg.norm(raw_normal, axis=1)
    raw_normal[norms < 1e-3] = (0.0, 0.0, 1.0)
    normal = raw_normal / np.linalg.norm(raw_normal, axis=1, keepdims=True)
    m = int((~flattened).sum())
    return QuadSet(
        x=draw(hnp.arrays(np.uint16, n, elements=st.integers(0, min(width, 4096) - 1))),
        y=draw(hnp.arrays(np.uint16, n, elements=st.integers(0, min(height, 4096) - 1))),
        size_log2=draw(hnp.arrays(np.uint8, n, elements=st.integers(0, MAX_SIZE_LOG2))),
        flattened=flattened,
        alpha=draw(hnp.arrays(bool, n)),
        normal=normal,
        depth=draw(hnp.arrays(np.float32, n, elements=st.floats(width=32, allow_nan=False, allow_infinity=False))),
        offsets=draw(
            hnp.arrays(np.float16, (m, OFFSETS_PER_QUAD),
                       elements=st.floats(width=16, allow_nan=False, allow_infinity=False))
        ),
    )


@st.composite
def quad_layers(draw) -> QuadLayer:
    width = draw(st.integers(1, 5000))
    height = draw(st.integers(1, 5000))
    return QuadLayer(
        kind=draw(st.sampled_from(list(LayerKind))),
        width=width,
        height=height,
        camera=draw(hnp.arrays(np.float32, 16, elements=st.floats(width=32, allow_nan=False, allow_infinity=False))),
        atlas_rect=tuple(draw(st.lists(st.integers(0, 0xFFFF), min_size=4, max_size=4))),
        quads=draw(quad_sets(width, height, max_n=min(24, width * height))),
    )


@st.composite
def quad_frames(draw) -> QuadFrame:
    return QuadFrame(layers=draw(st.lists(quad_layers(), max_size=3)))


# ---------------------------------------------------------------------------
# Round trips and packing
# ---------------------------------------------------------------------------


@DETERMINISTIC
@given(frame=quad_frames(), level=st.sampled_from([1, 3, 9]))
def test_blob_round_trip(frame: QuadFrame, level: int) -> None:
    decoded = decode_quad_frame(encode_quad_frame(frame, level=level))
    assert_frames_equal(frame, decoded)


def test_empty_frame_round_trip() -> None:
    frame = QuadFrame(layers=[])
    assert_frames_equal(frame, decode_quad_frame(encode_quad_frame(frame)))
    layer = QuadLayer(LayerKind.REVEALED, 8, 8, np.zeros(16), (0, 0, 8, 8), QuadSet.empty())
    frame = QuadFrame(layers=[layer])
    assert_frames_equal(frame, decode_quad_frame(bytearray(encode_quad_frame(frame))))


@DETERMINISTIC
@given(hnp.arrays(np.float64, (32, 3), elements=st.floats(-1e6, 1e6)))
def test_normals_within_documented_bound(raw: np.ndarray) -> None:
    norms = np.linalg.norm(raw, axis=1)
    raw = raw[norms > 1e-6]
    if raw.shape[0] == 0:
        return
    theta, phi = pack_normals(raw)
    assert theta.dtype == np.uint8 and phi.dtype == np.uint8
    out = unpack_normals(theta, phi)
    assert out.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(out, axis=1), 1.0, atol=1e-6)
    unit = raw / np.linalg.norm(raw, axis=1, keepdims=True)
    assert angle_between(unit, out).max() <= NORMAL_MAX_ANGULAR_ERROR


def test_normal_bound_is_tight_and_poles_exact() -> None:
    rng = np.random.default_rng(1)
    n = rng.normal(size=(200_000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    err = angle_between(n, unpack_normals(*pack_normals(n)))
    assert err.max() <= NORMAL_MAX_ANGULAR_ERROR
    assert err.max() > 0.9 * NORMAL_MAX_ANGULAR_ERROR  # the documented bound is not loose
    assert math.degrees(NORMAL_MAX_ANGULAR_ERROR) < 0.8
    poles = np.array([[0, 0, 1], [0, 0, -1], [-1, 0, 0]], np.float64)
    theta, phi = pack_normals(poles)
    np.testing.assert_array_equal(theta[:2], [0, 255])
    np.testing.assert_allclose(unpack_normals(theta, phi)[:2], poles[:2], atol=1e-7)
    assert phi[2] == 0  # phi = pi wraps to code 0 (phi = -pi)


def test_pack_normals_rejects_zero_and_bad_shape() -> None:
    with pytest.raises(ValueError, match=r"normal\[1\]"):
        pack_normals([[0, 0, 1], [0, 0, 0]])
    with pytest.raises(ValueError, match="shape"):
        pack_normals([1.0, 0.0, 0.0])


def test_quad_word_bit_layout() -> None:
    quads = QuadSet(
        x=[1, 4095], y=[2, 4095], size_log2=[3, 11], flattened=[True, False], alpha=[True, False],
        normal=[[0, 0, 1], [0, 1, 0]], depth=[1.0, 2.0], offsets=np.zeros((1, 16)),
    )
    words = pack_quad_words(quads)
    assert words.dtype == np.uint32
    assert int(words[0]) == (1 << 31) | (1 << 30) | (3 << 24) | (1 << 12) | 2
    assert int(words[1]) == (11 << 24) | (4095 << 12) | 4095
    fields = unpack_quad_words(words)
    np.testing.assert_array_equal(fields.x, quads.x)
    np.testing.assert_array_equal(fields.y, quads.y)
    np.testing.assert_array_equal(fields.size_log2, quads.size_log2)
    np.testing.assert_array_equal(fields.flattened, quads.flattened)
    np.testing.assert_array_equal(fields.alpha, quads.alpha)


def test_bits_per_quad_is_80() -> None:
    frame = small_frame()
    assert packed_size_bits_per_quad(frame) == PACKED_BITS_PER_QUAD == 80
    stats = quad_frame_stats(frame)
    assert stats.packed_bits_per_quad == 80
    assert stats.quad_count == 8
    assert stats.raw_payload_bytes == 10 * stats.quad_count + 32 * stats.offset_count
    assert stats.total_bytes == len(encode_quad_frame(frame))


# ---------------------------------------------------------------------------
# QuadSet / QuadLayer / QuadFrame validation and helpers
# ---------------------------------------------------------------------------


def quad_kwargs(**overrides):
    kwargs = dict(x=[0, 1], y=[0, 1], size_log2=[0, 1], flattened=[True, False], alpha=[False, True],
                  normal=[[0, 0, 1], [1, 0, 0]], depth=[1.0, 2.0], offsets=np.zeros((1, 16)))
    kwargs.update(overrides)
    return kwargs


@pytest.mark.parametrize(
    "overrides, pattern",
    [
        (dict(x=[0, 4096]), r"QuadSet\.x\[1\].*0\.\.4095.*4096"),
        (dict(y=[-1, 0]), r"QuadSet\.y\[0\]"),
        (dict(x=[0.0, 1.0]), r"QuadSet\.x.*integers"),
        (dict(size_log2=[0, 12]), r"QuadSet\.size_log2\[1\].*0\.\.11.*12"),
        (dict(y=[0, 1, 2]), r"QuadSet\.y.*length 2"),
        (dict(flattened=[2, 0]), r"QuadSet\.flattened\[0\]"),
        (dict(depth=[1.0, np.inf]), r"QuadSet\.depth\[1\].*finite"),
        (dict(depth=[1.0, 1e39]), r"QuadSet\.depth\[1\].*finite"),
        (dict(normal=[[0, 0, 2], [1, 0, 0]]), r"QuadSet\.normal\[0\].*unit"),
        (dict(normal=[[0, 0, 1]]), r"QuadSet\.normal.*shape"),
        (dict(offsets=np.zeros((2, 16))), r"QuadSet\.offsets.*\(1, 16\).*\(2, 16\)"),
        (dict(offsets=np.full((1, 16), 1e6)), r"QuadSet\.offsets\[0,0\].*finite"),
    ],
)
def test_quad_set_rejects_bad_columns(overrides, pattern) -> None:
    QuadSet(**quad_kwargs())  # the baseline is valid
    with pytest.raises(ValueError, match=pattern):
        QuadSet(**quad_kwargs(**overrides))


def test_quad_set_dtypes_and_empty() -> None:
    q = QuadSet(**quad_kwargs())
    assert (q.x.dtype, q.y.dtype, q.size_log2.dtype) == (np.uint16, np.uint16, np.uint8)
    assert (q.flattened.dtype, q.alpha.dtype) == (bool, bool)
    assert (q.normal.dtype, q.depth.dtype, q.offsets.dtype) == (np.float32, np.float32, np.float16)
    np.testing.assert_array_equal(q.offset_index, [-1, 0])
    empty = QuadSet.empty()
    assert len(empty) == 0 and empty.offsets.shape == (0, 16) and empty.normal.shape == (0, 3)
    assert len(QuadSet.concatenate([])) == 0


@DETERMINISTIC
@given(quads=quad_sets(4096, 4096, max_n=30), data=st.data())
def test_select_and_concatenate_keep_offsets_consistent(quads: QuadSet, data) -> None:
    n = len(quads)
    mask = data.draw(hnp.arrays(bool, n))
    picked = quads.select(mask)
    assert len(picked) == int(mask.sum())
    rows = quads.offset_index[mask]
    np.testing.assert_array_equal(picked.offsets.view(np.uint16), quads.offsets[rows[rows >= 0]].view(np.uint16))
    np.testing.assert_array_equal(picked.depth, quads.depth[mask])

    order = data.draw(st.permutations(range(n))) if n else []
    shuffled = quads.select(np.asarray(order, dtype=np.int64))
    for i, j in enumerate(order):
        a, b = shuffled.offset_index[i], quads.offset_index[j]
        assert (a < 0) == (b < 0)
        if a >= 0:
            np.testing.assert_array_equal(shuffled.offsets[a].view(np.uint16), quads.offsets[b].view(np.uint16))

    k = data.draw(st.integers(0, n))
    joined = QuadSet.concatenate([quads.select(np.arange(k)), quads.select(np.arange(k, n))])
    for name in ("x", "y", "size_log2", "flattened", "alpha", "normal", "depth", "offsets"):
        np.testing.assert_array_equal(getattr(joined, name), getattr(quads, name), err_msg=name)


def test_select_rejects_wrong_mask_length() -> None:
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        QuadSet(**quad_kwargs()).select(np.array([True]))


def test_layer_and_frame_validation() -> None:
    quads = QuadSet(**quad_kwargs(x=[0, 10]))
    with pytest.raises(ValueError, match=r"quads\.x\[1\].*width 10.*10"):
        QuadLayer(LayerKind.VISIBLE, 10, 10, np.zeros(16), (0, 0, 1, 1), quads)
    with pytest.raises(ValueError, match="camera"):
        QuadLayer(LayerKind.VISIBLE, 16, 16, np.zeros(15), (0, 0, 1, 1), quads)
    with pytest.raises(ValueError, match=r"camera\[3\].*finite"):
        QuadLayer(LayerKind.VISIBLE, 16, 16, np.array([0, 0, 0, np.nan] + [0] * 12), (0, 0, 1, 1), quads)
    with pytest.raises(ValueError, match=r"atlas_rect\[2\].*65536"):
        QuadLayer(LayerKind.VISIBLE, 16, 16, np.zeros(16), (0, 0, 65536, 1), quads)
    with pytest.raises(ValueError, match="kind"):
        QuadLayer(9, 16, 16, np.zeros(16), (0, 0, 1, 1), quads)
    layer = QuadLayer(LayerKind.VISIBLE, 16, 16, np.zeros(16), (0, 0, 1, 1), quads)
    with pytest.raises(ValueError, match="at most 16 layers, got 17"):
        QuadFrame([layer] * 17)
    with pytest.raises(ValueError, match=r"layers\[0\]: expected a QuadLayer"):
        QuadFrame(["not a layer"])


# ---------------------------------------------------------------------------
# Hostile input
# ---------------------------------------------------------------------------


def test_every_truncation_raises_protocol_error() -> None:
    blob = encode_quad_frame(small_frame())
    decode_quad_frame(blob)
    for cut in range(len(blob)):
        with pytest.raises(ProtocolError):
            decode_quad_frame(blob[:cut])


def test_trailing_bytes_rejected() -> None:
    blob = encode_quad_frame(small_frame())
    with pytest.raises(ProtocolError, match="payload: 1 trailing bytes after the zstd frame"):
        decode_quad_frame(blob + b"\x00")
    empty = encode_quad_frame(QuadFrame([]))
    with pytest.raises(ProtocolError, match="1 trailing bytes"):
        decode_quad_frame(empty + b"\x00")


def test_random_byte_flips_never_crash() -> None:
    frame = small_frame(3)
    blob = encode_quad_frame(frame)
    headers, raw = split_blob(blob, len(frame.layers))
    rng = np.random.default_rng(1234)
    outcomes = {"error": 0, "ok": 0}
    for trial in range(600):
        if trial % 2 == 0:  # flip bytes of the blob as sent
            target = bytearray(blob)
        else:  # flip bytes of headers/raw columns, then recompress (exercises post-decompression checks)
            target = bytearray(headers + raw)
        for _ in range(int(rng.integers(1, 4))):
            i = int(rng.integers(0, len(target)))
            target[i] ^= int(rng.integers(1, 256))
        if trial % 2 == 1:
            target = bytearray(rebuild_blob(bytes(target[: len(headers)]), bytes(target[len(headers):])))
        try:
            result = decode_quad_frame(bytes(target))
        except ProtocolError:
            outcomes["error"] += 1
        else:
            assert isinstance(result, QuadFrame)
            outcomes["ok"] += 1
    assert outcomes["error"] > 0 and outcomes["ok"] > 0


@pytest.mark.parametrize(
    "tamper, pattern",
    [
        ("size_log2", r"layer\[0\]\.quads\.size_log2\[0\].*0\.\.11.*12"),
        ("x_outside", r"layer\[0\].*quads\.x\[0\].*width 64"),
        ("nan_depth", r"layer\[0\].*depth\[0\].*finite"),
        ("flattened_flip", r"layer\[0\]\.offset_count: expected"),
        ("inf_offset", r"layer\[0\].*offsets\[0,0\].*finite"),
    ],
)
def test_decoded_columns_are_validated(tamper: str, pattern: str) -> None:
    frame = small_frame(5)
    headers, raw = split_blob(encode_quad_frame(frame), len(frame.layers))
    n, m = frame.quad_count, frame.offset_count * 16
    # Multi-byte columns are byte planes: un-shuffle them, tamper, shuffle back.
    def column(at, dtype, count):
        item = np.dtype(dtype).itemsize
        return np.frombuffer(raw, np.uint8, count * item, at).reshape(item, count).T.copy().view(dtype).ravel()

    def put(at, values):
        raw[at:at + values.nbytes] = np.ascontiguousarray(values.view(np.uint8).reshape(len(values), -1).T).tobytes()

    words, depth, offsets = column(0, "<u4", n), column(6 * n, "<f4", n), column(10 * n, "<f2", m)
    raw = bytearray(raw)
    if tamper == "size_log2":
        words[0] = (words[0] & ~np.uint32(0x3F << 24)) | np.uint32(12 << 24)
    elif tamper == "x_outside":
        words[0] = (words[0] & ~np.uint32(0xFFF << 12)) | np.uint32(64 << 12)
    elif tamper == "flattened_flip":
        words[0] ^= np.uint32(1 << 31)
    elif tamper == "nan_depth":
        depth[0] = np.nan
    elif tamper == "inf_offset":
        assert frame.offset_count > 0
        offsets[0] = np.inf
    put(0, words)
    put(6 * n, depth)
    put(10 * n, offsets)
    with pytest.raises(ProtocolError, match=pattern):
        decode_quad_frame(rebuild_blob(headers, bytes(raw)))


@pytest.mark.parametrize(
    "header, pattern",
    [
        (make_header(magic=b"QDCX"), r"header\.magic: expected b'QDCQ', got b'QDCX'"),
        (make_header(version=BLOB_VERSION + 1), rf"header\.version: expected {BLOB_VERSION}, got {BLOB_VERSION + 1}"),
        (make_header(flags=4), r"header\.flags"),
        (make_header(layer_count=17), r"header\.layer_count: expected at most 16, got 17"),
        (make_header(layer_count=1) + make_layer(kind=9), r"layer\[0\]\.kind.*got 9"),
        (make_header(layer_count=1) + make_layer(width=0), r"layer\[0\].*0x64"),
        (make_header(layer_count=1, payload_size=42) + make_layer(quads=1, offsets=2),
         r"layer\[0\]\.offset_count: expected <= quad count 1, got 2"),
        (make_header(layer_count=1, payload_size=11) + make_layer(quads=1),
         r"header\.payload_size: expected 10.*got 11"),
    ],
)
def test_bad_headers_named(header: bytes, pattern: str) -> None:
    blob = header + zstandard.ZstdCompressor().compress(b"")
    with pytest.raises(ProtocolError, match=pattern):
        decode_quad_frame(blob)


def test_non_bytes_input_rejected() -> None:
    with pytest.raises(ProtocolError, match="bytes-like"):
        decode_quad_frame("QDCQ")  # type: ignore[arg-type]


def _gigabyte_of_zeros_frame(size: int = 1 << 30) -> bytes:
    """A ~32 KB zstd frame that declares and inflates to `size` zero bytes."""
    cobj = zstandard.ZstdCompressor(level=1).compressobj(size=size)
    chunk = bytes(1 << 20)
    parts = [cobj.compress(chunk) for _ in range(size // len(chunk))]
    parts.append(cobj.flush())
    return b"".join(parts)


@pytest.fixture(scope="module")
def gigabyte_bomb() -> bytes:
    bomb = _gigabyte_of_zeros_frame()
    assert zstandard.frame_content_size(bomb) == 1 << 30
    return bomb


def _peak_python_allocation(fn) -> int:
    tracemalloc.start()
    try:
        fn()
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return peak


def _decode_expecting_error(blob: bytes, pattern: str, **limits) -> None:
    with pytest.raises(ProtocolError, match=pattern):
        decode_quad_frame(blob, **limits)


def test_oversized_counts_rejected_before_decompression(gigabyte_bomb: bytes) -> None:
    # 1 GiB of zeros claimed by consistent header counts: refused from the counts alone.
    quads = (1 << 30) // 10
    header = make_header(layer_count=1, payload_size=10 * quads) + make_layer(width=0xFFFF, height=0xFFFF, quads=quads)
    blob = header + gigabyte_bomb
    peak = _peak_python_allocation(lambda: _decode_expecting_error(blob, r"max_quads 8388608"))
    assert peak < 4 << 20
    peak = _peak_python_allocation(
        lambda: _decode_expecting_error(blob, r"exceeds max_bytes", max_quads=1 << 28)
    )
    assert peak < 4 << 20
    # Per-layer counts summed over layers also hit the cap.
    many = make_header(layer_count=2, payload_size=0) + make_layer(quads=5) + make_layer(quads=6)
    _decode_expecting_error(many + gigabyte_bomb, r"layer\[1\]\.quad_count: total quads 11 exceeds max_quads 10",
                            max_quads=10)


def test_declared_sizes_must_be_what_the_receiver_asked_for(gigabyte_bomb: bytes) -> None:
    # Issue 13: a small blob declaring 8 Mi quads in a 1-pixel-high layer; refused from its headers alone.
    quads = 1 << 23
    tall = make_header(layer_count=1, payload_size=10 * quads) + make_layer(width=0xFFFF, height=1, quads=quads)
    peak = _peak_python_allocation(lambda: _decode_expecting_error(tall + gigabyte_bomb, r"at most one per pixel"))
    assert peak < 4 << 20
    fits = make_header(layer_count=1, payload_size=10 * 100) + make_layer(width=320, height=180, quads=100)
    _decode_expecting_error(fits + gigabyte_bomb, r"layer\[0\]: 320x180, expected the 64x36 asked for", size=(64, 36))
    wide = make_header(layer_count=1, payload_size=10) + make_layer(kind=int(LayerKind.WIDE), width=66, height=36,
                                                                    quads=1)
    _decode_expecting_error(wide + gigabyte_bomb, r"wide layer of 66x36, larger than the 64x36", size=(64, 36))
    # a frame of the right sizes decodes (the wide layer smaller), and into views of its columns, not copies
    rng = np.random.default_rng(3)
    frame = QuadFrame([QuadLayer(LayerKind.VISIBLE, 64, 36, np.zeros(16), (0, 0, 64, 36), random_quads(rng, 9, 64, 36)),
                       QuadLayer(LayerKind.WIDE, 32, 18, np.zeros(16), (0, 36, 32, 18), QuadSet.empty())])
    assert_frames_equal(frame, decode_quad_frame(encode_quad_frame(frame), size=(64, 36)))


def test_decoding_needs_about_its_output_in_memory() -> None:
    rng = np.random.default_rng(1)
    w, h = 256, 128
    n = w * h
    flat = rng.random(n) < 0.5
    normal = rng.normal(size=(n, 3))
    quads = QuadSet(x=np.tile(np.arange(w), h), y=np.repeat(np.arange(h), w), size_log2=np.zeros(n, int),
                    flattened=flat, alpha=np.zeros(n, bool), normal=normal / np.linalg.norm(normal, axis=1)[:, None],
                    depth=rng.random(n) + 1, offsets=rng.random((int((~flat).sum()), 16)))
    blob = encode_quad_frame(QuadFrame([QuadLayer(LayerKind.VISIBLE, w, h, np.zeros(16), (0, 0, w, h), quads)]))
    decode_quad_frame(blob, size=(w, h))       # warm the normal table
    out = {}
    peak = _peak_python_allocation(lambda: out.setdefault("f", decode_quad_frame(blob, size=(w, h))))
    q = out["f"].layers[0].quads
    output = sum(getattr(q, c).nbytes for c in ("x", "y", "size_log2", "flattened", "alpha", "normal", "depth",
                                                "offsets"))
    assert peak < 2.5 * output, (peak, output)


def test_zstd_bomb_behind_small_header_rejected(gigabyte_bomb: bytes) -> None:
    header = make_header(layer_count=1, payload_size=30) + make_layer(quads=3)
    blob = header + gigabyte_bomb
    peak = _peak_python_allocation(
        lambda: _decode_expecting_error(blob, r"declares 1073741824 bytes, expected 30")
    )
    assert peak < 4 << 20


def test_zstd_bomb_lying_about_its_size_rejected(gigabyte_bomb: bytes) -> None:
    # Rewrite the bomb's declared content size to 30 bytes; libzstd must stop at the declared size.
    fhd = gigabyte_bomb[4]
    assert fhd >> 6 == 2 and not fhd & 0x20 and not fhd & 0x03  # 4-byte size, window byte, no dict id
    liar = gigabyte_bomb[:6] + (30).to_bytes(4, "little") + gigabyte_bomb[10:]
    assert zstandard.frame_content_size(liar) == 30
    blob = make_header(layer_count=1, payload_size=30) + make_layer(quads=3) + liar
    peak = _peak_python_allocation(lambda: _decode_expecting_error(blob, r"zstd decompression failed"))
    assert peak < 4 << 20
    # Same for a frame declaring zero bytes behind an empty frame header.
    zero_liar = gigabyte_bomb[:6] + (0).to_bytes(4, "little") + gigabyte_bomb[10:]
    blob = make_header(layer_count=0, payload_size=0) + zero_liar
    peak = _peak_python_allocation(lambda: _decode_expecting_error(blob, r"payload"))
    assert peak < 4 << 20


def test_zstd_frame_without_content_size_rejected() -> None:
    payload = zstandard.ZstdCompressor(write_content_size=False).compress(bytes(30))
    blob = make_header(layer_count=1, payload_size=30) + make_layer(quads=3) + payload
    _decode_expecting_error(blob, r"must declare its content size")


# ---------------------------------------------------------------------------
# Columnar layout
# ---------------------------------------------------------------------------


def smooth_frame() -> QuadFrame:
    """A 64x64 grid of 8x8-pixel quads on a smooth curved surface (normals and depths vary slowly)."""
    j, i = np.mgrid[0:64, 0:64]
    i, j = i.ravel(), j.ravel()
    u, v = (i - 32) / 64.0, (j - 32) / 64.0
    normal = np.stack([0.4 * u, 0.4 * v, np.ones_like(u)], axis=1)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    n = i.size
    quads = QuadSet(
        x=8 * i, y=8 * j, size_log2=np.full(n, 3), flattened=np.ones(n, bool), alpha=np.zeros(n, bool),
        normal=normal, depth=5.0 + 0.5 * u + 0.25 * v + 0.2 * (u * u + v * v),
        offsets=np.zeros((0, 16)),
    )
    layer = QuadLayer(LayerKind.VISIBLE, 512, 512, np.zeros(16), (0, 0, 512, 512), quads)
    return QuadFrame(layers=[layer])


def test_columnar_layout_beats_interleaved() -> None:
    frame = smooth_frame()
    quads = frame.layers[0].quads
    theta, phi = pack_normals(quads.normal)
    records = np.empty(len(quads), dtype=[("word", "<u4"), ("theta", "u1"), ("phi", "u1"), ("depth", "<f4")])
    records["word"] = pack_quad_words(quads)
    records["theta"], records["phi"], records["depth"] = theta, phi, quads.depth
    assert records.itemsize * 8 == PACKED_BITS_PER_QUAD
    compressor = zstandard.ZstdCompressor(level=3, write_content_size=True, write_checksum=True)
    interleaved = len(compressor.compress(records.tobytes()))
    stats = quad_frame_stats(frame, level=3)
    assert stats.raw_payload_bytes == records.nbytes
    assert stats.compressed_payload_bytes < 0.9 * interleaved, (stats.compressed_payload_bytes, interleaved)


# ---------------------------------------------------------------------------
# Depths rounded on the wire
# ---------------------------------------------------------------------------


@DETERMINISTIC
@given(hnp.arrays(np.float32, 64, elements=st.floats(-2.0 ** 127, 2.0 ** 127, width=32, allow_subnormal=False)),
       st.integers(1, 23))
def test_round_mantissa_is_nearest_within_its_bound(depth: np.ndarray, bits: int) -> None:
    rounded = round_mantissa(depth, bits)
    assert rounded.dtype == np.float32 and np.all(np.isfinite(rounded))
    assert not np.any(rounded.view(np.uint32) & np.uint32((1 << (23 - bits)) - 1))
    d = depth.astype(np.float64)
    assert np.all(np.abs(rounded - d) <= np.abs(d) * 2.0 ** -(bits + 1) * (1 + 1e-12))
    if bits == 23:
        assert np.array_equal(rounded, depth)


def test_with_depth_bits_rounds_only_the_depths() -> None:
    quads = smooth_frame().layers[0].quads
    rounded = quads.with_depth_bits(7)
    assert np.array_equal(rounded.depth, round_mantissa(quads.depth, 7))
    assert not np.array_equal(rounded.depth, quads.depth)
    for name in ("x", "y", "size_log2", "flattened", "alpha", "normal", "offsets"):
        assert np.array_equal(getattr(rounded, name), getattr(quads, name))


def test_round_mantissa_rejects_a_bad_bit_count() -> None:
    huge = np.array([np.finfo(np.float32).max], np.float32)
    assert round_mantissa(huge, 4)[0] == huge[0]          # would round past the largest float32: kept
    for bad in (0, 24, 2.5, True):
        with pytest.raises(ValueError, match="depth_bits"):
            round_mantissa(np.ones(3, np.float32), bad)


def test_rounded_depths_decode_as_sent_and_make_the_blob_smaller() -> None:
    frame = smooth_frame()
    rng = np.random.default_rng(3)           # rendered depths: a smooth surface with float noise in the low bits
    quads = frame.layers[0].quads
    noisy = QuadSet(x=quads.x, y=quads.y, size_log2=quads.size_log2, flattened=quads.flattened, alpha=quads.alpha,
                    normal=quads.normal, depth=quads.depth * (1 + rng.normal(0, 1e-6, len(quads))).astype(np.float32),
                    offsets=quads.offsets)
    frame = QuadFrame([QuadLayer(LayerKind.VISIBLE, 512, 512, np.zeros(16), (0, 0, 512, 512), noisy)])
    exact, rounded = encode_quad_frame(frame), encode_quad_frame(frame, depth_bits=12)
    decoded = decode_quad_frame(rounded).layers[0].quads
    assert np.array_equal(decoded.depth, round_mantissa(noisy.depth, 12))
    assert np.array_equal(decoded.x, noisy.x) and np.array_equal(decoded.offsets, noisy.offsets)
    assert len(rounded) < 0.85 * len(exact), (len(rounded), len(exact))
    assert_frames_equal(frame, decode_quad_frame(exact))
