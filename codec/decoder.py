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
from dataclasses import dataclass
from types import TracebackType

import av
import numpy as np

from quadcast.codec.nal import NAL_IDR_SLICE, nal_unit_types

__all__ = ["VideoError", "AtlasDecoder", "YuvPicture", "frame_to_rgb"]

# FFmpeg's default YUV->RGB conversion repeats each chroma sample over its 2x2 pixels and rounds coarsely; with
# these flags it interpolates chroma and rounds exactly (a monastery view through RGB -> 4:2:0 -> RGB alone, FLIP
# against its source: 0.049 -> 0.030).
_ACCURATE = av.video.reformatter.Interpolation.FULL_CHR_H_INT | av.video.reformatter.Interpolation.ACCURATE_RND



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


@dataclass(frozen=True)
class YuvPicture:
    """A decoded 8-bit 4:2:0 picture as its three planes (BT.601 limited range, top row first): ``y`` (height,
    width), ``u`` and ``v`` (height / 2, width / 2, rounded up), uint8. What a GPU client uploads and converts
    (render/atlas_texture.py); :meth:`to_rgb` converts on the CPU."""

    y: np.ndarray
    u: np.ndarray
    v: np.ndarray

    def __post_init__(self) -> None:
        h, w = self.y.shape
        chroma = ((h + 1) // 2, (w + 1) // 2)
        for name in ("y", "u", "v"):
            plane = getattr(self, name)
            if not isinstance(plane, np.ndarray) or plane.dtype != np.uint8 or plane.ndim != 2:
                raise ValueError(f"YuvPicture.{name} must be a 2-D uint8 array")
        if self.u.shape != chroma or self.v.shape != chroma:
            raise ValueError(f"YuvPicture: chroma planes must be {chroma[1]}x{chroma[0]} for {w}x{h} luma, "
                             f"got {self.u.shape[1]}x{self.u.shape[0]} and {self.v.shape[1]}x{self.v.shape[0]}")

    @property
    def width(self) -> int:
        return self.y.shape[1]

    @property
    def height(self) -> int:
        return self.y.shape[0]

    def to_rgb(self, rgba: bool = False) -> np.ndarray:
        """(height, width, 3) RGB uint8 ((height, width, 4) with alpha 255), chroma interpolated."""
        frame = av.VideoFrame(self.width, self.height, "yuv420p")
        for plane, data in zip(frame.planes, (self.y, self.u, self.v)):
            rows = np.zeros((plane.height, plane.line_size), np.uint8)
            rows[:, :plane.width] = data
            plane.update(rows)
        return frame_to_rgb(frame, rgba)


def frame_to_rgb(frame: av.VideoFrame, rgba: bool = False) -> np.ndarray:
    """A decoded PyAV picture as (height, width, 3) RGB uint8 ((height, width, 4) RGBA), chroma interpolated."""
    # One thread: FFmpeg's sliced YUV->RGB conversion writes a few wrong pixels, differently from run to run,
    # at a slice edge when the width is not a multiple of 16 (680: 8-16 of 220,000 in a 680x324 picture).
    out = frame.reformat(format="rgba" if rgba else "rgb24", src_colorspace="ITU601", src_color_range="MPEG",
                         interpolation=_ACCURATE, threads=1).to_ndarray()
    return np.ascontiguousarray(out, dtype=np.uint8)


def _planes(frame: av.VideoFrame) -> YuvPicture:
    planes = [np.frombuffer(p, np.uint8).reshape(p.height, p.line_size)[:, :p.width].copy() for p in frame.planes]
    return YuvPicture(*planes)


class AtlasDecoder:
    """Decoder for the H.264 atlas stream produced by ``server.video.AtlasEncoder``.

    Call :meth:`decode` once per received access unit.
    """

    OUTPUTS = ("rgb", "rgba", "yuv420")

    def __init__(self, max_pixels: int | None = None, output: str = "rgb") -> None:
        """``max_pixels``: the largest picture accepted (width x height), e.g. what the session asked for; a
        stream declaring a bigger one fails with VideoError before its picture is allocated. ``output``: pictures
        come out as (height, width, 3) RGB ("rgb"), (height, width, 4) RGBA with alpha 255 ("rgba"), or as their
        planes ("yuv420", a :class:`YuvPicture`: no conversion on the CPU, for a client that converts on the GPU)."""
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
            The decoded atlas, top row first: a uint8 array (height, width, 3) RGB, (height, width, 4) RGBA, or a
            :class:`YuvPicture`, as ``output`` says; or None when the access unit yields no picture, including
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
            picture = _planes(frame) if self.output == "yuv420" else frame_to_rgb(frame, self.output == "rgba")
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
