"""H.264 encoding of the server's colour atlas (one RGB image per server frame).

The server composites its colour layers into a single RGB "atlas" image per
frame and streams it as H.264 with libx264 through PyAV.  The encoder is set up
for the lowest possible latency: ``tune=zerolatency`` (no lookahead, no frame
threading), no B-frames and no scene-cut keyframes.  With that configuration
libx264 emits exactly one Annex-B access unit for every frame it is given, so
:meth:`AtlasEncoder.encode` is a strict one-frame-in / one-access-unit-out call
and never needs a flush; if the encoder ever returned zero or several packets
for one frame, the configuration is broken and a ``RuntimeError`` is raised.

IDR pictures are produced only for the first frame, every ``gop`` frames when
``VideoSettings.gop`` is set, and whenever the caller asks for one with
``keyframe=True`` (x264 ``forced-idr=1`` plus an I picture type on the frame).
Every IDR access unit carries its SPS and PPS in-band, so a decoder can start
(or restart after loss) at any IDR.

Colour: RGB is converted to 4:2:0 YUV with the BT.601 matrix in limited range,
and the stream's VUI says so, so any H.264 decoder converts it back the same
way.  4:2:0 needs even image sizes; odd widths or heights are rejected (pad the
atlas to even size before encoding) rather than padded silently, because a
padded picture would come out of the decoder with a different shape.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from fractions import Fraction
from types import TracebackType

import av
import numpy as np
from av.video.frame import PictureType

from quadcast.codec.nal import contains_idr
from quadcast.codec.picture import YuvPicture

__all__ = ["VideoSettings", "EncodedFrame", "AtlasEncoder"]

X264_PRESETS = (
    "ultrafast",
    "superfast",
    "veryfast",
    "faster",
    "fast",
    "medium",
    "slow",
    "slower",
    "veryslow",
    "placebo",
)
"""Preset names libx264 accepts, fastest first."""


# AVColorSpace / AVColorPrimaries / AVColorTransferCharacteristic / AVColorRange
# values written to the VUI: BT.601 (SMPTE 170M), limited ("MPEG") range.
_AVCOL_SMPTE170M = 6
_AVCOL_RANGE_MPEG = 1
# RGB -> 4:2:0 conversion flags: chroma from every input column, exact rounding
_CHROMA_INPUT = (av.video.reformatter.Interpolation.FULL_CHR_H_INP
                 | av.video.reformatter.Interpolation.ACCURATE_RND)


@dataclass(frozen=True)
class VideoSettings:
    """Rate control and speed settings for :class:`AtlasEncoder`.

    Attributes:
        crf: x264 constant rate factor (0 = lossless .. 51 = worst); used when
            ``bitrate_kbps`` is None.
        bitrate_kbps: target bitrate in kbit/s.  When set it takes precedence
            over ``crf``: the encoder runs in average-bitrate mode capped by a
            VBV of ``bitrate_kbps`` max rate and a one-second buffer.
        preset: x264 speed preset (see :data:`X264_PRESETS`).
        gop: maximum number of frames between IDR pictures; None means no
            periodic IDRs (only the first frame and forced keyframes are IDR).
        threads: encoder threads, 0 = let x264 choose.  Threads split each
            picture into slices, which adds no latency.
        fps: nominal frame rate; it sets the stream time base and is what the
            bitrate mode budgets bits against.
        chroma_qp_offset: x264's ``chroma-qp-offset`` (-12 .. 12), the step
            from each block's luma quantizer to its chroma quantizers (the
            PPS's ``chroma_qp_index_offset``, which every decoder reads).
            Negative codes colour finer than brightness; 0 is x264's default.
            QUASAR's server takes -6 (quadcast.protocol.methods.
            DEFAULT_CHROMA_QP_OFFSET).
        ipratio: x264's ``ipratio`` (1 .. 10), the ratio of the P frames'
            quantizer step to the I frames': an IDR is coded 6 * log2(ipratio)
            quantizer steps finer than the P frames around it (2.9 at x264's
            default, 1.4; 6 at 2).  QUASAR's server takes 2.0 (quadcast.
            protocol.methods.DEFAULT_IPRATIO).
    """

    crf: float | None = 23
    bitrate_kbps: int | None = None
    preset: str = "ultrafast"
    gop: int | None = None
    threads: int = 0
    fps: float = 60.0
    chroma_qp_offset: int = 0
    ipratio: float = 1.4

    def __post_init__(self) -> None:
        if self.bitrate_kbps is None:
            if self.crf is None:
                raise ValueError("VideoSettings needs crf or bitrate_kbps; both are None")
            if not 0 <= self.crf <= 51:
                raise ValueError(f"VideoSettings.crf must be in [0, 51]; got {self.crf}")
        elif self.bitrate_kbps <= 0:
            raise ValueError(
                f"VideoSettings.bitrate_kbps must be positive; got {self.bitrate_kbps}"
            )
        if self.preset not in X264_PRESETS:
            raise ValueError(
                f"VideoSettings.preset must be one of {', '.join(X264_PRESETS)}; "
                f"got {self.preset!r}"
            )
        if self.gop is not None and self.gop < 1:
            raise ValueError(f"VideoSettings.gop must be None or >= 1; got {self.gop}")
        if self.threads < 0:
            raise ValueError(f"VideoSettings.threads must be >= 0; got {self.threads}")
        if not self.fps > 0:
            raise ValueError(f"VideoSettings.fps must be positive; got {self.fps}")
        if not (isinstance(self.chroma_qp_offset, int) and -12 <= self.chroma_qp_offset <= 12):
            raise ValueError(f"VideoSettings.chroma_qp_offset must be an integer in [-12, 12]; "
                             f"got {self.chroma_qp_offset!r}")
        if not (isinstance(self.ipratio, (int, float)) and 1.0 <= self.ipratio <= 10.0):
            raise ValueError(f"VideoSettings.ipratio must be a number in [1, 10]; got {self.ipratio!r}")


@dataclass(frozen=True)
class EncodedFrame:
    """One encoded atlas frame.

    Attributes:
        data: exactly one H.264 access unit in Annex-B byte-stream format
            (start-code prefixed NAL units; IDRs include SPS and PPS).
        keyframe: True iff the access unit is an IDR picture.
        frame_index: 0-based index of the frame within this encoder's stream.
        encode_ms: wall-clock time spent converting and encoding, in ms.
    """

    data: bytes
    keyframe: bool
    frame_index: int
    encode_ms: float


class AtlasEncoder:
    """Low-latency H.264 encoder for fixed-size RGB atlas images.

    Args:
        width: atlas width in pixels; positive and even.
        height: atlas height in pixels; positive and even.
        settings: rate control / speed settings (defaults: CRF 23, ultrafast).

    Use as a context manager or call :meth:`close` when done.
    """

    def __init__(self, width: int, height: int, settings: VideoSettings | None = None):
        for name, value in (("width", width), ("height", height)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise TypeError(f"AtlasEncoder {name} must be an int; got {value!r}")
            if value <= 0:
                raise ValueError(f"AtlasEncoder {name} must be positive; got {value}")
            if value % 2:
                raise ValueError(
                    f"AtlasEncoder {name} must be even for 4:2:0 H.264; got {value} "
                    f"(pad the atlas to {value + 1})"
                )
        self.width = int(width)
        self.height = int(height)
        self.settings = settings if settings is not None else VideoSettings()
        self._frame_index = 0
        self._codec: av.VideoCodecContext | None = self._open_codec()

    def _open_codec(self) -> av.VideoCodecContext:
        s = self.settings
        codec = av.CodecContext.create("libx264", "w")
        codec.width = self.width
        codec.height = self.height
        codec.pix_fmt = "yuv420p"
        rate = Fraction(s.fps).limit_denominator(1001)
        codec.framerate = rate
        codec.time_base = 1 / rate
        codec.thread_count = s.threads
        codec.colorspace = _AVCOL_SMPTE170M
        codec.color_primaries = _AVCOL_SMPTE170M
        codec.color_trc = _AVCOL_SMPTE170M
        codec.color_range = _AVCOL_RANGE_MPEG

        keyint = "infinite" if s.gop is None else str(s.gop)
        # chromaloc=1: the VUI says chroma sits at the centre of each 2x2 block, where the RGB conversion
        # (_CHROMA_INPUT) puts it and the clients' conversion reads it (render/atlas_colour.glsl); H.264's
        # default when unsaid is left-sited
        x264_params = [f"keyint={keyint}", "scenecut=0", "bframes=0", "repeat-headers=1", "chromaloc=1",
                       f"chroma-qp-offset={s.chroma_qp_offset}", f"ipratio={float(s.ipratio):g}"]
        options = {"preset": s.preset, "tune": "zerolatency", "forced-idr": "1"}
        if s.bitrate_kbps is not None:
            kbps = int(s.bitrate_kbps)
            x264_params += [f"bitrate={kbps}", f"vbv-maxrate={kbps}", f"vbv-bufsize={kbps}"]
        else:
            options["crf"] = f"{float(s.crf):g}"
        options["x264-params"] = ":".join(x264_params)
        codec.options = options
        codec.open()
        return codec

    @property
    def frames_encoded(self) -> int:
        """Number of frames encoded so far (the next frame's ``frame_index``)."""
        return self._frame_index

    def encode(self, image: np.ndarray | YuvPicture, *, keyframe: bool) -> EncodedFrame:
        """Encode one atlas image into exactly one H.264 access unit.

        Args:
            image: uint8 array of shape (height, width, 3), RGB, top row first; or (height, width, 4), RGBA
                (alpha ignored), as a GPU texture reads back -- converted to the same 4:2:0 planes, without
                the copy that dropping the alpha channel would take; or a :class:`YuvPicture` of this size,
                coded as it is (a decoded picture re-encoded without converting its colour twice).
            keyframe: force this frame to be an IDR picture.

        Raises:
            ValueError: ``image`` is not a uint8 (height, width, 3 or 4) array nor a YuvPicture of this size.
            RuntimeError: the encoder is closed, or libx264 did not return
                exactly one access unit (a broken low-latency configuration).
        """
        if self._codec is None:
            raise RuntimeError("AtlasEncoder is closed")
        expected = (self.height, self.width, 3)
        if isinstance(image, YuvPicture):
            if (image.width, image.height) != (self.width, self.height):
                raise ValueError(f"atlas picture must be {self.width}x{self.height}; got {image.width}x{image.height}")
            start = time.perf_counter()
            frame = image.to_frame()
        else:
            if not isinstance(image, np.ndarray):
                raise ValueError(
                    f"atlas image must be a numpy uint8 array of shape {expected}; "
                    f"got {type(image).__name__}"
                )
            if image.shape not in (expected, expected[:2] + (4,)) or image.dtype != np.uint8:
                raise ValueError(
                    f"atlas image must be uint8 with shape {expected} (height, width, RGB) or "
                    f"{expected[:2] + (4,)} (RGBA); got shape {image.shape} dtype {image.dtype}"
                )
            start = time.perf_counter()
            layout = "rgb24" if image.shape[2] == 3 else "rgba"
            frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(image), format=layout)
            # exact rounding and every input pixel's chroma (FFmpeg's default drops half the columns' chroma and
            # rounds coarsely): no slower, and with the client's interpolated conversion a monastery view through
            # the conversions alone has FLIP 0.026 against its source instead of 0.030
            frame = frame.reformat(format="yuv420p", dst_colorspace="ITU601", dst_color_range="MPEG",
                                   interpolation=_CHROMA_INPUT)
        frame.pts = self._frame_index
        frame.pict_type = PictureType.I if keyframe else PictureType.NONE
        packets = self._codec.encode(frame)
        if len(packets) != 1:
            raise RuntimeError(
                f"libx264 returned {len(packets)} packets for frame {self._frame_index}; "
                "the zero-latency configuration must give exactly one access unit per frame"
            )
        data = bytes(packets[0])
        encode_ms = (time.perf_counter() - start) * 1000.0

        is_idr = contains_idr(data)
        if keyframe and not is_idr:
            raise RuntimeError(
                f"libx264 did not produce an IDR for forced keyframe {self._frame_index}"
            )
        encoded = EncodedFrame(
            data=data, keyframe=is_idr, frame_index=self._frame_index, encode_ms=encode_ms
        )
        self._frame_index += 1
        return encoded

    def close(self) -> None:
        """Release the encoder; further :meth:`encode` calls raise RuntimeError."""
        self._codec = None

    def __enter__(self) -> AtlasEncoder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
