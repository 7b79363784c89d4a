"""Foveated colour atlas: the atlas keeps its size, but away from the gaze its pictures get coarser.

After the gaze-driven multi-resolution paper (../shared/seeds/004): the resolution a region deserves falls with
the eye's sensitivity there, S(e) = exp(-max(0, e - r0)^2 / 2 sigma^2) at eccentricity e from the gaze point, as
S^gamma. Each view in the atlas (reference, current, hidden, wide) is blended, per pixel, between itself and copies
at 1/2, 1/4, ... of its resolution, by log2 of its pixel scale (:func:`quadcast.protocol.rate.fovea_scale`, capped
at the operating point's ``fovea_atlas``). The client samples the atlas as before; H.264 spends few bits on what
was smoothed. The picture size never changes, so a switch of operating point needs no new stream for this.
"""
from __future__ import annotations

import math

import numpy as np
from PIL import Image

from quadcast.protocol.rate import OperatingPoint
from quadcast.render.camera import Camera

__all__ = ["AtlasFoveation", "FoveatedEncoder"]


class AtlasFoveation:
    """Per-pixel blend weights for the views of an atlas, for one operating point and gaze.

    ``views``: ``(rect, camera)`` for each view in the atlas (``rect`` = x, y, w, h in atlas pixels; ``camera``
    the view's frustum at the rect's size); ``gaze`` a view-space direction shared by all views (they share the
    head's orientation)."""

    def __init__(self, views: list[tuple[tuple[int, int, int, int], Camera]], point: OperatingPoint,
                 gaze=(0.0, 0.0, -1.0)) -> None:
        self.point, self.gaze, self._views = point, tuple(gaze), list(views)
        self.levels = max(0, math.ceil(math.log2(point.fovea_atlas) - 1e-9)) if point.foveated else 0
        self.views = []
        for rect, camera in views:
            if (camera.width, camera.height) != rect[2:]:
                raise ValueError(f"AtlasFoveation: a {camera.width}x{camera.height} camera for a {rect[2]}x{rect[3]} "
                                 f"rect")
            scale = np.minimum(point.scale_at(camera.eccentricity_deg(gaze)), point.fovea_atlas)
            level = np.log2(np.maximum(scale, 1.0)).astype(np.float32)          # 0 .. self.levels
            if self.levels and float(level.max()) > 0:
                self.views.append((rect, level[..., None]))

    def with_gaze(self, gaze) -> "AtlasFoveation":
        """The same views and point around another gaze direction."""
        return AtlasFoveation(self._views, self.point, gaze)

    @property
    def active(self) -> bool:
        return bool(self.views)

    def apply(self, rgb: np.ndarray) -> np.ndarray:
        """The atlas (H, W, 3) uint8 with each view coarsened away from the gaze (a new array)."""
        if not self.views:
            return rgb
        out = rgb.copy()
        for (x, y, w, h), level in self.views:
            view = rgb[y:y + h, x:x + w]
            image = Image.fromarray(view)
            copies = [view.astype(np.float32)]
            for k in range(1, self.levels + 1):
                small = image.resize((max(1, w >> k), max(1, h >> k)), Image.Resampling.BOX)
                copies.append(np.asarray(small.resize((w, h), Image.Resampling.BILINEAR), np.float32))
            lo = np.floor(level).astype(np.int32)
            frac = level - lo
            stack = np.stack(copies)                                   # (levels + 1, h, w, 3)
            hi = np.minimum(lo + 1, self.levels)
            rows, cols = np.indices((h, w))
            a = stack[lo[..., 0], rows, cols]
            b = stack[hi[..., 0], rows, cols]
            out[y:y + h, x:x + w] = np.clip(a + (b - a) * frac + 0.5, 0, 255).astype(np.uint8)
        return out


class FoveatedEncoder:
    """An :class:`quadcast.codec.encoder.AtlasEncoder` that foveates each atlas before encoding it."""

    def __init__(self, encoder, foveation: AtlasFoveation) -> None:
        self.encoder, self.foveation = encoder, foveation

    def encode(self, rgb: np.ndarray, *, keyframe: bool):
        """As AtlasEncoder.encode: RGB, or RGBA whose alpha is dropped before foveating."""
        if rgb.ndim == 3 and rgb.shape[2] == 4:
            rgb = np.ascontiguousarray(rgb[..., :3])
        return self.encoder.encode(self.foveation.apply(rgb), keyframe=keyframe)

    def close(self) -> None:
        self.encoder.close()
