"""H.264 decoding of the server's colour atlas, one access unit at a time.

:class:`AtlasDecoder` takes each Annex-B access unit as it arrives off the link
and returns the decoded RGB atlas right away (the stream has no B-frames, so
the decoder never holds a picture back).  Damaged input is an error, not a
smeared picture: the decoder runs with FFmpeg's strict error detection and
without slice threading, so error resilience can see missing or garbled
macroblocks, and any access unit that fails or needs concealment raises
:class:`VideoError`.

After an error, or before the first IDR, the decoder waits for a keyframe:
:attr:`AtlasDecoder.needs_keyframe` is True and non-IDR access units are
dropped (``decode`` returns None) because they would predict from pictures the
decoder does not have.  Every error resets the decoder to a fresh state, so
nothing from the damaged stream carries over; decoding resumes at the next IDR
access unit, which must carry its SPS and PPS in-band (as those of
``server.video.AtlasEncoder`` do).
"""

from __future__ import annotations

import time
from types import TracebackType

import av
import numpy as np

from quadcast.codec.nal import NAL_IDR_SLICE, nal_unit_types
from quadcast.codec.picture import YuvPicture, frame_to_rgb

__all__ = ["VideoError", "AtlasDecoder"]


class VideoError(ValueError):
    """An H.264 access unit could not be decoded (corrupt, truncated or not H.264)."""


def _new_codec(max_pixels: int | None = None) -> av.VideoCodecContext:
    codec = av.CodecContext.create("h264", "r")
    # One thread, no slice threading: FFmpeg's error resilience only flags
    # concealed macroblocks when the picture is decoded by a single thread.
    codec.thread_count = 1
    options = {"err_detect": "careful+explode"}
    if max_pixels is not None:
        # FFmpeg refuses a stream whose SPS declares a bigger picture before allocating it
        options["max_pixels"] = str(int(max_pixels))
    codec.options = options
    return codec


class AtlasDecoder:
    """Decoder for the H.264 atlas stream produced by ``server.video.AtlasEncoder``.

    Call :meth:`decode` once per received access unit.
    """

    OUTPUTS = ("rgb", "yuv420")

    def __init__(self, max_pixels: int | None = None, output: str = "rgb") -> None:
        """``max_pixels``: the largest picture accepted (width x height), e.g. what the session asked for; a
        stream declaring a bigger one fails with VideoError before its picture is allocated. ``output``: pictures
        come out as (height, width, 3) RGB ("rgb", converted by FFmpeg with interpolated chroma) or as their planes
        ("yuv420", a :class:`~quadcast.codec.picture.YuvPicture`: no conversion on the CPU, for a client that
        converts on the GPU, render/atlas_texture.py and render/atlas_colour.glsl)."""
        if max_pixels is not None and max_pixels < 1:
            raise ValueError(f"AtlasDecoder: max_pixels must be >= 1, got {max_pixels}")
        if output not in self.OUTPUTS:
            raise ValueError(f"AtlasDecoder: output must be one of {', '.join(self.OUTPUTS)}, got {output!r}")
        self.max_pixels = max_pixels
        self.output = output
        self._codec: av.VideoCodecContext | None = _new_codec(max_pixels)
        self._needs_keyframe = True
        self._last_sequence: int | None = None
        self.decode_ms = 0.0
        """Wall-clock time of the last :meth:`decode` call, in milliseconds."""

    @property
    def needs_keyframe(self) -> bool:
        """True until an IDR has been decoded, and again after any decode error."""
        return self._needs_keyframe

    def decode(self, data: bytes, sequence: int | None = None) -> np.ndarray | YuvPicture | None:
        """Decode one Annex-B access unit.

        Args:
            data: exactly one H.264 access unit (bytes-like).
            sequence: the access unit's position in the stream (the sender's frame id), if known. A non-IDR
                unit whose sequence does not follow the last decoded one would predict from a picture that was
                lost on the way: it raises VideoError and the decoder waits for the next IDR. An older one
                (reordered) is refused the same way.

        Returns:
            The decoded atlas, top row first: a uint8 array (height, width, 3) RGB or a :class:`YuvPicture`, as
            ``output`` says; or None when the access unit yields no picture, including
            non-IDR access units dropped while :attr:`needs_keyframe` is True.

        Raises:
            VideoError: the data is empty, not an Annex-B H.264 stream, or fails
                to decode cleanly (truncated, corrupt, references missing).
                The decoder then waits for the next IDR.
            TypeError: ``data`` is not bytes-like.
            RuntimeError: the decoder is closed.
        """
        start = time.perf_counter()
        try:
            return self._decode(data, sequence)
        finally:
            self.decode_ms = (time.perf_counter() - start) * 1000.0

    def _decode(self, data: bytes, sequence: int | None) -> np.ndarray | YuvPicture | None:
        if self._codec is None:
            raise RuntimeError("AtlasDecoder is closed")
        if not isinstance(data, (bytes, bytearray, memoryview)):
            raise TypeError(f"access unit must be bytes-like; got {type(data).__name__}")
        data = bytes(data)
        if not data:
            # An empty packet would be taken as end-of-stream by FFmpeg.
            raise self._fail("empty access unit (0 bytes)")
        nal_types = nal_unit_types(data)
        if not nal_types:
            raise self._fail(
                f"not an Annex-B H.264 access unit ({len(data)} bytes, no start code found)"
            )
        is_idr = NAL_IDR_SLICE in nal_types
        if self._needs_keyframe and not is_idr:
            return None
        if (sequence is not None and not is_idr and self._last_sequence is not None
                and sequence != self._last_sequence + 1):
            missing = (f"frames {self._last_sequence + 1}..{sequence - 1} are missing"
                       if sequence > self._last_sequence else f"it is older than frame {self._last_sequence}")
            raise self._fail(f"access unit {sequence} cannot be decoded: {missing}; waiting for a keyframe")

        try:
            frames = self._codec.decode(av.Packet(data))
        except Exception as exc:  # bad bytes must surface as VideoError only
            raise self._fail(
                f"undecodable H.264 access unit ({len(data)} bytes, "
                f"NAL types {nal_types}): {exc}"
            ) from exc
        if not frames:
            return None
        frame = frames[-1]
        if frame.is_corrupt:
            raise self._fail(
                f"H.264 access unit decoded with errors ({len(data)} bytes, "
                f"NAL types {nal_types}): picture is truncated or corrupt"
            )
        if frame.format.name != "yuv420p":
            raise self._fail(f"decoded picture is {frame.format.name}, not the 8-bit 4:2:0 (yuv420p) the atlas "
                             "stream carries")
        try:
            picture = YuvPicture.from_frame(frame) if self.output == "yuv420" else frame_to_rgb(frame)
        except Exception as exc:
            raise self._fail(f"decoded picture could not be converted: {exc}") from exc
        if is_idr:
            self._needs_keyframe = False
        self._last_sequence = sequence
        return picture

    def _fail(self, message: str) -> VideoError:
        """Drop decoder state, wait for the next IDR, and build the error to raise."""
        self._needs_keyframe = True
        self._last_sequence = None
        if self._codec is not None:
            self._codec = _new_codec(self.max_pixels)
        return VideoError(message)

    def close(self) -> None:
        """Release the decoder; further :meth:`decode` calls raise RuntimeError."""
        self._codec = None

    def __enter__(self) -> AtlasDecoder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
