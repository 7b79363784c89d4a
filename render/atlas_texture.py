"""The decoded colour atlas on the GPU: a 4:2:0 picture's planes, converted to RGB where a draw samples them.

:meth:`AtlasTexture.write` uploads a decoded :class:`~quadcast.codec.picture.YuvPicture` as two textures (luma,
and Cb/Cr side by side at half size; 1.5 bytes a pixel), both with linear filtering. Every client's draw samples
them through ``atlas_colour.glsl``, which converts per fragment: BT.601 limited range, chroma interpolated
bilinearly from its sample positions (the centre of each 2x2 block, where the encoder's conversion puts them).
FFmpeg's fast conversion to RGB repeats each chroma sample over its 2x2 pixels and rounds coarsely instead; the
error that adds was most of a frame's FLIP at the reference pose (0.049 of 0.053 for a monastery view at CRF 18).

Converting the whole atlas to an RGBA texture once per frame instead (one full-screen pass) cost 11 ms on llvmpipe
for a 2040x1006 atlas, a fifth of a 960x540 client frame: the atlas holds about four times the display's pixels,
and the draws shade each display pixel about once. :meth:`AtlasTexture.read_rgb` still runs that pass, for a
picture of the atlas as the draws see it at texel centres.
"""

from __future__ import annotations

import moderngl
import numpy as np

from quadcast.codec.picture import YuvPicture
from quadcast.render.gl import RENDER_DIR, program, set_uniforms
from quadcast.render.renderer import read_texture

__all__ = ["AtlasTexture"]


class AtlasTexture:
    """The newest decoded picture's planes (top row first, linear filtering, clamped to the edge), for shaders that
    `#include "atlas_colour.glsl"`: bind them with :meth:`use`."""

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._planes: list[moderngl.Texture] = []

    @property
    def size(self) -> tuple[int, int] | None:
        """(width, height) of the picture held, or None before the first write."""
        return self._planes[0].size if self._planes else None

    def write(self, picture: YuvPicture) -> None:
        """Hold `picture`."""
        if not isinstance(picture, YuvPicture):
            raise ValueError(f"AtlasTexture.write: need a YuvPicture, got {type(picture).__name__}")
        chroma = np.empty(picture.u.shape + (2,), np.uint8)     # Cb and Cr side by side: one fetch for both
        chroma[..., 0], chroma[..., 1] = picture.u, picture.v
        sizes = [(picture.width, picture.height), (chroma.shape[1], chroma.shape[0])]
        if [t.size for t in self._planes] != sizes:
            self.release()
            self._planes = [self.ctx.texture(size, n, alignment=1) for size, n in zip(sizes, (1, 2))]
            for t in self._planes:
                t.filter = (moderngl.LINEAR, moderngl.LINEAR)
                t.repeat_x = t.repeat_y = False
        self._planes[0].write(np.ascontiguousarray(picture.y))
        self._planes[1].write(chroma)

    def use(self, unit: int = 0) -> dict[str, int]:
        """Bind luma to texture unit `unit` and chroma to `unit + 1`; the sampler uniforms to set (u_atlas,
        u_atlas_chroma)."""
        if not self._planes:
            raise ValueError("AtlasTexture.use: no picture written yet")
        for k, t in enumerate(self._planes):
            t.use(unit + k)
        return {"u_atlas": unit, "u_atlas_chroma": unit + 1}

    def read_rgb(self) -> np.ndarray:
        """The picture as the draws sample it at texel centres: (height, width, 3) uint8 RGB, top row first
        (one conversion pass, ``yuv_to_rgba.frag.glsl``)."""
        w, h = self.size
        prog = program(self.ctx, RENDER_DIR / "fullscreen.vert.glsl", RENDER_DIR / "yuv_to_rgba.frag.glsl")
        target = self.ctx.texture((w, h), 4)
        fbo = self.ctx.framebuffer([target])
        vao = self.ctx.vertex_array(prog, [])
        try:
            fbo.use()
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
            set_uniforms(prog, u_z=0.0, **self.use(0))
            vao.render(moderngl.TRIANGLES, vertices=3)
            return np.ascontiguousarray(read_texture(target, 4, "u1")[..., :3])
        finally:
            for obj in (vao, fbo, target):
                obj.release()

    def release(self) -> None:
        for t in self._planes:
            t.release()
        self._planes = []
