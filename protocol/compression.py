"""Bounded zstd decompression for the wire formats (sans-I/O: zstandard only).

Every compressed part of a message is exactly one zstd frame that declares its content size, and the receiver
knows from the message's headers how many bytes it must hold. :func:`decompress_exact` checks the declared size
against that before anything is allocated, caps the decoder's window (:func:`window_limit`) so memory stays within
a small multiple of the expected size whatever the frame claims, and refuses truncated frames and trailing bytes.
"""

from __future__ import annotations

import zstandard

from quadcast.protocol.errors import ProtocolError

__all__ = ["MIN_WINDOW_LOG", "MAX_WINDOW_LOG", "window_limit", "decompress_exact"]

MIN_WINDOW_LOG = 20
"""The window allowed for any frame (1 MiB), however small: never refuse a frame for the window a standard
encoder picks for small inputs."""

MAX_WINDOW_LOG = 27
"""The largest window allowed (128 MiB): libzstd's own default decoding limit."""


def window_limit(expected: int) -> int:
    """The largest zstd window (bytes) accepted for a frame of `expected` bytes: the power of two that holds it,
    clamped to [2**MIN_WINDOW_LOG, 2**MAX_WINDOW_LOG]. A frame never needs a window larger than its content."""
    return 1 << max(MIN_WINDOW_LOG, min(MAX_WINDOW_LOG, max(expected - 1, 1).bit_length()))


def decompress_exact(data: bytes | bytearray | memoryview, expected: int, what: str) -> bytes:
    """The content of the single zstd frame `data`, which must declare and hold exactly `expected` bytes.

    `what` names the part in error messages (e.g. ``"payload"``). Raises ProtocolError when `data` is empty, its
    frame header is invalid or truncated, does not declare its content size or declares another size, asks for a
    window over :func:`window_limit`, or the frame is corrupt, truncated or followed by trailing bytes. Memory:
    the output (`expected` bytes) plus at most the window limit, never what a lying frame would inflate to.
    """
    if expected < 0:
        raise ValueError(f"decompress_exact: expected must be >= 0 bytes, got {expected}")
    try:
        data = memoryview(data).cast("B")
    except TypeError:
        raise ProtocolError(f"{what}: expected bytes-like data, got {type(data).__name__}") from None
    if len(data) == 0:
        raise ProtocolError(f"{what}: missing zstd frame (no bytes), expected one holding {expected} bytes")
    try:
        params = zstandard.get_frame_parameters(data)
    except zstandard.ZstdError as exc:
        raise ProtocolError(f"{what}: invalid or truncated zstd frame header ({exc})") from None
    declared = params.content_size
    if declared in (zstandard.CONTENTSIZE_UNKNOWN, zstandard.CONTENTSIZE_ERROR):
        raise ProtocolError(f"{what}: zstd frame must declare its content size, it does not")
    if declared != expected:
        raise ProtocolError(f"{what}: zstd frame declares {declared} bytes, expected {expected}")
    limit = window_limit(expected)
    if params.window_size > limit:
        raise ProtocolError(f"{what}: zstd frame needs a {params.window_size}-byte window, more than the "
                            f"{limit} bytes allowed for {expected} bytes of content")
    dctx = zstandard.ZstdDecompressor(max_window_size=limit)
    if expected > 0:
        # One pass into a buffer of exactly the declared (== expected) size: libzstd stops with an error rather
        # than write past it. (decompress() returns b"" for a zero-size frame without reading it.)
        try:
            out = dctx.decompress(data, max_output_size=expected, allow_extra_data=False)
        except zstandard.ZstdError:
            pass  # find out what is wrong below
        else:
            if len(out) == expected:
                return out
    # Zero-size frames, and the diagnosis of a failed pass: stream the frame (libzstd still refuses to produce
    # more than the declared size) and say what is wrong with it.
    dobj = dctx.decompressobj()
    try:
        out = dobj.decompress(data)
    except zstandard.ZstdError as exc:
        raise ProtocolError(f"{what}: zstd decompression failed ({exc})") from None
    if not dobj.eof:
        raise ProtocolError(f"{what}: truncated zstd frame ({len(out)} of {expected} bytes decompressed)")
    if dobj.unused_data:
        raise ProtocolError(f"{what}: {len(dobj.unused_data)} trailing bytes after the zstd frame")
    if len(out) != expected:
        raise ProtocolError(f"{what}: zstd frame decompressed to {len(out)} bytes, expected {expected}")
    return out
