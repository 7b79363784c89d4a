"""protocol.compression: one zstd frame of a known size, decompressed with bounded memory."""
import tracemalloc

import pytest
import zstandard

from quadcast.protocol.compression import decompress_exact, window_limit
from quadcast.protocol.errors import ProtocolError

DATA = bytes(range(256)) * 40  # 10240 bytes


def frame(data: bytes = DATA, **options) -> bytes:
    return zstandard.ZstdCompressor(**options).compress(data)


def test_round_trip_and_empty_frame():
    assert decompress_exact(frame(), len(DATA), "blob") == DATA
    assert decompress_exact(memoryview(frame()), len(DATA), "blob") == DATA
    assert decompress_exact(frame(b""), 0, "blob") == b""


@pytest.mark.parametrize("data, expected, pattern", [
    (b"", 10, r"part: missing zstd frame"),
    (b"\x28\xb5", 10, r"part: invalid or truncated zstd frame header"),
    (b"not zstd at all", 10, r"part: invalid or truncated zstd frame header"),
    (frame(write_content_size=False), len(DATA), r"part: zstd frame must declare its content size"),
    (frame(), len(DATA) + 1, rf"part: zstd frame declares {len(DATA)} bytes, expected {len(DATA) + 1}"),
    (frame() + b"\x00\x01", len(DATA), r"part: 2 trailing bytes after the zstd frame"),
    (frame() + frame(), len(DATA), r"part: \d+ trailing bytes after the zstd frame"),
    (frame(b"") + b"\x00", 0, r"part: 1 trailing bytes after the zstd frame"),
    (frame()[:-3], len(DATA), r"part: truncated zstd frame \(\d+ of 10240 bytes decompressed\)"),
    ("text", 4, r"part: expected bytes-like data, got str"),
])
def test_defects_are_named(data, expected, pattern):
    with pytest.raises(ProtocolError, match=pattern):
        decompress_exact(data, expected, "part")


def test_every_truncation_is_refused():
    data = frame(DATA, write_checksum=True)
    for cut in range(len(data)):
        with pytest.raises(ProtocolError, match="^part: "):
            decompress_exact(data[:cut], len(DATA), "part")


def test_corrupt_frames_raise_protocol_error_or_decode_exactly():
    data = frame(DATA, write_checksum=True)
    for i in range(len(data)):
        bad = bytearray(data)
        bad[i] ^= 0x5A
        try:
            out = decompress_exact(bytes(bad), len(DATA), "part")
        except ProtocolError as exc:
            assert str(exc).startswith("part: ")
        else:
            assert len(out) == len(DATA)


def test_window_limit_is_a_small_multiple_of_the_size():
    assert window_limit(0) == window_limit(1) == window_limit(1000) == 1 << 20
    assert window_limit((1 << 20) + 1) == 1 << 21
    assert window_limit(3 << 20) == 1 << 22
    assert window_limit(1 << 40) == 1 << 27
    for n in (1, 5000, 1 << 20, (1 << 20) + 1, 3 << 20, 100 << 20):
        assert window_limit(n) >= n or window_limit(n) == 1 << 27
        assert window_limit(n) <= max(1 << 20, 2 * n)


def test_frame_asking_for_a_large_window_is_refused():
    # An 8 MiB frame with a 4 MiB window whose header is rewritten to declare 64 KiB: the window is refused (1 MiB
    # is the most allowed for 64 KiB) before anything is decompressed.
    params = zstandard.ZstdCompressionParameters.from_level(1, window_log=22)
    cobj = zstandard.ZstdCompressor(compression_params=params).compressobj(size=8 << 20)
    data = cobj.compress(bytes(8 << 20)) + cobj.flush()
    assert data[4] >> 6 == 2 and not data[4] & 0x23  # 4-byte content size after a window byte, no dictionary
    data = data[:6] + (64 << 10).to_bytes(4, "little") + data[10:]
    assert zstandard.get_frame_parameters(data).window_size == 4 << 20
    with pytest.raises(ProtocolError, match=r"part: zstd frame needs a 4194304-byte window, more than the 1048576"):
        decompress_exact(data, 64 << 10, "part")


def _bomb(size: int = 256 << 20) -> bytes:
    """A small frame that declares and inflates to `size` zero bytes."""
    cobj = zstandard.ZstdCompressor(level=1).compressobj(size=size)
    chunk = bytes(1 << 20)
    return b"".join([cobj.compress(chunk) for _ in range(size // len(chunk))] + [cobj.flush()])


@pytest.mark.parametrize("declared", [30, 0])
def test_frame_lying_about_its_size_stops_at_the_declared_size(declared):
    bomb = _bomb()
    assert bomb[4] >> 6 == 2 and not bomb[4] & 0x23  # 4-byte content size after a window byte, no dictionary
    liar = bomb[:6] + declared.to_bytes(4, "little") + bomb[10:]
    tracemalloc.start()
    try:
        with pytest.raises(ProtocolError, match="part: zstd decompression failed"):
            decompress_exact(liar, declared, "part")
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    assert peak < 2 << 20
