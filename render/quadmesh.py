"""Layered quad meshes on the GPU: quads -> vertices/indices (compute shader) -> a forward pass from any pose.

Shared by the client (which displays the mesh) and the server (which renders the client's cached mesh to find
what a residual frame must add). Each `MeshLayer` is one layer's `QuadSet` with the camera it was generated from
and where its colour sits in the video atlas.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from quadcast.protocol.quads import QuadSet
from quadcast.render.camera import Camera, gl_matrix
from quadcast.render.gl import compute, program, set_uniforms
from quadcast.render.renderer import CullFn, read_texture

HERE = Path(__file__).resolve().parent
QUAD_FLOATS = 24  # uvec4 head, vec4 normal+depth, 4 x vec4 offsets


@dataclass
class MeshLayer:
    quads: QuadSet
    camera: Camera
    atlas_rect: tuple[int, int, int, int]
    # >1 draws the layer slightly farther along each eye ray (same pixels), so that where a fill-in layer
    # (hidden, wide FOV) overlaps the main one at nearly the same depth, the main one wins the depth test.
    depth_scale: float = 1.0


def quads_to_gpu(quads: QuadSet) -> np.ndarray:
    """The (N, 24) float32 rows the mesh and gather shaders use (offsets zero for flattened quads)."""
    n = len(quads)
    rows = np.zeros((n, QUAD_FLOATS), np.float32)
    head = rows[:, :4].view(np.uint32)
    head[:, 0], head[:, 1], head[:, 2] = quads.x, quads.y, quads.size_log2
    rows[:, 4:7] = quads.normal
    rows[:, 7] = quads.depth
    idx = quads.offset_index
    has = idx >= 0
    rows[has, 8:24] = quads.offsets[idx[has]].astype(np.float32)
    return rows


class QuadMesh:
    """GPU buffers holding the layered mesh; `build` refills them, `draw` renders them."""

    def __init__(self, ctx: moderngl.Context, capacity: int = 1 << 16):
        self.ctx = ctx
        self.builder = compute(ctx, HERE / "quad_mesh.comp")
        self.prog = program(ctx, HERE / "quad_mesh.vert.glsl", HERE / "quad_mesh.frag.glsl")
        self.capacity = 0
        self.layers: list[tuple[MeshLayer, int, int]] = []  # layer, first quad, count
        self._reserve(capacity)

    def _reserve(self, quads: int) -> None:
        if quads <= self.capacity:
            return
        cap = max(quads, 2 * self.capacity, 1024)
        for name in ("quad_buf", "vertex_buf", "index_buf", "vao"):
            if hasattr(self, name):
                getattr(self, name).release()
        self.quad_buf = self.ctx.buffer(reserve=cap * QUAD_FLOATS * 4)
        self.vertex_buf = self.ctx.buffer(reserve=cap * 16 * 5 * 4)
        self.index_buf = self.ctx.buffer(reserve=cap * 24 * 4)
        self.vao = self.ctx.vertex_array(self.prog, [(self.vertex_buf, "3f 2f", "in_position", "in_uv")],
                                         self.index_buf)
        self.capacity = cap

    @property
    def quad_count(self) -> int:
        return sum(n for _, _, n in self.layers)

    def build(self, layers: list[MeshLayer], atlas_size: tuple[int, int]) -> None:
        """Upload every layer's quads and generate the mesh (one compute dispatch per layer)."""
        total = sum(len(l.quads) for l in layers)
        self._reserve(total)
        self.layers = []
        if total == 0:
            return
        self.quad_buf.write(np.concatenate([quads_to_gpu(l.quads) for l in layers]).tobytes())
        self.quad_buf.bind_to_storage_buffer(0)
        self.vertex_buf.bind_to_storage_buffer(1)
        self.index_buf.bind_to_storage_buffer(2)
        first = 0
        for layer in layers:
            n = len(layer.quads)
            if n:
                f = layer.camera.frustum
                set_uniforms(self.builder, u_frustum=(f.left, f.right, f.bottom, f.top), u_near=f.near,
                             u_far=f.far, u_size=(layer.camera.width, layer.camera.height), u_count=n,
                             u_base_quad=first, u_atlas_rect=tuple(float(v) for v in layer.atlas_rect),
                             u_atlas_size=(float(atlas_size[0]), float(atlas_size[1])))
                self.builder.run((n + 63) // 64)
                self.layers.append((layer, first, n))
            first += n
        self.ctx.memory_barrier()

    def draw(self, camera: Camera, atlas: moderngl.Texture) -> None:
        """Render the mesh from `camera` into the bound framebuffer (depth test on)."""
        atlas.use(0)
        set_uniforms(self.prog, u_atlas=0, u_proj=gl_matrix(camera.projection_matrix()))
        view = camera.view_matrix()
        for layer, first, n in self.layers:
            set_uniforms(self.prog, u_layer_to_view=gl_matrix(view @ layer.camera.pose.camera_to_world()),
                         u_depth_scale=float(layer.depth_scale))
            self.vao.render(moderngl.TRIANGLES, vertices=24 * n, first=24 * first)


class MeshView:
    """An off-screen target for drawing a `QuadMesh`: colour, view position and depth at one size."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int, clear_color=(0.0, 0.0, 0.0)):
        self.ctx, self.width, self.height = ctx, width, height
        self.color = ctx.texture((width, height), 4)
        self.position = ctx.texture((width, height), 4, dtype="f4")
        self.position.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.depth = ctx.depth_texture((width, height))
        self.fbo = ctx.framebuffer([self.color, self.position], self.depth)
        self.clear_color = clear_color

    def render(self, mesh: QuadMesh, camera: Camera, atlas: moderngl.Texture, cull: CullFn | None = None) -> None:
        """Clear and draw `mesh` from `camera` (depth test LESS). `cull` (see `quadcast.render.renderer.CullFn`)
        restricts the draw to the pixels it leaves at depth 1 (client.stereo's mode 2)."""
        self.fbo.use()
        self.fbo.clear(*self.clear_color, 0.0, depth=1.0)
        if cull is not None:
            cull(self.depth)
            self.fbo.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        self.ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        mesh.draw(camera, atlas)

    def read_color(self) -> np.ndarray:
        return read_texture(self.color, 4, "u1")[..., :3]

    def read_color_drawn(self) -> tuple[np.ndarray, np.ndarray]:
        """The colour (H, W, 3) and where the mesh drew (H, W) bool, from one read-back: the target is cleared to
        alpha 0 and every mesh fragment writes alpha 1."""
        rgba = read_texture(self.color, 4, "u1")
        return np.ascontiguousarray(rgba[..., :3]), rgba[..., 3] > 0

    def read_depth(self) -> np.ndarray:
        pos = read_texture(self.position, 4, "f4")
        return np.where(pos[..., 3] > 0, -pos[..., 2], np.inf).astype(np.float32)
