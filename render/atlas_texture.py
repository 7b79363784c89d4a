"""The decoded colour atlas as a GL texture: a 4:2:0 picture converted to RGBA on the GPU, once per frame.

Every client samples its colour from one RGBA8 texture with linear filtering. :meth:`AtlasTexture.write` takes a
decoded :class:`~quadcast.codec.picture.YuvPicture` (three planes, 1.5 bytes a pixel to upload) and converts it in
one full-screen pass (``yuv_to_rgba.frag.glsl``): BT.601 limited range, chroma interpolated bilinearly from its
sample positions (the centre of each 2x2 block, where the encoder's conversion puts them). FFmpeg's fast conversion
to RGB repeats each chroma sample over its 2x2 pixels and rounds coarsely instead; the error that adds was most of
a frame's FLIP at the reference pose (0.049 of 0.053 for a monastery view at CRF 18). (A compute pass converting a
2x2 block per invocation cost the same on llvmpipe: 11.2–14.9 against 10.8–11.3 ms for a 2040x1006 picture, upload
to ``ctx.finish()``.)
"""

from __future__ import annotations

from pathlib import Path

import moderngl
import numpy as np

from quadcast.codec.picture import YuvPicture
from quadcast.render.gl import RENDER_DIR, program, set_uniforms

__all__ = ["AtlasTexture"]

HERE = Path(__file__).resolve().parent


class AtlasTexture:
    """An RGBA8 texture (linear filtering, clamped to edge) holding the newest decoded picture.

    ``bottom_first``: GL's row order (row 0 the picture's bottom row), as the MeshWarp and ATW shaders sample it;
    otherwise row 0 is the picture's top row (the quad mesh's atlas uv count from the top)."""

    def __init__(self, ctx: moderngl.Context, bottom_first: bool = False):
        self.ctx = ctx
        self.bottom_first = bool(bottom_first)
        self.texture: moderngl.Texture | None = None
        self._fbo: moderngl.Framebuffer | None = None
        self._planes: list[moderngl.Texture] = []
        self._prog = program(ctx, RENDER_DIR / "fullscreen.vert.glsl", HERE / "yuv_to_rgba.frag.glsl")
        self._vao = ctx.vertex_array(self._prog, [])

    @property
    def size(self) -> tuple[int, int] | None:
        """(width, height) of the picture held, or None before the first write."""
        return None if self.texture is None else self.texture.size

    def _target(self, size: tuple[int, int]) -> moderngl.Texture:
        if self.texture is None or self.texture.size != size:
            self._release_texture()
            self.texture = self.ctx.texture(size, 4)
            self.texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
            self.texture.repeat_x = self.texture.repeat_y = False
        return self.texture

    def write(self, picture: YuvPicture) -> None:
        """Hold `picture` (top row first), converted by a draw into the texture's framebuffer, which stays
        bound: bind yours before drawing."""
        if not isinstance(picture, YuvPicture):
            raise ValueError(f"AtlasTexture.write: need a YuvPicture, got {type(picture).__name__}")
        chroma = np.empty(picture.u.shape + (2,), np.uint8)     # Cb and Cr side by side: one fetch for both
        chroma[..., 0], chroma[..., 1] = picture.u, picture.v
        sizes = [(picture.width, picture.height), (chroma.shape[1], chroma.shape[0])]
        if [t.size for t in self._planes] != sizes:
            for t in self._planes:
                t.release()
            self._planes = [self.ctx.texture(size, n, alignment=1) for size, n in zip(sizes, (1, 2))]
            for t in self._planes:
                t.filter = (moderngl.NEAREST, moderngl.NEAREST)
                t.repeat_x = t.repeat_y = False
        self._planes[0].write(np.ascontiguousarray(picture.y))
        self._planes[1].write(chroma)
        target = self._target((picture.width, picture.height))
        if self._fbo is None:
            self._fbo = self.ctx.framebuffer([target])
        self._fbo.use()
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.CULL_FACE)
        for unit, t in enumerate(self._planes):
            t.use(unit)
        set_uniforms(self._prog, u_y=0, u_uv=1, u_bottom_first=self.bottom_first, u_z=0.0)
        self._vao.render(moderngl.TRIANGLES, vertices=3)

    def use(self, location: int = 0) -> None:
        self.texture.use(location)

    def _release_texture(self) -> None:
        for obj in (self._fbo, self.texture):
            if obj is not None:
                obj.release()
        self._fbo = self.texture = None

    def release(self) -> None:
        self._release_texture()
        for t in self._planes:
            t.release()
        self._planes = []
