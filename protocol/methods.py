"""The streaming methods by name, and the parameters both halves of a method agree on (sans-I/O, no GL).

A client names its method in :class:`quadcast.protocol.messages.Hello`; :mod:`quadcast.methods` builds the
server half and the client half of each name.
"""
from __future__ import annotations

from dataclasses import dataclass

__all__ = ["METHODS", "STEREO_METHODS", "DEFAULT_CRF", "DEFAULT_CHROMA_QP_OFFSET", "DEFAULT_IPRATIO", "MethodConfig",
           "check_method", "method_crf", "method_video", "MAX_ATLAS_VIEWS", "meshwarp_render_size"]

METHODS = ("quasar", "quadstream", "meshwarp", "meshwarp120", "atw")
"""Every method: QUASAR, the QuadStream-like baseline, MeshWarp (60° or, as meshwarp120, 120° at twice the
resolution) and ATW."""

STEREO_METHODS = ("quasar", "quadstream")
"""Methods whose client keeps the depth of what it shows (a quad mesh), so it can synthesize the second eye."""


MAX_ATLAS_VIEWS = 16
"""A method's video picture holds at most this many pictures of the size a client asked for (QuadStream's atlas,
the largest, has 10.5; 120-degree MeshWarp's frame 4): a client refuses a stream declaring more."""


def meshwarp_render_size(width: int, height: int, fovy_deg: float,
                         render_scale: float | None = None) -> tuple[int, int]:
    """The size MeshWarp's server renders (its video and depth map) for a ``width`` x ``height`` display: scaled
    by ``render_scale``, by default 2 for a field of view over 90 degrees (QUASAR's 120-degree MeshWarp) and 1
    otherwise; rounded to even sizes."""
    if render_scale is None:
        render_scale = 2.0 if fovy_deg > 90.0 else 1.0
    return max(2, 2 * round(width * render_scale / 2)), max(2, 2 * round(height * render_scale / 2))


@dataclass(frozen=True)
class MethodConfig:
    """What a method's server and client are built with."""

    width: int = 960
    height: int = 540
    fovy_deg: float = 60.0
    viewcell_radius: float = 0.5   # metres (QuadStream: half the side of its box viewcell)
    reference_every: int = 5
    layers: int = 4
    crf: float | None = None      # x264 CRF of the method's video; None: the method's own (DEFAULT_CRF)
    chroma_qp_offset: int | None = None   # its x264 chroma-qp-offset; None: the method's own (DEFAULT_CHROMA_QP_OFFSET)


DEFAULT_CRF = {"quasar": 20.0}
"""Each method's video quality when none is asked for (x264 CRF; 23 for the others). QUASAR's atlas carries the
colour of every layer it sends, and its error floor at small pose errors is the video's: CRF 18 bought the
courtyard's real-trace runs 9% lower FLIP for 15% more Mbps, well inside a quarter of QuadStream's rate (README,
`quadcast bench quality`). Since the colour is coded finer (`VideoSettings.chroma_qp_offset`), CRF 19 sends about
what CRF 18 sent, for lower FLIP (README, "Colour coded finer"); since its reference frames are coded finer
(DEFAULT_IPRATIO), CRF 20 sends about what CRF 19 sent. The baselines keep x264's default."""

DEFAULT_CHROMA_QP_OFFSET = {"quasar": -6}
"""Each method's x264 chroma-qp-offset (`VideoSettings.chroma_qp_offset`; 0, x264's default, for the others): QUASAR
codes its atlas's colour 6 quantizer steps finer than its brightness. FLIP scores colour differences: in the
benchmark's scenes bits spent on colour lower it more than the same bits spent through a lower CRF (README, "Colour
coded finer", which also gives MeshWarp's figures with the same offset)."""

DEFAULT_IPRATIO = {"quasar": 2.0}
"""Each method's x264 ipratio (`VideoSettings.ipratio`; 1.4, x264's default, for the others): QUASAR codes its
reference frames (IDRs) 6 quantizer steps finer than its residual frames, not 2.9. A reference frame's visible layer
is the client's cache, drawn at every frame until the next reference frame, so bits spent on it buy more than the
same bits spread over every frame through a lower CRF (README, "Reference frames coded finer")."""


def method_crf(name: str, crf: float | None) -> float:
    """The CRF a method's video is encoded with: `crf` if given, else the method's default."""
    return float(crf) if crf is not None else DEFAULT_CRF.get(name, 23.0)


def method_video(name: str, crf: float | None, chroma_qp_offset: int | None = None) -> dict:
    """The keyword arguments of a method's `quadcast.codec.encoder.VideoSettings`: `crf` and `chroma_qp_offset`
    where given, else the method's own (`method_crf`, DEFAULT_CHROMA_QP_OFFSET), and its ipratio if DEFAULT_IPRATIO
    names it."""
    offset = DEFAULT_CHROMA_QP_OFFSET.get(name, 0) if chroma_qp_offset is None else chroma_qp_offset
    video = {"crf": method_crf(name, crf), "chroma_qp_offset": offset}
    if name in DEFAULT_IPRATIO:            # else VideoSettings' own, x264's default
        video["ipratio"] = DEFAULT_IPRATIO[name]
    return video


def check_method(name: str, option: str = "method") -> str:
    """``name`` if it is a method, else ValueError naming the methods."""
    if name not in METHODS:
        raise ValueError(f"{option}: unknown method {name!r}; methods are {', '.join(METHODS)}")
    return name
