"""Decoded pictures: 8-bit 4:2:0 planes (:class:`YuvPicture`) and their accurate conversion to RGB.

The atlas stream is BT.601 limited range ("MPEG"), chroma at the centre of each 2x2 block (codec/encoder.py)."""

from __future__ import annotations

from dataclasses import dataclass

import av
import numpy as np

__all__ = ["YuvPicture", "frame_to_rgb"]

# FFmpeg's default YUV->RGB conversion repeats each chroma sample over its 2x2 pixels and rounds coarsely; with
# these flags it interpolates chroma and rounds exactly (a monastery view through RGB -> 4:2:0 -> RGB alone, FLIP
# against its source: 0.049 -> 0.030).
_ACCURATE = av.video.reformatter.Interpolation.FULL_CHR_H_INT | av.video.reformatter.Interpolation.ACCURATE_RND


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

    @classmethod
    def grey(cls, width: int, height: int) -> YuvPicture:
        """A uniform mid-grey picture (every plane 128): what the clients' warm-ups code as made-up frames."""
        chroma = ((height + 1) // 2, (width + 1) // 2)
        return cls(np.full((height, width), 128, np.uint8), np.full(chroma, 128, np.uint8),
                   np.full(chroma, 128, np.uint8))

    @classmethod
    def from_frame(cls, frame: av.VideoFrame) -> YuvPicture:
        """The planes of a yuv420p PyAV picture (copied)."""
        if frame.format.name != "yuv420p":
            raise ValueError(f"YuvPicture.from_frame: the picture is {frame.format.name}, not yuv420p")
        return cls(*[np.frombuffer(p, np.uint8).reshape(p.height, p.line_size)[:, :p.width].copy()
                     for p in frame.planes])

    def to_frame(self) -> av.VideoFrame:
        """A yuv420p PyAV picture holding these planes."""
        frame = av.VideoFrame(self.width, self.height, "yuv420p")
        for plane, data in zip(frame.planes, (self.y, self.u, self.v)):
            rows = np.zeros((plane.height, plane.line_size), np.uint8)
            rows[:, :plane.width] = data
            plane.update(rows)
        return frame

    def to_rgb(self) -> np.ndarray:
        """(height, width, 3) RGB uint8, chroma interpolated."""
        return frame_to_rgb(self.to_frame())


def frame_to_rgb(frame: av.VideoFrame) -> np.ndarray:
    """A decoded PyAV picture as (height, width, 3) RGB uint8, chroma interpolated."""
    # One thread: FFmpeg's sliced YUV->RGB conversion writes a few wrong pixels, differently from run to run,
    # at a slice edge when the width is not a multiple of 16 (680: 8-16 of 220,000 in a 680x324 picture).
    out = frame.reformat(format="rgb24", src_colorspace="ITU601", src_color_range="MPEG",
                         interpolation=_ACCURATE, threads=1).to_ndarray()
    return np.ascontiguousarray(out, dtype=np.uint8)
