"""The server's G-buffers for one frame (QUASAR §3.1, §3.3): the visible layer, k-1 hidden layers by Effective
Depth Peeling for a view sphere of radius r, and a wide-FOV view; plus the video atlas they are packed into."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from quadcast.render.camera import Camera, Frustum
from quadcast.render.gl import RENDER_DIR, can_copy_textures, compute, copy_texture, program, set_uniforms
from quadcast.render.renderer import DeferredRenderer, GBuffer, MaterialProgram, read_texture

HERE = Path(__file__).resolve().parent
MAX_DEPTH_LEVELS = 8   # levels of LayerRenderer.visible_max (the size of peel_visibility.glsl's u_max_levels)
LIST_FRAGMENT_BYTES = 64              # server/peel_list_buffers.glsl's PeelFragment
INITIAL_LIST_FRAGMENTS_PER_PIXEL = 2  # the one-pass peel's first room, grown by doubling as frames need
MAX_LIST_FRAGMENTS_PER_PIXEL = 16     # its most (a mean over the hidden layers' pixels): beyond, a pass a layer
MAX_LIST_BYTES = 256 << 20            # and at most this much memory
CULL, RESTORE, BEHIND = 0, 1, 2       # the depth steps of server/peel_cull.frag.glsl (LayerRenderer._depth_step)


def wide_camera(camera: Camera, fovy_deg: float = 120.0, scale: float = 0.5) -> Camera:
    """The wide-FOV view at the same pose: `fovy_deg` vertical field of view, `scale` of the resolution."""
    w, h = max(2, int(round(camera.width * scale / 2)) * 2), max(2, int(round(camera.height * scale / 2)) * 2)
    f = Frustum.symmetric(fovy_deg, camera.frustum.aspect, camera.frustum.near, camera.frustum.far)
    return Camera(camera.pose, f, w, h)


def resized(camera: Camera, width: int, height: int) -> Camera:
    """The same view (pose and frustum) as an image of another size."""
    return Camera(camera.pose, camera.frustum, width, height)


class LayerRenderer:
    """Renders the visible layer and the EDP hidden layers into pre-allocated G-buffers.

    The hidden layers are rendered -- peeled, lit and later turned into quads -- at `hidden_size`, the size their
    colour has in the video atlas (QUASAR sends them at reduced resolution), not at the visible layer's: peeling is
    the server's most expensive pass (a draw of the scene, see `one_pass`). They peel from the visible layer's
    view positions reduced to that size (the nearest sample of each block, server/downsample.frag.glsl), not from a
    second render of it: on llvmpipe a geometry pass costs its triangles at any size."""

    def __init__(self, renderer: DeferredRenderer, width: int, height: int, layers: int = 4,
                 hidden_size: tuple[int, int] | None = None):
        if layers < 1:
            raise ValueError(f"need at least 1 layer, got {layers}")
        self.renderer, self.ctx = renderer, renderer.ctx
        self.size = (width, height)
        self.hidden_size = hw, hh = hidden_size or (width, height)
        self.visible = GBuffer(self.ctx, width, height)
        self.visible_small = None          # the visible layer's positions at the hidden size, for peeling
        if layers > 1 and (hw, hh) != (width, height):
            self.visible_small = self.ctx.texture((hw, hh), 4, dtype="f4")
            self.visible_small.filter = (moderngl.NEAREST, moderngl.NEAREST)
            self._small_fbo = self.ctx.framebuffer([self.visible_small])
            self._downsample = program(self.ctx, RENDER_DIR / "fullscreen.vert.glsl", HERE / "downsample.frag.glsl")
            self._downsample_vao = self.ctx.vertex_array(self._downsample, [])
        self.hidden = [GBuffer(self.ctx, hw, hh) for _ in range(layers - 1)]
        # the visible layer's farthest depth over blocks (server/peel_depth_max.comp) for the peel pass's early
        # reject: levels of halved size (rounded up) side by side, at most MAX_DEPTH_LEVELS
        sizes = [(hw, hh)]
        while len(sizes) < MAX_DEPTH_LEVELS and sizes[-1] != (1, 1):
            sizes.append(((sizes[-1][0] + 1) // 2, (sizes[-1][1] + 1) // 2))
        offsets = np.cumsum([0] + [w for w, _ in sizes[:-1]])
        self._depth_levels = np.zeros((MAX_DEPTH_LEVELS, 4), np.int32)        # x offset, width, height, 0
        self._depth_levels[:len(sizes), :3] = [(x, w, h) for x, (w, h) in zip(offsets, sizes)]
        self._depth_level_count = len(sizes)
        self.visible_max = self.ctx.texture((int(offsets[-1]) + sizes[-1][0], hh), 1, dtype="f4")
        self.visible_max.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.early_reject = True            # False: the peel shader runs its full search on every fragment
        # the peel passes leave out closed meshes' back faces (DeferredRenderer.draw_geometry), which no eye in the
        # view cell can see unless it is inside the mesh; False: they peel them like any surface
        self.skip_closed_back_faces = True
        self.visible_max_levels = 0         # the levels the last `render` built
        self._depth_max = {level0: compute(self.ctx, HERE / "peel_depth_max.comp", LEVEL0=level0)
                           for level0 in (1, 0)}
        self.peel = MaterialProgram(self.ctx, RENDER_DIR / "gbuffer.vert.glsl", HERE / "peel.frag.glsl",
                                    MAX_DEPTH_LEVELS=MAX_DEPTH_LEVELS)
        # The hidden layers from one draw of the scene (server/peel_list.frag.glsl stores every potentially visible
        # fragment behind the visible layer in per-pixel lists, server/peel_resolve.frag.glsl takes the layers from
        # them) instead of a draw per layer; False: a peel pass per layer. The same layers either way (on a GPU,
        # which may store a pixel's fragments out of drawing order, up to which of two at exactly one depth is kept).
        self.one_pass = True
        self._peel_list = MaterialProgram(self.ctx, RENDER_DIR / "gbuffer.vert.glsl", HERE / "peel_list.frag.glsl",
                                          MAX_DEPTH_LEVELS=MAX_DEPTH_LEVELS)
        self._peel_resolve = program(self.ctx, RENDER_DIR / "fullscreen.vert.glsl", HERE / "peel_resolve.frag.glsl")
        self._peel_resolve_vao = self.ctx.vertex_array(self._peel_resolve, [])
        self._list_depth = self.ctx.depth_texture((hw, hh))    # the cull step's (see _depth_step)
        self._list_heads = self.ctx.buffer(reserve=4 * (1 + hw * hh))
        self._list_fragments: moderngl.Buffer | None = None
        self.list_capacity = 0               # fragments the lists hold now (grown as frames need)
        self.last_list_fragments = 0         # fragments the last one-pass peel stored
        self._peel_cull = program(self.ctx, RENDER_DIR / "fullscreen.vert.glsl", HERE / "peel_cull.frag.glsl")
        self._peel_cull_vao = self.ctx.vertex_array(self._peel_cull, [])
        self._peel_cull_fbos: dict[int, moderngl.Framebuffer] = {}
        # The one-pass peel's list is drawn with the depth test rejecting, before its shader runs, every fragment
        # at or in front of the visible layer (BEHIND in peel_cull.frag.glsl), which its shader would discard at
        # its first test; False: only those where the visible layer is empty (CULL). The same lists either way.
        self.list_cull_visible = True

    def _depth_step(self, depth: moderngl.Texture, position: moderngl.Texture, step: int,
                    behind: tuple[Camera, float] | None = None) -> None:
        """server/peel_cull.frag.glsl on `depth`: CULL (depth 0 where `position` is empty), RESTORE (depth 1 there
        again) or BEHIND (for the one-pass peel's list, drawn with the test GREATER: `behind` = (its camera, the
        connectivity))."""
        fbo = self._peel_cull_fbos.get(depth.glo)
        if fbo is None:
            fbo = self._peel_cull_fbos[depth.glo] = self.ctx.framebuffer(depth_attachment=depth)
        fbo.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "1"          # always: every pixel drawn takes the step's depth
        position.use(0)
        if behind is not None:
            camera, connectivity = behind
            set_uniforms(self._peel_cull, u_near_far=(camera.frustum.near, camera.frustum.far),
                         u_connectivity=float(connectivity))
        set_uniforms(self._peel_cull, u_position=0, u_step=step, u_z=0.0)
        self._peel_cull_vao.render(moderngl.TRIANGLES, vertices=3)
        self.ctx.depth_func = "<"

    def _peel_uniforms(self, prog: MaterialProgram, focal_px: float, max_level: int, max_radius_px: int,
                       viewcell_radius: float, connectivity: float) -> None:
        """The uniforms of server/peel_visibility.glsl (the visible layer's positions on unit 5, its farthest
        depths on 6)."""
        set_uniforms(prog, u_visible_position=5, u_visible_max=6, u_max_level=max_level,
                     u_max_levels=self._depth_levels.tobytes(), u_focal_px=focal_px,
                     u_viewcell_radius=float(viewcell_radius), u_connectivity=float(connectivity),
                     u_max_radius_px=max_radius_px)

    def _peel_in_one_pass(self, small: Camera, t: float, visible_position: moderngl.Texture,
                          connectivity: float) -> bool:
        """The hidden layers into `self.hidden` from one draw of the scene (see `one_pass`; the peel uniforms
        already set). Returns False, leaving them to the layer-by-layer passes, where the potentially visible
        fragments behind the visible layer outnumber what the lists may hold (MAX_LIST_FRAGMENTS_PER_PIXEL a pixel,
        MAX_LIST_BYTES in all)."""
        ctx, (hw, hh) = self.ctx, self.hidden_size
        for _ in range(2):
            self._list_heads.clear()       # no fragment stored, every list empty
            if self._list_fragments is None:
                self._grow_list(INITIAL_LIST_FRAGMENTS_PER_PIXEL * hw * hh)
            self._list_heads.bind_to_storage_buffer(0)
            self._list_fragments.bind_to_storage_buffer(1)
            # the test only (a fragment behind another is stored too), against the depth behind which the list's
            # shader keeps fragments, or with `list_cull_visible` off against where the visible layer is empty
            if self.list_cull_visible:
                self._depth_step(self._list_depth, visible_position, BEHIND, (small, connectivity))
            else:
                self._depth_step(self._list_depth, visible_position, CULL)
            fbo = self._peel_cull_fbos[self._list_depth.glo]
            fbo.depth_mask = False
            fbo.use()
            ctx.enable(moderngl.DEPTH_TEST)
            ctx.depth_func = ">" if self.list_cull_visible else "<"
            ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
            set_uniforms(self._peel_list, u_capacity=self.list_capacity, u_list_width=hw)
            self.renderer.draw_geometry(small, t, self._peel_list, closed_back_faces=not self.skip_closed_back_faces)
            ctx.depth_func = "<"
            fbo.depth_mask = True
            ctx.memory_barrier()
            stored = int(np.frombuffer(self._list_heads.read(4), np.uint32)[0])
            self.last_list_fragments = stored
            if stored <= self.list_capacity:
                break
            if stored > self._max_list_fragments():
                return False
            self._grow_list(stored)
        else:
            return False
        set_uniforms(self._peel_resolve, u_prev_position=4, u_connectivity=float(connectivity), u_list_width=hw)
        prev_position = visible_position
        for gb in self.hidden:
            gb.geometry_fbo.use()
            gb.clear()
            ctx.enable(moderngl.DEPTH_TEST)
            ctx.depth_func = "1"           # always: every pixel resolved takes its fragment's depth
            prev_position.use(4)
            self._peel_resolve_vao.render(moderngl.TRIANGLES, vertices=3)
            ctx.depth_func = "<"
            gb.camera = small
            prev_position = gb.position
        return True

    def _max_list_fragments(self) -> int:
        hw, hh = self.hidden_size
        return int(min(MAX_LIST_FRAGMENTS_PER_PIXEL * hw * hh, MAX_LIST_BYTES // LIST_FRAGMENT_BYTES))

    def _grow_list(self, fragments: int) -> None:
        """Room for at least `fragments` in the one-pass peel's lists (doubling, within the per-pixel limit)."""
        capacity = max(self.list_capacity, 1)
        while capacity < fragments:
            capacity *= 2
        capacity = min(capacity, self._max_list_fragments())
        if self._list_fragments is not None:
            self._list_fragments.release()
        self._list_fragments = self.ctx.buffer(reserve=LIST_FRAGMENT_BYTES * capacity)
        self.list_capacity = capacity

    def _build_visible_max(self, position: moderngl.Texture, max_level: int) -> None:
        """Levels 0..max_level of `visible_max` from the visible layer's view positions at the hidden size."""
        position.use(0)
        self.visible_max.bind_to_image(0, read=True, write=True)
        for level in range(max_level + 1):
            cs = self._depth_max[int(level == 0)]
            out = self._depth_levels[level]
            set_uniforms(cs, u_position=0, u_out=tuple(int(v) for v in out),
                         u_in=tuple(int(v) for v in self._depth_levels[level - 1]))
            cs.run(-(-int(out[1]) // 8), -(-int(out[2]) // 8))
            self.ctx.memory_barrier()

    def read_visible_max(self, level: int) -> np.ndarray:
        """Level `level` (< `visible_max_levels`) of `visible_max` as the last `render` built it (float32 (h, w), top
        row first)."""
        x, w, h, _ = (int(v) for v in self._depth_levels[level])
        return read_texture(self.visible_max, 1, "f4")[-h:, x:x + w]

    def _cull_where_empty(self, prev_position: moderngl.Texture):
        """A cull step (render.renderer.CullFn) for a peel pass: depth 0 where `prev_position` holds nothing."""
        return lambda depth: self._depth_step(depth, prev_position, CULL)

    def use_hidden_layers(self, count: int) -> None:
        """Render only the first ``count`` hidden layers (of those allocated) from the next frame on."""
        if not hasattr(self, "_allocated"):
            self._allocated = list(self.hidden)
        self.hidden = self._allocated[:max(0, int(count))]

    def hidden_camera(self, camera: Camera) -> Camera:
        return resized(camera, *self.hidden_size)

    def draw_visible(self, camera: Camera, t: float) -> GBuffer:
        """The visible layer's geometry pass alone, for a caller that draws other views' geometry before
        `render(..., visible_drawn=True)` lights it (QuasarServer.encode)."""
        return self.renderer.geometry_pass(camera, t, target=self.visible)

    def render(self, camera: Camera, t: float, viewcell_radius: float, connectivity: float = 0.001,
               max_radius_deg: float = 5.9, visible_drawn: bool = False, hidden: bool = True) -> list[GBuffer]:
        """The visible layer (at the camera's size) and the hidden layers (at `hidden_size`, seen by
        `hidden_camera(camera)`). A hidden fragment is searched for a visible edge within the disc it can shift
        by inside the view sphere, at most `max_radius_deg` of the view across. `visible_drawn`: `draw_visible`
        already drew the visible layer's geometry (same camera and time). `hidden` False: the visible layer alone
        is made, and the hidden layers are returned as the last call left them."""
        r = self.renderer
        if not visible_drawn:
            self.draw_visible(camera, t)
        r.lighting_pass(self.visible, t)
        layers = [self.visible]
        if not self.hidden or not hidden:
            return layers + self.hidden
        small = self.hidden_camera(camera)
        visible_position = layers[0].position
        if self.visible_small is not None:
            # Taken from the visible layer, not rendered again (a geometry pass costs its triangles at any size).
            self._small_fbo.use()
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND)
            layers[0].position.use(0)
            set_uniforms(self._downsample, u_position=0, u_z=0.0, u_small_size=self.hidden_size)
            self._downsample_vao.render(moderngl.TRIANGLES, vertices=3)
            visible_position = self.visible_small
        prev_position = visible_position
        focal_px = small.focal_px[1]  # fy (fx for square pixels)
        max_radius_px = max(1, int(round(focal_px * np.tan(np.radians(max_radius_deg)))))
        # the peel shader's widest square, 2 * (max_radius_px + 1) + 1 pixels, fits 2 x 2 texels of this level
        max_level = min(int(2 * (max_radius_px + 1)).bit_length(), self._depth_level_count - 1)
        if not self.early_reject:
            max_level = -1
        self._build_visible_max(visible_position, max_level)
        self.visible_max_levels = max_level + 1
        visible_position.use(5)
        self.visible_max.use(6)
        if self.one_pass:
            self._peel_uniforms(self._peel_list, focal_px, max_level, max_radius_px, viewcell_radius, connectivity)
            if self._peel_in_one_pass(small, t, visible_position, connectivity):
                for gb in self.hidden:
                    r.lighting_pass(gb, t, geometry_only=True)
                    layers.append(gb)
                return layers
        set_uniforms(self.peel, u_prev_position=4)
        self._peel_uniforms(self.peel, focal_px, max_level, max_radius_px, viewcell_radius, connectivity)
        for gb in self.hidden:
            prev_position.use(4)
            r.geometry_pass(small, t, target=gb, prog=self.peel, cull=self._cull_where_empty(prev_position),
                            closed_back_faces=not self.skip_closed_back_faces)
            self._depth_step(gb.depth, gb.position, RESTORE)
            r.lighting_pass(gb, t, geometry_only=True)    # the atlas needs no sky colour in hidden layers
            layers.append(gb)
            prev_position = gb.position
        return layers


@dataclass(frozen=True)
class AtlasLayout:
    """Where each layer's colour goes in the video frame: the reference view and the new view at full size side by
    side, then the hidden layers and the wide FOV at reduced size in a row below (QUASAR §3.4.1, linear packing),
    then, with a far field, its six cube faces in a row below that."""

    width: int
    height: int
    reference: tuple[int, int, int, int]
    current: tuple[int, int, int, int]
    hidden: tuple[tuple[int, int, int, int], ...]
    wide: tuple[int, int, int, int]
    far: tuple[tuple[int, int, int, int], ...] = ()

    @classmethod
    def for_view(cls, width: int, height: int, hidden_layers: int, wide_size: tuple[int, int],
                 hidden_scale: float = 0.5, far_size: int = 0) -> "AtlasLayout":
        hw, hh = max(2, int(width * hidden_scale)), max(2, int(height * hidden_scale))
        hidden = tuple((i * hw, height, hw, hh) for i in range(hidden_layers))
        wide = (hidden_layers * hw, height, *wide_size)
        aw = max(2 * width, wide[0] + wide[2])
        ah = height + max(hh if hidden_layers else 0, wide[3])
        far = tuple((i * far_size, ah, far_size, far_size) for i in range(6)) if far_size else ()
        if far:
            aw, ah = max(aw, 6 * far_size), ah + far_size
        return cls(aw + aw % 2, ah + ah % 2, (0, 0, width, height), (width, 0, width, height), hidden, wide, far)


class AtlasComposer:
    """Draws layer colour textures into one atlas framebuffer and reads it back for the video encoder."""

    def __init__(self, ctx: moderngl.Context, layout: AtlasLayout):
        self.ctx, self.layout = ctx, layout
        self.texture = ctx.texture((layout.width, layout.height), 4)
        self.fbo = ctx.framebuffer([self.texture])
        self.prog = program(ctx, RENDER_DIR / "fullscreen.vert.glsl", HERE / "atlas.frag.glsl")
        self.vao = ctx.vertex_array(self.prog, [])
        self.fovea_prog = program(ctx, RENDER_DIR / "fullscreen.vert.glsl", HERE / "atlas_fovea.frag.glsl")
        self.fovea_vao = ctx.vertex_array(self.fovea_prog, [])
        # one per rect, not per size: no view's texture is rewritten while a queued draw of another may sample it
        self._fovea_views: dict[tuple[int, int, int, int], tuple[moderngl.Texture, moderngl.Framebuffer]] = {}
        self._copy = can_copy_textures()    # False: every layer is drawn (the pass the copy stands for)

    def clear(self) -> None:
        self.fbo.use()
        self.fbo.viewport = (0, 0, self.layout.width, self.layout.height)
        self.fbo.clear(0.0, 0.0, 0.0, 1.0)

    def draw(self, color: moderngl.Texture, rect: tuple[int, int, int, int]) -> None:
        """`color` into `rect` (x, y, w, h from the top-left corner): copied where it has the rect's size and the
        atlas's format (the same bytes as the drawing pass, which samples it at its texel centres, in a fifth of
        the time on llvmpipe), else drawn, scaled to fit."""
        x, y, w, h = rect
        if self._copy and color.size == (w, h) and (color.components, color.dtype) == (4, "f1"):
            copy_texture(self.ctx, color, self.texture, at=(x, self.layout.height - y - h))
            return
        # rects are top-left based; GL is bottom-left
        self._draw_scaled(color, self.fbo, (x, self.layout.height - y - h, w, h))

    def _draw_scaled(self, color: moderngl.Texture, fbo: moderngl.Framebuffer,
                     viewport: tuple[int, int, int, int]) -> None:
        fbo.use()
        fbo.viewport = viewport
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND)
        color.filter = (moderngl.LINEAR, moderngl.LINEAR)
        color.use(0)
        set_uniforms(self.prog, u_layer=0)
        self.vao.render(moderngl.TRIANGLES, vertices=3)
        color.filter = (moderngl.NEAREST, moderngl.NEAREST)

    def draw_foveated(self, color: moderngl.Texture, rect: tuple[int, int, int, int], levels: int,
                      uniforms: dict) -> None:
        """`color` into `rect` as :meth:`draw` puts it there, coarsened away from the gaze
        (server/atlas_fovea.frag.glsl): through a rect-sized texture whose `levels` mip levels are its copies at 1/2,
        1/4, ... of its size; `uniforms` say where the gaze is and how coarse each eccentricity may be
        (:meth:`quadcast.server.foveation.AtlasFoveation.uniforms`)."""
        x, y, w, h = rect
        view = self._fovea_views.get(tuple(rect))
        if view is None:
            tex = self.ctx.texture((w, h), 4)
            tex.repeat_x = tex.repeat_y = False     # clamped to the view's own edge: no neighbour's colour
            view = self._fovea_views[tuple(rect)] = (tex, self.ctx.framebuffer([tex]))
        tex, fbo = view
        if self._copy and color.size == (w, h) and (color.components, color.dtype) == (4, "f1"):
            copy_texture(self.ctx, color, tex)
        else:
            self._draw_scaled(color, fbo, (0, 0, w, h))
        tex.build_mipmaps(0, max(1, int(levels)))
        tex.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        self.fbo.use()
        self.fbo.viewport = (x, self.layout.height - y - h, w, h)
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND)
        tex.use(0)
        set_uniforms(self.fovea_prog, u_view=0, **uniforms)
        self.fovea_vao.render(moderngl.TRIANGLES, vertices=3)

    def read(self) -> np.ndarray:
        """The atlas as (H, W, 4) RGBA, top row first: what the encoders take, without the 12 ms (at 1920x938)
        that copying out the RGB channels would cost."""
        self.fbo.viewport = (0, 0, self.layout.width, self.layout.height)
        return read_texture(self.texture, 4, "u1")
