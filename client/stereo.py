"""Single-render stereo: the second eye synthesized from the dominant eye's colour and depth.

Mode 1 is YORO (Chen et al., MobiSys '25, sections 5-7), three compute shaders:

1. `yoro_reproject.comp` (Algorithm 1): per ImBuffer pixel, one matrix (dominant view space -> other eye's clip
   space, eq. 5) gives where the pixel lands in the other eye; for parallel eyes that is a shift of f*ipd/z.
2. `yoro_scan.comp` (Algorithm 2): one invocation per row scatters the row, keeps the nearest pixel where
   several land on one, and records each disocclusion's left edge, width and background side.
3. `yoro_patch.comp` (Algorithm 3, eq. 6): per output pixel, colour from the source position; disocclusions
   are filled from background pixels only.

The ImBuffer (intermediate buffer) is `intermediate_scale` times the eye width (full height); the Patcher reads it
at full resolution, interpolating the source position along x.

Mode 2 is stereo shading reprojection (Oculus): the pixels the reprojection cannot supply -- disocclusions, plus
covered pixels within 2 px of a nearer surface in the source (the conservative min-depth triangle filter against
edge ghosting) -- are re-rendered by the caller's draw function, culled everywhere else by a depth mask (depth 0
where the reprojection is kept), and composited with the reprojected pixels.

On the client (`MeshStereo`, used by `QuasarClient.stereo_frame` / `render_stereo`): the dominant eye is drawn
from the quad mesh into the client's `MeshView`, whose colour and linear-depth targets are the synthesizer's
input; mode 2 re-renders the masked pixels of the other eye from the same mesh. Clients without depth (ATW,
MeshWarp) only support rendering both eyes (`stereo_pair(..., "both")`).

Cost ratio (`StereoFrame.cost_ratio`, `quadcast eval --stereo`, `quadcast bench stereo`), as YORO reports it (51.4%):
(dominant-eye render + synthesis [+ mode 2's masked re-render and composite]) / (dominant-eye render + other-eye
render), the other eye rendered normally from the same source; each stage timed from `ctx.finish()` to
`ctx.finish()`, read-backs excluded. Below 1 means one render plus synthesis is cheaper than two renders.

All images on the GPU use GL's row order (bottom first); `read_*` methods return numpy images top row first.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, TypeVar

import moderngl
import numpy as np

from quadcast.render.atlas_texture import AtlasTexture
from quadcast.render.camera import DEFAULT_IPD_M, Camera, Pose, gl_matrix
from quadcast.render.gl import RENDER_DIR, compute, program, set_uniforms
from quadcast.render.quadmesh import MeshView, QuadMesh
from quadcast.render.renderer import CullFn, GBuffer, read_texture

HERE = Path(__file__).resolve().parent
T = TypeVar("T")
# An ImBuffer texel no source pixel has written (yoro_scan.comp; client/stereo_common.glsl has the format): (0, -1).
# The row pass starts from it; the buffer is cleared to it, a fill, where a loop of image stores in the row pass
# itself (eight rows apart, one per SIMD lane) cost llvmpipe ~7 ms at 960x540.
UNSET_TEXEL = (0.0, -1.0, 0.0, 0.0)
ROWS_PER_GROUP = 8   # the row pass's workgroup (yoro_scan.comp): 540 rows make 68 groups for llvmpipe's threads

DrawFn = Callable[[Camera, CullFn], moderngl.Texture]
"""draw_fn(camera, cull) renders `camera`'s view with `cull` as the draw's cull step (`CullFn`: the shared draw
routines `DeferredRenderer.geometry_pass` and `MeshView.render` take it as `cull=`), so only the pixels to
re-render are shaded, and returns the colour texture (RGBA8, the synthesizer's size)."""


def _timed(ctx: moderngl.Context, fn: Callable[[], T]) -> tuple[T, float]:
    """`fn()` and how long it took in milliseconds, the GPU finished before and after."""
    ctx.finish()
    t0 = time.perf_counter()
    out = fn()
    ctx.finish()
    return out, (time.perf_counter() - t0) * 1e3


@dataclass
class StereoResult:
    """The synthesized other eye. Textures belong to the synthesizer and are overwritten by its next call."""

    color: moderngl.Texture   # RGBA8 sRGB, GL rows (bottom first)
    mask: moderngl.Texture    # RG8: r = disoccluded (patched), g = conservative edge reject
    camera: Camera            # the other eye

    def read_color(self) -> np.ndarray:
        """(H, W, 3) uint8, top row first."""
        return read_texture(self.color, 4, "u1")[..., :3]

    def read_masks(self) -> tuple[np.ndarray, np.ndarray]:
        """Both masks from one read-back: (:meth:`read_disocclusion`, :meth:`read_rerender_mask`)."""
        m = read_texture(self.mask, 2, "u1")
        disoccluded = m[..., 0] > 127
        return disoccluded, disoccluded | (m[..., 1] > 127)

    def read_disocclusion(self) -> np.ndarray:
        """(H, W) bool: pixels the dominant eye did not see (filled by the Patcher)."""
        return self.read_masks()[0]

    def read_rerender_mask(self) -> np.ndarray:
        """(H, W) bool: pixels mode 2 re-renders (disocclusions and conservative edge rejects)."""
        return self.read_masks()[1]


class StereoSynthesizer:
    """Makes the other eye of a `width` x `height` stereo pair from the dominant eye's colour and depth.

    `ipd` is the eye separation (metres); `dominant` says which eye is rendered ("left" makes the right eye);
    the ImBuffer is `intermediate_scale` (0, 1] of the eye width (full height), trading edge quality for work.
    Tuning: `linear` interpolates source colours along x (YORO's option d); the Patcher kernel is `kernel_rows`
    high and at most `kernel_max` ImBuffer pixels wide; `continuity` is the relative depth step below which
    neighbouring pixels count as one surface; the conservative filter flags covered pixels whose source has,
    within `edge_radius` pixels, a surface whose disparity exceeds theirs by `edge_disparity` pixels.
    """

    def __init__(self, ctx: moderngl.Context, width: int, height: int, ipd: float = DEFAULT_IPD_M,
                 intermediate_scale: float = 1.0, dominant: str = "left", *, linear: bool = True,
                 kernel_rows: int = 3, kernel_max: int = 16, continuity: float = 0.05, edge_radius: float = 2.0,
                 edge_disparity: float = 0.75, max_stretch: float = 4.0):
        if int(width) != width or int(height) != height or width <= 0 or height <= 0:
            raise ValueError(f"StereoSynthesizer: size must be positive integers, got {width}x{height}")
        if not ipd > 0:
            raise ValueError(f"StereoSynthesizer: ipd must be > 0 metres, got {ipd}")
        if not 0 < intermediate_scale <= 1:
            raise ValueError(f"StereoSynthesizer: intermediate_scale must be in (0, 1], got {intermediate_scale}")
        if dominant not in ("left", "right"):
            raise ValueError(f"StereoSynthesizer: dominant must be 'left' or 'right', got {dominant!r}")
        if kernel_rows < 1 or kernel_max < 1:
            raise ValueError(f"StereoSynthesizer: kernel_rows and kernel_max must be >= 1, "
                             f"got {kernel_rows} and {kernel_max}")
        self.ctx = ctx
        self.width, self.height = int(width), int(height)
        self.ipd = float(ipd)
        self.dominant = dominant
        self.intermediate_width = max(1, int(round(self.width * intermediate_scale)))
        self.settings = dict(u_kernel_rows=int(kernel_rows), u_kernel_max=int(kernel_max),
                             u_continuity=float(continuity), u_edge_radius=float(edge_radius),
                             u_edge_disparity=float(edge_disparity), u_max_stretch=float(max_stretch))
        self.reproject_cs = compute(ctx, HERE / "yoro_reproject.comp")
        self.scan_cs = compute(ctx, HERE / "yoro_scan.comp", FUSED=0, ROWS_PER_GROUP=ROWS_PER_GROUP)
        fixed = dict(LINEAR=int(bool(linear)), COARSE=int(self.intermediate_width < self.width))
        row_words = -(-self.width // 32)   # the fused row pass's same-surface bits: 32-pixel words per row
        # a full-resolution ImBuffer: the three stages' row pass in one dispatch, with and without the edge reject,
        # and its hole pass, which finds the disocclusions' runs
        self.row_cs = None if fixed["COARSE"] else {
            edges: compute(ctx, HERE / "yoro_scan.comp", FUSED=1, EDGES=int(edges), LINEAR=fixed["LINEAR"],
                           ROWS_PER_GROUP=ROWS_PER_GROUP, ROW_WORDS=row_words)
            for edges in (True, False)}
        self.fused_hole_cs = None if fixed["COARSE"] else compute(ctx, HERE / "yoro_patch.comp", HOLES=1, EDGES=0,
                                                                  FIND_RUNS=1, ROW_WORDS=row_words, **fixed)
        # covered pixels (and lists the holes), with and without the edge reject; the listed holes
        self.patch_cs = {edges: compute(ctx, HERE / "yoro_patch.comp", HOLES=0, EDGES=int(edges), **fixed)
                         for edges in (True, False)}
        self.hole_cs = compute(ctx, HERE / "yoro_patch.comp", HOLES=1, EDGES=0, **fixed)
        self.hole_groups_cs = compute(ctx, HERE / "yoro_hole_groups.comp")
        self.composite_cs = compute(ctx, HERE / "stereo_composite.comp")
        self.mask_prog = program(ctx, RENDER_DIR / "fullscreen.vert.glsl", HERE / "stereo_mask.frag.glsl")
        self.fullscreen = ctx.vertex_array(self.mask_prog, [])
        iw, w, h = self.intermediate_width, self.width, self.height
        self.targets = ctx.texture((iw, h), 2, dtype="f4")      # Algorithm 1 output
        self.imbuffer = ctx.texture((iw, h), 2, dtype="f4")     # Algorithm 2 output: covered texels
        self.records = ctx.texture((iw, h), 4, dtype="f4")      # ... and the disocclusions' records
        self.color = ctx.texture((w, h), 4, dtype="f1")
        self.mask = ctx.texture((w, h), 2, dtype="f1")
        self.merged = ctx.texture((w, h), 4, dtype="f1")        # mode 2 composite
        self._imbuffer_fbo = ctx.framebuffer([self.imbuffer])   # to clear it (UNSET_TEXEL)
        self._mask_fbo = ctx.framebuffer([self.mask])            # cleared to 0: the patch writes only its 1s
        self.holes = ctx.buffer(reserve=4 * (1 + w * h))        # the Patcher's hole list: count, then pixels
        self.hole_groups = ctx.buffer(reserve=12)               # its indirect dispatch
        # the fused row pass's same-surface bits per source pixel, which its hole pass reads (yoro_scan.comp)
        self.same_bits = ctx.buffer(reserve=4 * row_words * h)
        self._cull_fbos: dict[int, moderngl.Framebuffer] = {}   # per depth texture drawn into (mode 2)
        for tex in (self.targets, self.imbuffer, self.records, self.color, self.mask, self.merged):
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._last: StereoResult | None = None

    # ------------------------------------------------------------------------------------------------ mode 1
    def other_eye(self, camera: Camera) -> Camera:
        """The camera of the eye this synthesizer makes, given the dominant eye's camera."""
        dx = self.ipd if self.dominant == "left" else -self.ipd
        return camera.with_pose(camera.pose.offset_local([dx, 0.0, 0.0]))

    def _check_inputs(self, color: moderngl.Texture | None, depth: moderngl.Texture, camera: Camera) -> bool:
        size = (self.width, self.height)
        if (camera.width, camera.height) != size:
            raise ValueError(f"synthesize: camera is {camera.width}x{camera.height}, synthesizer is "
                             f"{self.width}x{self.height}")
        if color is not None and (not isinstance(color, moderngl.Texture) or color.depth or color.components != 4
                                  or color.dtype != "f1"):
            raise ValueError("synthesize: color must be an RGBA8 texture (GBuffer.color), got "
                             f"{getattr(color, 'components', '?')} components of {getattr(color, 'dtype', color)!r}")
        if not isinstance(depth, moderngl.Texture) or depth.depth:
            raise ValueError("synthesize: depth must be GBuffer.position (RGBA32F) or a linear-depth R32F texture, "
                             "not a depth buffer")
        if depth.dtype != "f4" or depth.components not in (1, 4):
            raise ValueError(f"synthesize: depth must be RGBA32F view-space positions or R32F linear depth, got "
                             f"{depth.components} components of {depth.dtype!r}")
        for name, tex in (("color", color), ("depth", depth)):
            if tex is not None and tex.size != size:
                raise ValueError(f"synthesize: {name} texture is {tex.size[0]}x{tex.size[1]}, synthesizer is "
                                 f"{self.width}x{self.height}")
        return depth.components == 4

    def synthesize(self, color: moderngl.Texture, depth: moderngl.Texture, camera: Camera,
                   edge_mask: bool = True) -> StereoResult:
        """The other eye from the dominant eye's colour (RGBA8), depth (GBuffer.position or R32F linear depth)
        and camera: the three YORO stages, `reproject`, `scan` and `patch` (with a full-resolution ImBuffer fused
        into one row pass and the hole pass: the same images). `edge_mask=False` skips the conservative edge reject
        (the mask's g), which only mode 2 uses."""
        is_position = self._check_inputs(color, depth, camera)
        if self.row_cs is not None:
            return self._synthesize_rows(color, depth, camera, edge_mask, is_position)
        self.reproject(depth, camera)
        self.scan()
        return self.patch(color, depth, camera, edge_mask)

    def _set_reprojection(self, cs, depth: moderngl.Texture, camera: Camera, is_position: bool) -> None:
        """Algorithm 1's uniforms (eq. 5's matrix, the frustum; depth on unit 1)."""
        other, f = self.other_eye(camera), camera.frustum
        matrix = other.projection_matrix() @ other.view_matrix() @ camera.pose.camera_to_world()
        depth.use(1)
        set_uniforms(cs, u_depth=1, u_depth_is_position=is_position, u_reproject=gl_matrix(matrix),
                     u_extents=f.unit_extents)

    def _patch_uniforms(self, edge_mask: bool, is_position: bool, camera: Camera) -> tuple[bool, dict]:
        """Whether the edge reject runs, and the Patcher's uniforms (colour on unit 0, depth on unit 1)."""
        edges = edge_mask and self.settings["u_edge_radius"] > 0
        settings = self.settings if edges else {**self.settings, "u_edge_radius": 0.0}
        return edges, dict(u_color=0, u_depth=1, u_depth_is_position=is_position,
                           u_disparity_scale=camera.focal_px[0] * self.ipd, **settings)

    def _synthesize_rows(self, color: moderngl.Texture, depth: moderngl.Texture, camera: Camera,
                         edge_mask: bool, is_position: bool) -> StereoResult:
        """`synthesize` with a full-resolution ImBuffer: one row pass (yoro_scan.comp, FUSED) does what
        `reproject`, `scan` and the covered pixels of `patch` do, then the Patcher's hole pass fills the listed
        disocclusions. The same images as the three stages. The inputs are checked (`is_position` is
        `_check_inputs`'s answer)."""
        edges, uniforms = self._patch_uniforms(edge_mask, is_position, camera)
        row_cs = self.row_cs[edges]
        self._set_reprojection(row_cs, depth, camera, is_position)
        set_uniforms(row_cs, **uniforms)
        color.use(0)
        self.imbuffer.bind_to_image(1, read=True, write=True)
        self.color.bind_to_image(2, read=False, write=True)
        self.mask.bind_to_image(3, read=False, write=True)
        self.holes.write(b"\0\0\0\0")
        self.holes.bind_to_storage_buffer(3)
        self.same_bits.bind_to_storage_buffer(5)
        self._clear(self._imbuffer_fbo, UNSET_TEXEL)
        self._clear(self._mask_fbo, (0.0, 0.0, 0.0, 0.0))
        row_cs.run(-(-self.height // ROWS_PER_GROUP))
        self.ctx.memory_barrier()
        return self._fill_holes(camera, uniforms, fused=True)

    def _fill_holes(self, camera: Camera, uniforms: dict, fused: bool = False) -> StereoResult:
        """The Patcher's hole pass over the listed disocclusions (an indirect dispatch); `fused`: after the fused
        row pass, which lists them without their records (the pass finds and writes them)."""
        hole_cs = self.fused_hole_cs if fused else self.hole_cs
        set_uniforms(hole_cs, **uniforms)
        self.imbuffer.bind_to_image(0, read=True, write=False)
        self.records.bind_to_image(4, read=not fused, write=fused)
        self.color.bind_to_image(1, read=False, write=True)
        self.mask.bind_to_image(2, read=False, write=True)
        self.holes.bind_to_storage_buffer(3)
        self.hole_groups.bind_to_storage_buffer(4)
        if fused:
            self.same_bits.bind_to_storage_buffer(5)
        self.hole_groups_cs.run(1)
        self.ctx.memory_barrier()
        hole_cs.run_indirect(self.hole_groups)
        self.ctx.memory_barrier()
        self._last = StereoResult(self.color, self.mask, self.other_eye(camera))
        return self._last

    def _clear(self, target: moderngl.Framebuffer, rgba: tuple[float, float, float, float]) -> None:
        """Fill a whole image the passes read (a clear, where image stores in a pass cost llvmpipe far more)."""
        target.clear(*rgba)
        self.ctx.memory_barrier()

    def reproject(self, depth: moderngl.Texture, camera: Camera) -> None:
        """Algorithm 1 into `targets` (RG32F, ImBuffer size): where each pixel lands in the other eye (x in
        ImBuffer pixel-centre units) and its depth there."""
        is_position = self._check_inputs(None, depth, camera)
        self._set_reprojection(self.reproject_cs, depth, camera, is_position)
        self.targets.bind_to_image(0, read=False, write=True)
        self.reproject_cs.run((self.intermediate_width + 7) // 8, (self.height + 7) // 8)
        self.ctx.memory_barrier()

    def scan(self) -> None:
        """Algorithm 2, `targets` -> `imbuffer` (RG32F) and `records` (RGBA32F): per texel (source u - target u,
        depth) where covered, else (0, -1) and, in `records`, (left edge x, background depth, width,
        background-side neighbour x or -1) of its disocclusion. `read_imbuffer` shows both as one image."""
        set_uniforms(self.scan_cs, **self.settings)
        self._clear(self._imbuffer_fbo, UNSET_TEXEL)
        self.targets.bind_to_image(0, read=True, write=False)
        self.imbuffer.bind_to_image(1, read=True, write=True)
        self.records.bind_to_image(4, read=False, write=True)
        self.scan_cs.run(-(-self.height // ROWS_PER_GROUP))
        self.ctx.memory_barrier()

    def patch(self, color: moderngl.Texture, depth: moderngl.Texture, camera: Camera,
              edge_mask: bool = True) -> StereoResult:
        """Algorithm 3, `imbuffer` + the dominant eye's colour and depth -> the other eye's colour and mask (its
        g, the conservative edge reject, only with `edge_mask`)."""
        is_position = self._check_inputs(color, depth, camera)
        color.use(0)
        depth.use(1)
        edges, uniforms = self._patch_uniforms(edge_mask, is_position, camera)
        patch_cs = self.patch_cs[edges]
        set_uniforms(patch_cs, **uniforms)
        self.imbuffer.bind_to_image(0, read=True, write=False)
        self.color.bind_to_image(1, read=False, write=True)
        self.mask.bind_to_image(2, read=False, write=True)
        self.holes.write(b"\0\0\0\0")
        self.holes.bind_to_storage_buffer(3)
        self._clear(self._mask_fbo, (0.0, 0.0, 0.0, 0.0))
        patch_cs.run((self.width + 7) // 8, (self.height + 7) // 8)
        self.ctx.memory_barrier()
        return self._fill_holes(camera, uniforms)

    def read_imbuffer(self) -> np.ndarray:
        """The ImBuffer as (H, intermediate width, 4) float32, top row first: (source u - target u, depth, 0, 0)
        where covered, its disocclusion's record elsewhere (see `scan`)."""
        covered = read_texture(self.imbuffer, 2, "f4")
        out = read_texture(self.records, 4, "f4")
        is_covered = covered[..., 1] >= 0
        out[is_covered] = 0.0
        out[is_covered, :2] = covered[is_covered]
        return out

    def write_imbuffer(self, image: np.ndarray) -> None:
        """Set the ImBuffer from an image in `read_imbuffer`'s layout (a texel is covered where its z is 0), as
        `patch` reads it."""
        image = np.asarray(image, np.float32)
        if image.shape != (self.height, self.intermediate_width, 4):
            raise ValueError(f"write_imbuffer: expected a ({self.height}, {self.intermediate_width}, 4) image, "
                             f"got {image.shape}")
        is_covered = image[..., 2] == 0
        covered = np.where(is_covered[..., None], image[..., :2], np.float32(UNSET_TEXEL[:2]))
        self.imbuffer.write(np.ascontiguousarray(covered[::-1], np.float32))
        self.records.write(np.ascontiguousarray(image[::-1]))

    def synthesize_gbuffer(self, gb: GBuffer, edge_mask: bool = True) -> StereoResult:
        """`synthesize` from a rendered G-buffer (its lit colour, view positions and camera)."""
        if gb.camera is None:
            raise ValueError("synthesize_gbuffer: the G-buffer has no camera (render it first)")
        return self.synthesize(gb.color, gb.position, gb.camera, edge_mask)

    # ------------------------------------------------------------------------------------------------ mode 2
    def cull(self, depth_texture: moderngl.Texture, result: StereoResult | None = None) -> None:
        """Write the culling mask of `result` (the last one by default) into a depth attachment: 0 where the
        reprojection is kept, 1 where the pixel must be re-rendered. Leaves depth testing on with func LESS and
        the previously bound framebuffer bound."""
        result = result or self._last
        if result is None:
            raise ValueError("cull: nothing synthesized yet")
        if not isinstance(depth_texture, moderngl.Texture) or not depth_texture.depth:
            raise ValueError("cull: expected a depth texture (the draw's depth attachment)")
        if depth_texture.size != (self.width, self.height):
            raise ValueError(f"cull: depth texture is {depth_texture.size[0]}x{depth_texture.size[1]}, "
                             f"synthesizer is {self.width}x{self.height}")
        ctx = self.ctx
        previous = ctx.fbo
        fbo = self._cull_fbos.get(depth_texture.glo)
        if fbo is None:
            fbo = self._cull_fbos[depth_texture.glo] = ctx.framebuffer(depth_attachment=depth_texture)
        try:
            fbo.use()
            ctx.enable(moderngl.DEPTH_TEST)
            ctx.depth_func = "1"  # always: every pixel gets the mask's depth
            result.mask.use(0)
            set_uniforms(self.mask_prog, u_mask=0)
            self.fullscreen.render(moderngl.TRIANGLES, vertices=3)
        finally:
            ctx.depth_func = "<"
            if previous is not None:
                previous.use()

    def rerender_disoccluded(self, draw_fn: DrawFn, result: StereoResult | None = None) -> StereoResult:
        """Mode 2: re-render only the masked pixels of the other eye with `draw_fn` (see `DrawFn`) and composite
        them with the reprojected ones. Returns a result whose colour is the composite."""
        result = result or self._last
        if result is None:
            raise ValueError("rerender_disoccluded: call synthesize first")
        rendered = draw_fn(result.camera, lambda tex: self.cull(tex, result))
        if not isinstance(rendered, moderngl.Texture) or rendered.size != (self.width, self.height):
            raise ValueError(f"rerender_disoccluded: draw_fn must return a {self.width}x{self.height} colour "
                             f"texture, got {rendered!r}")
        result.color.use(0)
        rendered.use(1)
        result.mask.use(2)
        set_uniforms(self.composite_cs, u_reprojected=0, u_rerendered=1, u_mask=2)
        self.merged.bind_to_image(0, read=False, write=True)
        self.composite_cs.run((self.width + 7) // 8, (self.height + 7) // 8)
        self.ctx.memory_barrier()
        return StereoResult(self.merged, result.mask, result.camera)

    def release(self) -> None:
        for obj in (self.fullscreen, self._imbuffer_fbo, self._mask_fbo, self.targets, self.imbuffer, self.records,
                    self.color, self.mask, self.merged, self.holes, self.hole_groups, self.same_bits,
                    *self._cull_fbos.values()):
            obj.release()
        self._cull_fbos.clear()


def deferred_draw_fn(renderer, t: float = 0.0) -> DrawFn:
    """A `DrawFn` for `quadcast.render.renderer.DeferredRenderer` at time `t`: its culled geometry pass into a
    G-buffer of this draw function's own (culled pixels stay empty, so the lighting pass treats them as cheap sky),
    then the lighting pass. The G-buffer last drawn is `draw_fn.gbuffer`."""
    targets: dict[tuple[int, int], GBuffer] = {}

    def draw(camera: Camera, cull: CullFn) -> moderngl.Texture:
        key = (camera.width, camera.height)
        if key not in targets:
            targets[key] = GBuffer(renderer.ctx, *key)
        gb = renderer.geometry_pass(camera, t, target=targets[key], cull=cull)
        renderer.lighting_pass(gb, t)
        draw.gbuffer = gb
        return gb.color

    return draw


@dataclass
class StereoBenchmark:
    """One stereo frame three ways, and what each cost (milliseconds, GPU finished)."""

    left: np.ndarray            # dominant eye (H, W, 3) uint8
    synthesized: np.ndarray     # mode 1: YORO reprojection + Patcher
    rerendered: np.ndarray      # mode 2: reprojection + re-rendered disocclusions / edges
    truth: np.ndarray           # the other eye rendered normally
    disoccluded_fraction: float
    rerender_fraction: float
    synthesize_ms: float
    rerender_ms: float          # mode 2's draw + composite (after synthesize)
    render_ms: float            # rendering the other eye normally (geometry + lighting)


def benchmark_stereo(renderer, camera: Camera, t: float = 0.0, synthesizer: StereoSynthesizer | None = None,
                     repeats: int = 3) -> StereoBenchmark:
    """Render the dominant eye of head `camera` (eyes `synthesizer.ipd` apart), then make the other eye by YORO,
    by mode 2 and by rendering it; times are the median of `repeats` runs after one warm-up."""
    ctx = renderer.ctx
    synth = synthesizer or StereoSynthesizer(ctx, camera.width, camera.height)
    left_pose, right_pose = camera.pose.stereo_eyes(synth.ipd)
    dominant = camera.with_pose(left_pose if synth.dominant == "left" else right_pose)
    draw = deferred_draw_fn(renderer, t)
    synth_ms, rerender_ms, render_ms = [], [], []
    for _ in range(repeats + 1):
        gb = renderer.gbuffer(dominant, t)
        left = gb.read_color()
        result, ms1 = _timed(ctx, lambda: synth.synthesize_gbuffer(gb, edge_mask=False))
        synthesized = result.read_color()
        result = synth.synthesize_gbuffer(gb)                      # mode 2 needs the edge reject too
        merged, ms2 = _timed(ctx, lambda: synth.rerender_disoccluded(draw, result))
        rerendered = merged.read_color()
        _, ms3 = _timed(ctx, lambda: renderer.gbuffer(result.camera, t))
        synth_ms.append(ms1), rerender_ms.append(ms2), render_ms.append(ms3)
    truth = renderer.gbuffer(result.camera, t).read_color()
    fractions = tuple(float(m.mean()) for m in result.read_masks())
    if synthesizer is None:
        synth.release()
    return StereoBenchmark(left, synthesized, rerendered, truth, *fractions, float(np.median(synth_ms[1:])),
                           float(np.median(rerender_ms[1:])), float(np.median(render_ms[1:])))


# ------------------------------------------------------------------------------------- from the quad mesh

STEREO_MODES = ("yoro", "rerender", "both")
"""How a client makes the second eye: `yoro` = mode 1 (reprojection + Patcher), `rerender` = mode 2 (mode 1, then
the disoccluded and edge pixels re-rendered from the mesh), `both` = both eyes rendered (the reference cost)."""


@dataclass
class StereoFrame:
    """One stereo frame made by a client: both eyes, and what each stage cost (ms, GPU finished before and after).

    `ms` has `dominant` (rendering the dominant eye), `synthesize` (YORO's three passes), `rerender` (mode 2's
    masked draw + composite; 0 otherwise) and, when the other eye was also rendered for reference, `other`
    (rendering the other eye normally). Read-backs are not timed."""

    left: np.ndarray                      # (H, W, 3) uint8
    right: np.ndarray
    dominant: str                         # "left" or "right": the eye rendered
    mode: str
    other_camera: Camera                  # the eye that was synthesized
    ms: dict
    rendered_other: np.ndarray | None = None   # the other eye rendered from the same mesh (with_rendered)
    disoccluded_fraction: float | None = 0.0  # None: the masks were not read back (`masks=False`)
    rerender_fraction: float | None = 0.0
    rerender_mask: np.ndarray | None = None    # (H, W) bool: the pixels mode 2 re-renders (None for "both")

    @property
    def synthesized(self) -> np.ndarray:
        """The eye that was synthesized (for `both`, rendered)."""
        return self.right if self.dominant == "left" else self.left

    @property
    def cost_ratio(self) -> float | None:
        """YORO's cost measure: (dominant render + synthesis [+ mode 2 re-render]) / (dominant render + other-eye
        render), from this frame's timings; None unless the other eye was also rendered (`with_rendered`)."""
        if "other" not in self.ms:
            return None
        if self.mode == "both":
            return 1.0
        spent = self.ms["dominant"] + self.ms["synthesize"] + self.ms["rerender"]
        return spent / (self.ms["dominant"] + self.ms["other"])


class MeshStereo:
    """Stereo for a client that shows a `quadcast.render.quadmesh.QuadMesh`: the dominant eye is drawn into the client's
    `MeshView`, whose colour and linear-depth targets feed the `StereoSynthesizer`; mode 2 re-renders the masked
    pixels of the other eye from the same mesh into a second `MeshView` (`MeshView.render` with `cull=`), which
    fills cracks as the client's view does (`crack_fill`)."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int, ipd: float = DEFAULT_IPD_M,
                 dominant: str = "left", crack_fill: bool = True, **synth_options):
        self.ctx = ctx
        self.synth = StereoSynthesizer(ctx, width, height, ipd, dominant=dominant, **synth_options)
        self.other_view = MeshView(ctx, width, height, crack_fill=crack_fill)
        # Warm-up: drivers compile shaders on first use; keep that out of the first frame's timings. Both row
        # passes: with the edge reject (mode "rerender") and without it (mode "yoro").
        probe = Camera.perspective(Pose([0.0, 0.0, 0.0]), width, height)
        for edge_mask in (True, False):
            self.synth.synthesize(self.other_view.color, self.other_view.view_depth, probe, edge_mask=edge_mask)
        ctx.finish()

    def eye_cameras(self, head: Camera) -> tuple[Camera, Camera]:
        """(dominant, other) eye cameras of a head camera: each eye half the IPD from the head, as
        `Pose.stereo_eyes`."""
        left, right = head.pose.stereo_eyes(self.synth.ipd)
        dominant = head.with_pose(left if self.synth.dominant == "left" else right)
        return dominant, self.synth.other_eye(dominant)

    def frame(self, mesh: QuadMesh, view: MeshView, atlas: AtlasTexture, head: Camera, mode: str = "yoro",
              with_rendered: bool = False, masks: bool = True) -> StereoFrame:
        """Both eyes of `head` from `mesh` (drawn with `atlas`) and the client's `view` (a MeshView of this size).
        `masks=False` skips reading back the disocclusion masks (the frame's fractions and mask are then None)."""
        if mode not in STEREO_MODES:
            raise ValueError(f"stereo mode must be one of {', '.join(STEREO_MODES)}, got {mode!r}")
        if (view.width, view.height) != (self.synth.width, self.synth.height):
            raise ValueError(f"stereo: the view is {view.width}x{view.height}, the synthesizer "
                             f"{self.synth.width}x{self.synth.height}")
        ctx = self.ctx
        dominant_cam, other_cam = self.eye_cameras(head)
        ms = {"dominant": 0.0, "synthesize": 0.0, "rerender": 0.0}

        _, ms["dominant"] = _timed(ctx, lambda: view.render(mesh, dominant_cam, atlas))
        dominant_img = view.read_color()
        rendered = None
        if with_rendered or mode == "both":
            _, ms["other"] = _timed(ctx, lambda: self.other_view.render(mesh, other_cam, atlas))
            rendered = self.other_view.read_color()
        fractions, mask = (0.0, 0.0), None
        if mode == "both":
            other_img = rendered
        else:
            result, ms["synthesize"] = _timed(
                ctx, lambda: self.synth.synthesize(view.color, view.view_depth, dominant_cam,
                                                   edge_mask=mode == "rerender"))
            if mode == "rerender":
                def draw(camera: Camera, cull: CullFn) -> moderngl.Texture:
                    self.other_view.render(mesh, camera, atlas, cull=cull)
                    return self.other_view.color
                result, ms["rerender"] = _timed(ctx, lambda: self.synth.rerender_disoccluded(draw, result))
            other_img = result.read_color()
            if masks:
                disoccluded, mask = result.read_masks()
                fractions = (float(disoccluded.mean()), float(mask.mean()))
            else:
                fractions = (None, None)
        left, right = (dominant_img, other_img) if self.synth.dominant == "left" else (other_img, dominant_img)
        return StereoFrame(left, right, self.synth.dominant, mode, other_cam, ms, rendered, *fractions, mask)

    def release(self) -> None:
        self.synth.release()
        self.other_view.release()


def stereo_pair(client, pose, mode: str = "yoro") -> tuple[np.ndarray, np.ndarray]:
    """(left, right) eye images of any `quadcast.client.method.MethodClient` at head `pose`. Clients that keep a depth
    buffer (QuasarClient: quasar, quadstream) support every mode of `STEREO_MODES`; the others (ATW, MeshWarp) only
    `both`, which renders each eye with `quadcast.client.render`."""
    if mode not in STEREO_MODES:
        raise ValueError(f"stereo mode must be one of {', '.join(STEREO_MODES)}, got {mode!r}")
    if hasattr(client, "render_stereo"):
        return client.render_stereo(pose, mode)
    if mode != "both":
        raise ValueError(f"the {getattr(client, 'name', type(client).__name__)} client cannot synthesize an eye "
                         f"(it keeps no depth of what it shows); use mode 'both' or a quasar/quadstream client")
    left, right = pose.stereo_eyes()
    return client.render(left), client.render(right)
