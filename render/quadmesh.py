"""Layered quad meshes on the GPU: quads -> vertices/indices (compute shader) -> a forward pass from any pose.

Shared by the client (which displays the mesh) and the server (which renders the client's cached mesh to find
what a residual frame must add). Each `MeshLayer` is one layer's `QuadSet` with the camera it was generated from
and where its colour sits in the video atlas. A flattened quad (a plane) becomes one quad of the mesh, a quad with
depth offsets four sub-quads. Each layer keeps its own buffers, so a layer whose quads did not change since the
last build (a client's cache that a residual frame left as it was) is not rebuilt, and a layer whose quads came
from the last build's by a `QuadSetEdit` (the cache after a residual frame) is edited in place: the appended quads
get new vertices at the end, the freed ones empty triangles, until the dead vertices outnumber the live ones.
The triangles drawn, and their order, are those of a build from scratch.

A large layer's flattened quads are then drawn in runs (quad_mesh_runs.comp): quads of one size side by side on one
surface as one rectangle, the others of the rectangle as empty triangles. Along depth edges and over detailed
surfaces the quadtree leaves rows and columns of 1- and 2-pixel quads, and llvmpipe pays per triangle. "One
surface" is bounded by parallax (`run_parallax_px`): a rectangle is drawn where no quad of it lies so far from it
that a viewer RUN_PARALLAX_M beside the layer's camera would see the difference move a point by more than that many
pixels; with 0, the strict test (planes within 1e-3, normals within 2.6 degrees). A monastery view's cache layer
draws 18% of its quads' triangles with the parallax bound, 41% with the strict test. After an edit only the blocks
of places it touched are redone.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import moderngl
import numpy as np

from quadcast.protocol.quads import QuadSet
from quadcast.render.atlas_texture import AtlasTexture
from quadcast.render.camera import Camera, gl_matrix
from quadcast.render.gl import compute, program, set_uniforms
from quadcast.render.quadcache import QuadSetEdit
from quadcast.render.renderer import CullFn, read_texture

HERE = Path(__file__).resolve().parent
QUAD_FLOATS = 24  # uvec4 head, vec4 normal+depth, 4 x vec4 offsets
FLAT_VERTICES, FULL_VERTICES = 4, 16     # a flattened quad is one quad of the mesh, one with offsets four
# Runs (quad_mesh_runs.comp): blocks of same-size flattened quads on one surface drawn as one rectangle, at most
# MAX_RUN quads wide and MAX_STACK high; "one surface": planes within RUN_TOLERANCE (relative) on their shared
# edge, normals within ~2.6 degrees.
MAX_RUN, MAX_STACK, RUN_TOLERANCE, RUN_MIN_COS = 16, 8, 1e-3, 0.999
# With a parallax bound (QuadMesh.run_parallax_px > 0) "one surface" is looser: a rectangle is drawn where every quad
# of it lies so close to it that, seen from RUN_PARALLAX_M beside the layer's camera (the view cell's radius; at 30
# frames/s the quasar server renews its reference within 5 frames, seldom that far away, and a slower server within
# 1 m, where a point moves up to twice as far), no point moves more than run_parallax_px pixels; else its rows, else
# its quads one by one. The pairs need only meet within that distance (no normals).
RUN_PARALLAX_PX, RUN_PARALLAX_M = 0.5, 0.5
MAX_RUN_GRID = 1 << 23   # grid cells (32 MiB): a larger layer is drawn quad by quad
CRACK_TOLERANCE = 0.05  # MeshView's crack fill: the neighbours' depths agree within this share, relative
CRACK_SHARE = 16        # ... and it keeps at most one crack per this many pixels of the view
CRACK_UNIT = 14         # ... and samples the first layer's targets from this texture unit and the next
MIN_RUN_QUADS = 16384    # a smaller layer too: its triangles cost less than finding its runs (about 1 ms)


@dataclass
class MeshLayer:
    quads: QuadSet
    camera: Camera
    atlas_rect: tuple[int, int, int, int]
    # >1 draws the layer slightly farther along each eye ray (same pixels), so that where a fill-in layer
    # (hidden, wide FOV) overlaps the main one at nearly the same depth, the main one wins the depth test.
    depth_scale: float = 1.0
    edit: QuadSetEdit | None = None   # how `quads` came from an earlier QuadSet (see the module's doc)
    # colour from an older frame (a client's cache): where the current view saw the same surfaces, drawn as the
    # mean of both (QuadMesh.set_current_view)
    cached: bool = False


@dataclass
class CurrentView:
    """The newest frame's own view of the scene (QuadMesh.set_current_view): its camera and where its colour sits in
    the atlas."""
    camera: Camera
    atlas_rect: tuple[int, int, int, int]


def quads_to_gpu(quads: QuadSet, first_vertex: int = 0) -> tuple[np.ndarray, int]:
    """The (N, 24) float32 rows the mesh shader reads (offsets zero for flattened quads), each quad's head.w
    holding its first vertex (from `first_vertex` on; its indices start at 3/2 of that) and whether it is
    flattened; and the vertex count. The head's columns are filled in a (4, N) array and copied over in one go
    (filled in place, 96 bytes apart, a monastery view's 80k quads took 3.3 ms instead of 2.1)."""
    n = len(quads)
    flat = quads.flattened          # a QuadSet's offsets hold one row per other quad, in order
    counts = np.where(flat, FLAT_VERTICES, FULL_VERTICES)
    ends = np.cumsum(counts) + first_vertex
    total = int(ends[-1]) - first_vertex if n else 0
    if first_vertex + total >= 1 << 31:
        raise ValueError(f"quad mesh: {first_vertex + total} vertices do not fit a 31-bit vertex index")
    head = np.empty((4, n), np.uint32)
    head[0], head[1], head[2] = quads.x, quads.y, quads.size_log2
    head[3] = ends - counts
    head[3] |= flat.astype(np.uint32) << np.uint32(31)
    rows = np.empty((n, QUAD_FLOATS), np.float32)
    rows[:, :4] = head.view(np.float32).T
    rows[:, 4:7] = quads.normal
    rows[:, 7] = quads.depth
    rows[:, 8:] = 0.0
    if len(quads.offsets):
        rows[~flat, 8:] = quads.offsets
    return rows, total


class _LayerBuffers:
    """One layer's quads, vertices, indices and vertex array; grown as needed. `first` and `count` hold each
    current quad's first vertex and vertex count; vertices up to `end` are in use, `dead` of them by freed quads."""

    def __init__(self) -> None:
        self.quads: QuadSet | None = None   # what the buffers were built from
        self.key = None
        self.quad_capacity = self.vertex_capacity = 0
        self.first = self.count = np.zeros(0, np.int64)
        self.end = self.dead = 0
        self.merged = False   # whether the indices hold runs (QuadMesh._merge_runs)
        self.packed_indices: int | None = None   # how many indices `pack` packed, while they are current
        self.packed_capacity = 0

    @property
    def indices(self) -> int:
        """Indices to draw: those of every vertex slot in use (a quad's start at 3/2 of its first vertex)."""
        return self.end * 3 // 2

    def reserve(self, ctx: moderngl.Context, programs: dict, quads: int, vertices: int) -> None:
        if quads <= self.quad_capacity and vertices <= self.vertex_capacity:
            return
        if self.quad_capacity:
            for b in (*self.vaos.values(), self.quad_buf, self.order_buf, self.vertex_buf, self.index_buf,
                      self.plane_buf):
                b.release()
        self.release_packed()
        # half as much again as asked for: a cache layer's first residual frames append to it in place (with room
        # for exactly the reference frame's quads, the first one rebuilt the whole layer: 20 ms in the courtyard)
        self.quad_capacity = max(quads * 3 // 2, 2 * self.quad_capacity, 256)
        self.vertex_capacity = max(vertices * 3 // 2, 2 * self.vertex_capacity, 256 * FLAT_VERTICES)
        self.quad_buf = ctx.buffer(reserve=self.quad_capacity * QUAD_FLOATS * 4)
        self.order_buf = ctx.buffer(reserve=self.quad_capacity * 4)
        self.vertex_buf = ctx.buffer(reserve=self.vertex_capacity * 5 * 4)
        self.index_buf = ctx.buffer(reserve=self.vertex_capacity * 3 // 2 * 4)
        self.plane_buf = ctx.buffer(reserve=self.vertex_capacity // FLAT_VERTICES * 16)
        self.vaos = self._vertex_arrays(ctx, programs, self.index_buf)

    def _vertex_arrays(self, ctx: moderngl.Context, programs: dict, index_buf: moderngl.Buffer) -> dict:
        """One vertex array per program (QuadMesh.programs), "depth" reading positions alone."""
        return {name: ctx.vertex_array(prog, [(self.vertex_buf, "3f 8x", "in_position")] if name == "depth" else
                                       [(self.vertex_buf, "3f 2f", "in_position", "in_uv")], index_buf)
                for name, prog in programs.items()}

    def pack(self, ctx: moderngl.Context, programs: dict) -> None:
        """Copy the indices of the live triangles, in order, to the packed index buffer (drawn instead of the slots
        until the next build or edit): the empty triangles of freed quads and of runs' other quads cost llvmpipe
        about 30 ns each to cull."""
        idx = np.frombuffer(self.index_buf.read(size=4 * self.indices), np.uint32).reshape(-1, 3)
        live = idx[(idx[:, 0] != idx[:, 1]) | (idx[:, 1] != idx[:, 2])]
        if live.size > self.packed_capacity:
            self.release_packed()
            self.packed_capacity = max(live.size, 3 * 1024)
            self.packed_buf = ctx.buffer(reserve=4 * self.packed_capacity)
            self.packed_vaos = self._vertex_arrays(ctx, programs, self.packed_buf)
        if live.size:
            self.packed_buf.write(live)
        self.packed_indices = live.size

    def release_packed(self) -> None:
        if self.packed_capacity:
            for b in (*self.packed_vaos.values(), self.packed_buf):
                b.release()
        self.packed_capacity, self.packed_indices = 0, None

    def draw(self, program: str) -> None:
        """Draw the layer's triangles with one of QuadMesh.programs."""
        if self.packed_indices is not None:
            vao, count = self.packed_vaos[program], self.packed_indices
        else:
            vao, count = self.vaos[program], self.indices
        if count:
            vao.render(moderngl.TRIANGLES, vertices=count)


def uv_rect(rect: tuple[int, int, int, int], atlas_size: tuple[int, int]) -> tuple[float, float, float, float]:
    """The atlas uv a layer's colour is sampled within (render/quad_mesh_fragment.glsl): its rect (x, y, w, h,
    pixels from the top-left corner) half a texel in from every edge, as (u0, v0, u1, v1)."""
    x, y, w, h = rect
    aw, ah = atlas_size
    return (x + 0.5) / aw, (y + 0.5) / ah, (x + w - 0.5) / aw, (y + h - 0.5) / ah


def _vertex_places(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each uploaded quad's first vertex and vertex count (from its head.w)."""
    w = rows[:, 3].view(np.uint32)
    flat = (w >> np.uint32(31)) != 0
    return (w & np.uint32(0x7FFFFFFF)).astype(np.int64), np.where(flat, FLAT_VERTICES, FULL_VERTICES)


class QuadMesh:
    """GPU buffers holding the layered mesh; `build` refills them (the layers that changed), `draw` renders them."""

    def __init__(self, ctx: moderngl.Context, run_parallax_px: float = RUN_PARALLAX_PX):
        """`run_parallax_px`: the runs' bound (see the module's doc); 0, the strict test. The servers' model of a
        client's mesh takes 0: their residual frames' change test is relative in depth and would count the client's
        half-pixel approximation of far surfaces as changed."""
        self.ctx = ctx
        self.builders = {flat: compute(ctx, HERE / "quad_mesh.comp", FLATTENED=int(flat)) for flat in (True, False)}
        self.eraser = compute(ctx, HERE / "quad_mesh_erase.comp")
        self.runs = [compute(ctx, HERE / "quad_mesh_runs.comp", PASS=k) for k in range(5)]
        self.min_run_quads = MIN_RUN_QUADS   # 0 merges every layer; None none
        self.run_parallax_px = float(run_parallax_px)
        self._scratch_buffers: dict[str, moderngl.Buffer] = {}   # the runs' grid and lists (_scratch)
        # the colour draws sample the atlas's planes (atlas_colour.glsl); the "_rgb" ones an RGBA texture
        self.programs = {name + suffix: program(ctx, HERE / f"{vertex}.vert.glsl", HERE / f"{fragment}.frag.glsl",
                                                **defines)
                         for name, vertex, fragment in (("colour", "quad_mesh", "quad_mesh"),
                                                        ("depth", "quad_mesh", "quad_mesh_depth"),
                                                        ("refresh", "quad_mesh_refresh", "quad_mesh_refresh"))
                         for suffix, defines in (("", {}), ("_rgb", {"ATLAS_RGB": 1}))
                         if name != "depth" or not suffix}
        self.current: CurrentView | None = None
        self._buffers: list[_LayerBuffers] = []
        self.layers: list[tuple[MeshLayer, _LayerBuffers]] = []
        self.quad_count = 0

    def build(self, layers: list[MeshLayer], atlas_size: tuple[int, int]) -> None:
        """Generate every layer's mesh (one compute dispatch per layer), but for a layer whose quads are the very
        same `QuadSet`, camera and atlas place as at the previous build, and edit a layer whose `edit` starts
        from them (see the module's doc). Each layer gets the buffers built from its quads (or from those its
        edit starts from) wherever it stood in the last build's list: a client's far field, kept from its reference
        frame, comes after a number of fill-in layers that changes from frame to frame."""
        self.layers = []
        self.quad_count = sum(len(layer.quads) for layer in layers)
        for layer, buf in zip(layers, self._assign_buffers(layers)):
            key = (layer.camera.to_array().tobytes(), tuple(layer.atlas_rect), tuple(atlas_size))
            if buf.quads is not layer.quads or buf.key != key:
                edit = layer.edit
                merge = self.min_run_quads is not None and len(layer.quads) >= self.min_run_quads
                edited = (edit is not None and buf.quads is edit.previous and buf.key == key
                          and buf.merged == merge and self._edit(layer, buf, atlas_size))
                if not edited:
                    self._generate(layer, buf, atlas_size)
                buf.quads, buf.key, buf.merged, buf.packed_indices = layer.quads, key, merge, None
                if merge:
                    # after an edit only the rows it touched: the others' runs hold the same quads as before
                    self._merge_runs(layer, buf, edit if edited else None)
                    if not edited and buf.indices:
                        # packed after a build from scratch (a reference frame), where it pays: a cache that
                        # changes with every frame (an animated scene) would pack every frame for little gain
                        self.ctx.memory_barrier()
                        buf.pack(self.ctx, self.programs)
            if buf.indices:
                self.layers.append((layer, buf))
        self.ctx.memory_barrier()

    def _assign_buffers(self, layers: list[MeshLayer]) -> list[_LayerBuffers]:
        """The buffers each layer is built in: those last built from its quads or from its edit's previous ones,
        else any left over (or new ones); the buffers no layer takes forget what they held."""
        free = {id(buf.quads): buf for buf in self._buffers if buf.quads is not None}
        chosen = []
        for layer in layers:
            previous = layer.edit.previous if layer.edit is not None else None
            buf = free.pop(id(layer.quads), None) or (free.pop(id(previous), None) if previous is not None else None)
            chosen.append(buf)
        taken = {id(buf) for buf in chosen if buf is not None}
        spare = [buf for buf in self._buffers if id(buf) not in taken]
        for buf in spare:
            buf.quads = None
        for k, buf in enumerate(chosen):
            if buf is None:
                if not spare:
                    spare.append(_LayerBuffers())
                    self._buffers.append(spare[-1])
                chosen[k] = spare.pop(0)
        return chosen

    def _generate(self, layer: MeshLayer, buf: _LayerBuffers, atlas_size: tuple[int, int]) -> None:
        n = len(layer.quads)
        rows, vertices = quads_to_gpu(layer.quads)
        buf.first, buf.count = _vertex_places(rows)
        buf.end, buf.dead = vertices, 0
        if not n:
            return
        buf.reserve(self.ctx, self.programs, n, vertices)
        self._run_builders(layer, buf, rows, atlas_size)

    def _edit(self, layer: MeshLayer, buf: _LayerBuffers, atlas_size: tuple[int, int]) -> bool:
        """Apply layer.edit to buffers built from edit.previous; False (nothing done) where the appended quads do
        not fit the buffers or the freed vertices would outnumber the live ones: build from scratch then."""
        edit = layer.edit
        n = len(edit.previous) + len(edit.appended)
        if len(buf.first) != len(edit.previous) or (edit.kept is not None and len(edit.kept) != n):
            return False
        rows, added = quads_to_gpu(edit.appended, first_vertex=buf.end)
        first, count = _vertex_places(rows)
        first, count = np.concatenate([buf.first, first]), np.concatenate([buf.count, count])
        freed = np.zeros(0, np.int64) if edit.kept is None else np.flatnonzero(~edit.kept)
        dead = buf.dead + int(count[freed].sum())
        end = buf.end + added
        if len(rows) > buf.quad_capacity or end > buf.vertex_capacity or 2 * dead > end:
            return False
        if len(rows):
            self._run_builders(layer, buf, rows, atlas_size)
        if len(freed):
            # after the builders: a quad may be appended and freed by the same edit
            self.ctx.memory_barrier()
            places = np.stack([first[freed], count[freed]], axis=1).astype(np.uint32)
            erased = self.ctx.buffer(places.tobytes())
            erased.bind_to_storage_buffer(0)
            buf.index_buf.bind_to_storage_buffer(2)
            set_uniforms(self.eraser, u_count=len(places))
            self.eraser.run((len(places) + 63) // 64)
            erased.release()
            first, count = first[edit.kept], count[edit.kept]
        buf.first, buf.count, buf.end, buf.dead = first, count, end, dead
        return True

    def _run_builders(self, layer: MeshLayer, buf: _LayerBuffers, rows: np.ndarray,
                      atlas_size: tuple[int, int]) -> None:
        """Run the mesh shader on `rows` (quads_to_gpu's, the head.w of each saying where its vertices go)."""
        n = len(rows)
        flat = (rows[:, 3].view(np.uint32) >> np.uint32(31)) != 0
        n_flat = int(flat.sum())
        # Each kind its own dispatch, through a list of the quads' places (flattened ones first): reordering the
        # rows themselves copied 8 MB for a monastery reference frame (5.8 ms).
        order = np.concatenate([np.flatnonzero(flat), np.flatnonzero(~flat)]).astype(np.uint32)
        buf.quad_buf.write(rows)
        buf.order_buf.write(order)
        buf.quad_buf.bind_to_storage_buffer(0)
        buf.vertex_buf.bind_to_storage_buffer(1)
        buf.index_buf.bind_to_storage_buffer(2)
        buf.order_buf.bind_to_storage_buffer(3)
        buf.plane_buf.bind_to_storage_buffer(4)
        f = layer.camera.frustum
        for is_flat, first, count in ((True, 0, n_flat), (False, n_flat, n)):
            if count > first:
                builder = self.builders[is_flat]
                set_uniforms(builder, u_frustum=(f.left, f.right, f.bottom, f.top), u_near=f.near, u_far=f.far,
                             u_size=(layer.camera.width, layer.camera.height), u_first=first, u_count=count,
                             u_atlas_rect=tuple(float(v) for v in layer.atlas_rect),
                             u_atlas_size=(float(atlas_size[0]), float(atlas_size[1])))
                builder.run((count - first + 63) // 64)

    def _merge_runs(self, layer: MeshLayer, buf: _LayerBuffers, edit: QuadSetEdit | None = None) -> None:
        """Rewrite the indices of the layer's flattened quads as runs (quad_mesh_runs.comp), so that they depend
        only on the quads and their vertices; after `edit` (applied to indices that held runs) only those of the
        quads in a block of MAX_RUN x MAX_STACK places of one size (a run never leaves one) where it appended or
        freed a quad."""
        w, h = layer.camera.width, layer.camera.height
        offsets, cells = [], 0
        for s in range(12):
            offsets.append(cells)
            cells += ((w + (1 << s) - 1) >> s) * ((h + (1 << s) - 1) >> s)
        if cells > MAX_RUN_GRID:
            return
        q = layer.quads
        mask = np.left_shift(1, q.size_log2.astype(np.int32)) - 1
        chosen = (buf.count == FLAT_VERTICES) & ((q.x & mask) == 0) & ((q.y & mask) == 0) & (q.x < w) & (q.y < h)
        if edit is not None:
            changed = [(edit.appended.x, edit.appended.y, edit.appended.size_log2)]
            if edit.kept is not None:
                freed, n = np.flatnonzero(~edit.kept), len(edit.previous)
                prev, app = freed[freed < n], freed[freed >= n] - n
                changed += [(edit.previous.x[prev], edit.previous.y[prev], edit.previous.size_log2[prev]),
                            (edit.appended.x[app], edit.appended.y[app], edit.appended.size_log2[app])]
            def block(x, y, size_log2):
                s = size_log2.astype(np.int32)
                return (np.minimum(y, h - 1) >> s) // MAX_STACK, (np.minimum(x, w - 1) >> s) // MAX_RUN, size_log2

            touched = np.zeros((h // MAX_STACK + 1, w // MAX_RUN + 1, 12), bool)
            for x, y, size_log2 in changed:
                touched[block(x, y, size_log2)] = True
            chosen &= touched[block(q.x, q.y, q.size_log2)]
        sel = np.flatnonzero(chosen)
        if not len(sel):
            return
        places = np.empty((len(sel), 4), np.uint32)
        places[:, 0], places[:, 1], places[:, 2], places[:, 3] = q.x[sel], q.y[sel], q.size_log2[sel], buf.first[sel]
        grid, placed, last = (self._scratch(k, n) for k, n in (("grid", 4 * cells), ("places", places.nbytes),
                                                                ("last", 4 * len(places))))
        grid.clear(size=4 * cells)
        placed.write(places)
        self.ctx.memory_barrier()
        placed.bind_to_storage_buffer(0)
        buf.plane_buf.bind_to_storage_buffer(1)
        buf.index_buf.bind_to_storage_buffer(2)
        grid.bind_to_storage_buffer(3)
        last.bind_to_storage_buffer(4)
        f = layer.camera.frustum
        # a depth error dz at view depth z moves a point f * RUN_PARALLAX_M * dz / z^2 pixels seen from
        # RUN_PARALLAX_M beside the camera (f its focal length in pixels): dz <= parallax * z^2 keeps it within
        # run_parallax_px
        parallax = self.run_parallax_px / (float(min(layer.camera.focal_px)) * RUN_PARALLAX_M)
        for shader in self.runs:
            set_uniforms(shader, u_count=len(places), u_size=(w, h), u_level_offset=offsets, u_max_run=MAX_RUN,
                         u_max_stack=MAX_STACK, u_tolerance=RUN_TOLERANCE, u_parallax=parallax,
                         u_min_cos=RUN_MIN_COS, u_near=f.near, u_frustum=(f.left, f.right, f.bottom, f.top))
            shader.run((len(places) + 63) // 64)
            self.ctx.memory_barrier()

    def _scratch(self, name: str, nbytes: int) -> moderngl.Buffer:
        """The runs' buffer `name`, at least `nbytes` long: kept between builds, grown (doubling) when short."""
        buffer = self._scratch_buffers.get(name)
        if buffer is not None and buffer.size >= nbytes:
            return buffer
        size = max(nbytes, 1 << 16)
        if buffer is not None:
            size = max(size, 2 * buffer.size)
            buffer.release()
        buffer = self._scratch_buffers[name] = self.ctx.buffer(reserve=size)
        return buffer

    def set_current_view(self, camera: Camera | None, atlas_rect: tuple[int, int, int, int] | None = None) -> None:
        """Until the next call, draw the cached layers (MeshLayer.cached) with the current view's colour as well:
        `camera` is the newest frame's own view, its colour at `atlas_rect` of the atlas `draw` is given. A cached
        surface was textured from an older view, often at a steeper angle, and both pictures carry their own coding
        error: where the current view saw the surface the pixel is a weighted mean of both colours (the cached one,
        from a finer-coded reference frame, weighs 0.7). "Saw": the point lies in that view's frustum and the colours
        agree (quad_mesh_refresh_fragment.glsl); a surface in front of it there, of another colour, keeps the cached
        one. None: the cached colour alone (a reference frame's view is the cache's own)."""
        self.current = None if camera is None else CurrentView(camera, tuple(atlas_rect))

    def draw(self, camera: Camera, atlas: AtlasTexture | moderngl.Texture | None,
             after_first: Callable[[], None] | None = None) -> None:
        """Render the mesh from `camera` into the bound framebuffer (depth test on): colour from `atlas` (the
        decoded planes, or an RGBA texture with linear filtering) and view depth into its two targets, or, without
        an atlas, the view depth alone into its one target. `after_first` runs after the first layer's draw
        (MeshView's crack fill), which must leave the same framebuffer bound and the depth test on."""
        current = self.current if atlas is not None else None
        view = camera.view_matrix()
        suffix = "_rgb" if isinstance(atlas, moderngl.Texture) else ""
        names = ("colour" + suffix, "refresh" + suffix) if atlas is not None else ("depth",)
        samplers = {}
        if isinstance(atlas, AtlasTexture):
            samplers = atlas.use(0)
        elif atlas is not None:
            atlas.use(0)
            samplers = {"u_atlas": 0}
        for name in names:
            set_uniforms(self.programs[name], u_proj=gl_matrix(camera.projection_matrix()),
                         u_max_depth=0.999 * camera.frustum.far, **samplers)
        if current is not None:
            x, y, w, h = current.atlas_rect
            aw, ah = atlas.size
            set_uniforms(self.programs["refresh" + suffix], u_current_rect=(x / aw, y / ah, w / aw, h / ah),
                         u_current_uv_rect=uv_rect(current.atlas_rect, atlas.size))
        for place, (layer, buf) in enumerate(self.layers):
            name = "depth" if atlas is None else "refresh" if current is not None and layer.cached else "colour"
            key = name if atlas is None else name + suffix
            prog = self.programs[key]
            if atlas is not None:
                set_uniforms(prog, u_uv_rect=uv_rect(layer.atlas_rect, atlas.size))
            set_uniforms(prog, u_layer_to_view=gl_matrix(view @ layer.camera.pose.camera_to_world()),
                         u_depth_scale=float(layer.depth_scale))
            if name == "refresh":
                set_uniforms(prog, u_layer_to_current=gl_matrix(current.camera.view_projection()
                                                                @ layer.camera.pose.camera_to_world()))
            buf.draw(key)
            if place == 0 and after_first is not None:
                after_first()


class MeshView:
    """An off-screen target for drawing a `QuadMesh` at one size: colour (alpha 1 where drawn), linear view depth
    (R32F, 0 where nothing was drawn) and the depth buffer. With `depth_only` (a server finding what the client's
    mesh covers) no colour: the mesh is drawn without its atlas, the same depths for less work.

    A colour view fills the one-pixel cracks of the mesh's first layer (a client's cache) before the other layers
    are drawn (`crack_fill=False` leaves them). Where quads of different sizes meet on a curved surface, or two
    flattened quads' planes part, the seam between them opens once the eye moves away from the frame's pose, and a
    farther layer or the far field shows through in dots and one-pixel lines. A pixel the first layer missed whose
    two opposite neighbours -- in its row, its column or a diagonal -- it drew at depths that agree takes their mean
    colour and depth (`crack_find.frag.glsl`, which runs only where the first layer drew nothing: the depth test
    leaves out the rest), and is drawn as a point with that depth (`crack_points.vert.glsl`), so the layers drawn
    after it are hidden behind it as behind the surface. A layer tiles its own view, so a gap that view saw
    (between a railing's balusters) holds the layer's farther surface, and stays."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int, clear_color=(0.0, 0.0, 0.0),
                 depth_only: bool = False, crack_fill: bool = True):
        self.ctx, self.width, self.height = ctx, width, height
        self.depth_only = depth_only
        self.color = None if depth_only else ctx.texture((width, height), 4)
        self.view_depth = ctx.texture((width, height), 1, dtype="f4")
        self.view_depth.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.depth = ctx.depth_texture((width, height))
        targets = [self.view_depth] if depth_only else [self.color, self.view_depth]
        self.fbo = ctx.framebuffer(targets, self.depth)
        self.clear_color = clear_color
        self._cracks = _CrackFill(ctx, self) if crack_fill and not depth_only else None

    def render(self, mesh: QuadMesh, camera: Camera, atlas: AtlasTexture | moderngl.Texture | None = None,
               cull: CullFn | None = None) -> None:
        """Clear and draw `mesh` from `camera` (depth test LESS), coloured from `atlas` (none for a depth-only
        view), filling the first layer's cracks. `cull` (see `quadcast.render.renderer.CullFn`) restricts the draw
        to the pixels it leaves at depth 1 (client.stereo's mode 2)."""
        if (atlas is None) != self.depth_only:
            raise ValueError("MeshView.render: a depth-only view takes no atlas, a colour view needs one")
        self.fbo.use()
        self.fbo.clear(*self.clear_color, 0.0, depth=1.0)
        if cull is not None:
            cull(self.depth)
            self.fbo.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        self.ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        mesh.draw(camera, atlas, None if self._cracks is None else lambda: self._cracks.fill(camera))

    def _check_color(self) -> None:
        if self.depth_only:
            raise ValueError("MeshView: a depth-only view has no colour to read")

    def read_color(self) -> np.ndarray:
        """The colour (H, W, 3) uint8, top row first, read as RGB (the driver drops alpha faster than numpy
        copies three of four bytes: 0.9 ms against 3.2 at 960x540)."""
        self._check_color()
        rgb = np.frombuffer(self.fbo.read(components=3, attachment=0), np.uint8)
        return rgb.reshape(self.height, self.width, 3)[::-1].copy()

    def read_drawn(self) -> np.ndarray:
        """Where the mesh drew (or filled a crack), (H, W) bool, top row first: every mesh fragment writes a view
        depth > 0 where the target is cleared to 0."""
        return read_texture(self.view_depth, 1, "f4") > 0

    def read_depth(self) -> np.ndarray:
        """Linear view depth, top row first; inf where nothing was drawn."""
        depth = read_texture(self.view_depth, 1, "f4")
        return np.where(depth > 0, depth, np.inf).astype(np.float32)

    def release(self) -> None:
        for obj in (self.fbo, self.color, self.view_depth, self.depth):
            if obj is not None:
                obj.release()
        if self._cracks is not None:
            self._cracks.release()


class _CrackFill:
    """MeshView's crack fill (see its doc): a pass that lists the cracks, then a draw of them as points."""

    def __init__(self, ctx: moderngl.Context, view: MeshView):
        self.ctx, self.view = ctx, view
        self.capacity = max(1, view.width * view.height // CRACK_SHARE)
        # the points' indirect draw command {count, instances, first, base instance}, then one uvec4 per crack
        self.buffer = ctx.buffer(reserve=16 + 16 * self.capacity)
        self.reset = np.array([0, 1, 0, 0], np.uint32).tobytes()
        self.find = program(ctx, HERE / "fullscreen.vert.glsl", HERE / "crack_find.frag.glsl")
        self.points = program(ctx, HERE / "crack_points.vert.glsl", HERE / "crack_points.frag.glsl")
        self.find_vao = ctx.vertex_array(self.find, [])
        self.points_vao = ctx.vertex_array(self.points, [])
        self.depth_fbo = ctx.framebuffer(depth_attachment=view.depth)   # the find pass writes no target
        self.depth_fbo.depth_mask = False

    def fill(self, camera: Camera) -> None:
        """After the first layer's draw into `view.fbo` (bound, depth test on): find its cracks, draw them."""
        ctx, view = self.ctx, self.view
        self.buffer.write(self.reset)
        self.buffer.bind_to_storage_buffer(0)
        view.color.use(CRACK_UNIT)          # units the mesh's draws leave alone (they bind the atlas's from 0)
        view.view_depth.use(CRACK_UNIT + 1)
        self.depth_fbo.use()
        ctx.depth_func = "<="      # the triangle lies on the far plane: it passes only where nothing was drawn
        set_uniforms(self.find, u_color=CRACK_UNIT, u_view_depth=CRACK_UNIT + 1, u_tolerance=CRACK_TOLERANCE,
                     u_capacity=self.capacity, u_z=1.0)
        self.find_vao.render(moderngl.TRIANGLES, vertices=3)
        ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT)
        view.fbo.use()
        ctx.depth_func = "<"
        set_uniforms(self.points, u_proj=gl_matrix(camera.projection_matrix()),
                     u_size=(view.width, view.height))
        self.points_vao.render_indirect(self.buffer, moderngl.POINTS, count=1)

    def release(self) -> None:
        for obj in (self.find_vao, self.points_vao, self.depth_fbo, self.buffer):
            obj.release()
