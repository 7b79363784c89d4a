"""Foveated colour atlas: the atlas keeps its size, but away from the gaze its pictures get coarser.

After the gaze-driven multi-resolution paper (../shared/seeds/004): the resolution a region deserves falls with
the eye's sensitivity there, S(e) = exp(-max(0, e - r0)^2 / 2 sigma^2) at eccentricity e from the gaze point, as
S^gamma. Each view in the atlas (reference, current, hidden, wide) is blended, per pixel, between itself and copies
at 1/2, 1/4, ... of its resolution, by log2 of its pixel scale (:func:`quadcast.protocol.rate.fovea_scale`, capped
at the operating point's ``fovea_atlas``). The client samples the atlas as before; H.264 spends few bits on what
was smoothed. The picture size never changes, so a switch of operating point needs no new stream for this.

The blend runs on the GPU as the atlas is composed (:meth:`quadcast.server.layers.AtlasComposer.draw_foveated`,
server/atlas_fovea.frag.glsl): the copies are the view's mip levels, and each pixel is sampled between the two
levels around its own (trilinear filtering), so a gaze that moves costs nothing but uniforms.
"""
from __future__ import annotations

import math

import numpy as np

from quadcast.protocol.rate import OperatingPoint
from quadcast.render.camera import Camera

__all__ = ["AtlasFoveation"]


class AtlasFoveation:
    """Which views of an atlas are coarsened away from the gaze, and how, for one operating point and gaze.

    ``views``: ``(rect, camera)`` for each view in the atlas (``rect`` = x, y, w, h in atlas pixels; ``camera``
    the view's frustum at the rect's size); ``gaze`` a view-space direction shared by all views (they share the
    head's orientation). :attr:`cameras` maps the rect of each view coarsened somewhere to its camera."""

    def __init__(self, views: list[tuple[tuple[int, int, int, int], Camera]], point: OperatingPoint,
                 gaze=(0.0, 0.0, -1.0)) -> None:
        self.point, self._views = point, list(views)
        g = np.asarray(gaze, np.float64)
        self.gaze = tuple(float(v) for v in g / np.linalg.norm(g))
        self.levels = max(0, math.ceil(math.log2(point.fovea_atlas) - 1e-9)) if point.foveated else 0
        self.cameras: dict[tuple[int, int, int, int], Camera] = {}
        for rect, camera in views:
            if (camera.width, camera.height) != rect[2:]:
                raise ValueError(f"AtlasFoveation: a {camera.width}x{camera.height} camera for a {rect[2]}x{rect[3]} "
                                 f"rect")
            if self.levels and self._coarsest(camera) > 1.0:
                self.cameras[tuple(rect)] = camera

    def _coarsest(self, camera: Camera) -> float:
        """The largest pixel scale in the view: at one of its corners, the rays farthest from the gaze (the rays
        within an angle of it make a convex region of the image plane)."""
        l, r, b, t = camera.frustum.unit_extents
        corners = np.array([[x, y, -1.0] for x in (l, r) for y in (b, t)])
        cos = corners @ np.asarray(self.gaze) / np.linalg.norm(corners, axis=1)
        ecc = float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).max())
        return float(min(self.point.scale_at(ecc), self.point.fovea_atlas))

    def with_gaze(self, gaze) -> "AtlasFoveation":
        """The same views and point around another gaze direction."""
        return AtlasFoveation(self._views, self.point, gaze)

    @property
    def active(self) -> bool:
        return bool(self.cameras)

    def uniforms(self, camera: Camera) -> dict:
        """server/atlas_fovea.frag.glsl's uniforms for a view seen through `camera`: its frustum, the gaze and
        fovea.glsl's (r0, sigma, gamma, largest scale), the scale capped at the point's atlas factor."""
        p = self.point
        return {"u_extents": tuple(float(v) for v in camera.frustum.unit_extents), "u_gaze": self.gaze,
                "u_fovea": (math.radians(p.fovea_deg), math.radians(p.fovea_sigma_deg), float(p.fovea_gamma),
                            float(min(p.fovea_max_scale, p.fovea_atlas)))}
