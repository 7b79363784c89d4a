"""Quad generation on the GPU (QUASAR §3.2): create -> merge (m-1 passes) -> gather, for one G-buffer layer.

`QuadGenerator(ctx, width, height).generate(gbuffer, camera, params, mask=None)` returns the layer's `QuadSet`
and the milliseconds of each stage. Thresholds follow QUASAR's code: δ_max compares normalised depths
((z - near) / (far - near)), δ_sim compares plane equations (unit normal, offset in metres), δ_flatten compares
depth offsets (metres along the corner's ray).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import moderngl
import numpy as np

from quadcast.protocol.frame import FrameStats
from quadcast.protocol.quads import PACKED_BITS_PER_QUAD, QuadFrame, QuadSet
from quadcast.render.camera import Camera
from quadcast.render.gl import compute, read_buffer, set_uniforms
from quadcast.render.quadmesh import QUAD_FLOATS

HERE = Path(__file__).resolve().parent
TILE = 8                 # the quad passes' workgroups are TILE x TILE entries of a map (quad_tiles.glsl)
MAX_GROUPS_X = 1024      # workgroups per row of a dispatch over a tile list
PLANE_BYTES, OFFSET_BYTES = 4 * 4, 16 * 4   # a Quad Map entry's plane and its 16 offsets (quad_entry.glsl)
# The wide view's quads leave out the pixels whose rays lie inside the main view's frustum scaled by this (2% inside
# its edges, so the wide view overlaps the main view by a pixel or two).
INNER_KEEP = 0.98


def inner_rect(wide: Camera, inner: Camera, margin_px: int = 3) -> tuple[int, int, int, int]:
    """The pixels (x, y, w, h from the top-left) of view `wide` whose centres lie `margin_px` or more inside the
    part of view `inner` (same pose) that `wide`'s quads leave out (`INNER_KEEP`): no quad of `wide`, nor the plane
    of any neighbour one of its quads reads, comes from them. (0, 0, 0, 0) when there are none."""
    wl, wr, wb, wt = wide.frustum.unit_extents
    il, ir, ib, it = (INNER_KEEP * v for v in inner.frustum.unit_extents)
    # pixel-centre coordinates (from the left, from the top) of the inner view's edges in the wide view
    left, right = ((v - wl) / (wr - wl) * wide.width - 0.5 for v in (il, ir))
    top, bottom = ((wt - v) / (wt - wb) * wide.height - 0.5 for v in (it, ib))
    x0, x1 = max(0, math.ceil(left + margin_px)), min(wide.width - 1, math.floor(right - margin_px))
    y0, y1 = max(0, math.ceil(top + margin_px)), min(wide.height - 1, math.floor(bottom - margin_px))
    if x1 < x0 or y1 < y0:
        return (0, 0, 0, 0)
    return (x0, y0, x1 - x0 + 1, y1 - y0 + 1)


@dataclass(frozen=True)
class QuadParams:
    """Quad fitting and merging thresholds of one layer (QUASAR §4.1.2 defaults for the visible layer)."""

    delta_max: float = 0.0005      # depth-discontinuity threshold, normalised depth
    delta_flatten: float = 0.2     # offsets below this (m) are dropped: the quad is "flattened"
    delta_sim: float = 0.5         # plane-equation similarity for merging
    coarse_passes: int = 3         # first passes also merge continuous (non-similar) quads
    max_angle_deg: float = 80.0    # normals are kept within this angle of the view ray
    sky: bool = True               # pixels with no geometry get far, camera-facing quads (the sky's colour)
    max_depth: float = 0.0         # > 0: geometry farther than this (m, view depth) gets no quads (the far field)
    # foveation (fovea.glsl, quadcast.protocol.rate.fovea_scale): delta_sim, delta_flatten and the coarse passes
    # grow with eccentricity from `gaze` (a view-space direction) beyond fovea_deg; fovea_sigma_deg 0 = uniform
    fovea_deg: float = 10.0
    fovea_sigma_deg: float = 0.0
    fovea_gamma: float = 1.0
    fovea_max_scale: float = 8.0
    gaze: tuple[float, float, float] = (0.0, 0.0, -1.0)

    def fovea_uniforms(self) -> dict:
        g = np.asarray(self.gaze, np.float64)
        g = g / max(np.linalg.norm(g), 1e-12)
        return {"u_fovea": (math.radians(self.fovea_deg), math.radians(self.fovea_sigma_deg), self.fovea_gamma,
                            self.fovea_max_scale), "u_gaze": tuple(map(float, g))}

    def relaxed(self, factor: float = 10.0, coarse_passes: int = 4) -> "QuadParams":
        """Hidden layers and wide FOV: thresholds ×factor, one more coarse pass (QUASAR §4.1.2)."""
        return replace(self, delta_flatten=self.delta_flatten * factor, delta_sim=self.delta_sim * factor,
                       coarse_passes=coarse_passes, sky=False)


@dataclass
class QuadTimings:
    quads: float = 0.0
    merge: float = 0.0
    gather: float = 0.0

    @property
    def total(self) -> float:
        return self.quads + self.merge + self.gather

    def add(self, other: "QuadTimings") -> None:
        self.quads += other.quads
        self.merge += other.merge
        self.gather += other.gather


def quad_stats(frame: QuadFrame, ms: dict[str, float], cache_quads: int = 0) -> FrameStats:
    """The server's figures of a quad frame: quads per layer, offsets, raw bits per quad, ms per stage."""
    counts = [len(layer.quads) for layer in frame.layers]
    return FrameStats(ms=ms, quads=int(sum(counts)),
                      quads_per_layer={f"{i}:{layer.kind.name.lower()}": n
                                       for i, (layer, n) in enumerate(zip(frame.layers, counts))},
                      offsets=int(frame.offset_count),
                      bits_per_quad_raw=float(PACKED_BITS_PER_QUAD) if frame.quad_count else 0.0,   # fixed columns
                      cache_quads=cache_quads)


def grow_mask(mask: np.ndarray) -> np.ndarray:
    """A boolean image mask grown by one pixel to its 4 neighbours: scipy.ndimage.binary_dilation(mask,
    iterations=1), as four shifted ORs -- 0.2 ms at 960x540 where scipy takes 4-6 ms."""
    grown = mask.copy()
    grown[1:] |= mask[:-1]
    grown[:-1] |= mask[1:]
    grown[:, 1:] |= mask[:, :-1]
    grown[:, :-1] |= mask[:, 1:]
    return grown


def tile_levels(active: np.ndarray, levels: int) -> list[np.ndarray]:
    """Per level l < `levels`, the sorted (ty << 16) | tx codes of the tiles of level l (2^l level-0 tiles across)
    that hold an `active` ((th, tw) bools) level-0 tile: each level's grid is the one below pooled 2 x 2."""
    out = []
    for level in range(levels):
        ty, tx = np.nonzero(active)
        out.append(ty.astype(np.uint32) << 16 | tx.astype(np.uint32))
        h, w = active.shape
        if level + 1 < levels:
            even = np.zeros((h + (h & 1), w + (w & 1)), bool)
            even[:h, :w] = active
            active = even.reshape(even.shape[0] // 2, 2, even.shape[1] // 2, 2).any(axis=(1, 3))
    return out


def tile_ring(codes: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """The (ty << 16) | tx codes of the tiles of a (tw, th) grid that touch one of `codes` (8-neighbourhood) but
    are not among them."""
    tw, th = grid
    listed = np.zeros((th + 2, tw + 2), bool)
    listed[(codes >> 16).astype(np.int64) + 1, (codes & 0xFFFF).astype(np.int64) + 1] = True
    near = listed.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            near[1:-1, 1:-1] |= listed[1 + dy:th + 1 + dy, 1 + dx:tw + 1 + dx]
    ty, tx = np.nonzero(near[1:-1, 1:-1] & ~listed[1:-1, 1:-1])
    return (ty.astype(np.uint32) << 16) | tx.astype(np.uint32)


def quad_map_levels(width: int, height: int) -> int:
    """m = floor(log2(min(w, h))) + 1 Quad Maps (QUASAR §3.2), capped at the 80-bit format's 2^11 quads."""
    return min(int(math.floor(math.log2(min(width, height)))) + 1, 12)


class QuadGenerator:
    """Pre-allocated Quad Maps for one layer size, and the compute stages: pixel planes, create, merge, gather."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int):
        self.ctx, self.width, self.height = ctx, width, height
        self.levels = quad_map_levels(width, height)
        self.sizes = [(-(-width // (1 << l)), -(-height // (1 << l))) for l in range(self.levels)]
        self.planes = [ctx.buffer(reserve=w * h * PLANE_BYTES) for w, h in self.sizes]
        self.offsets = [ctx.buffer(reserve=w * h * OFFSET_BYTES) for w, h in self.sizes]
        self.capacity = width * height
        self.tile_grids = [(-(-w // TILE), -(-h // TILE)) for w, h in self.sizes]
        # every level's tile list, then the ring around level 0's (the plane pass's extra tiles)
        tw, th = self.tile_grids[0]
        self.tiles = ctx.buffer(reserve=4 * (sum(w * h for w, h in self.tile_grids) + tw * th))
        # under a sparse mask the passes' entries, level by level (listed_pixels, then their parents)
        self.pixels = ctx.buffer(reserve=4 * width * height)
        self.use_pixel_list = True     # False: the passes run on whole tiles under a mask too
        self.pixel_planes = ctx.texture((width, height), 4, dtype="f4")   # quad_planes.comp's, copied from
        self.pixel_planes_buffer = ctx.buffer(reserve=width * height * 16)  # ... the buffer it writes
        self.pixel_planes.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.counter = ctx.buffer(reserve=4)
        self.gathered = ctx.buffer(reserve=self.capacity * QUAD_FLOATS * 4)
        self.plane_pass = compute(ctx, HERE / "quad_planes.comp")
        self.create = compute(ctx, HERE / "quad_create.comp")
        self.merge = compute(ctx, HERE / "quad_merge.comp")
        self.gather = compute(ctx, HERE / "quad_gather.comp")
        self.occupancy = compute(ctx, HERE / "quad_occupancy.comp")
        self.occupied = ctx.buffer(reserve=8 * self.tile_grids[0][0] * self.tile_grids[0][1])
        self._occupied_bits: np.ndarray | None = None    # the last occupied_tiles' read-back, (th, tw, 8) bytes
        self._empty_mask = ctx.texture((1, 1), 1, b"\x01", dtype="u1")
        self._mask = ctx.texture((width, height), 1, dtype="u1")
        self._mask.filter = (moderngl.NEAREST, moderngl.NEAREST)

    def _upload_mask(self, mask: np.ndarray) -> moderngl.Texture:
        """A top-row-first boolean mask of the layer's size, in the generator's mask texture (GL row order)."""
        if mask.shape != (self.height, self.width):
            raise ValueError(f"QuadGenerator: mask is {mask.shape[1]}x{mask.shape[0]}, layer is "
                             f"{self.width}x{self.height}")
        self._mask.write(np.ascontiguousarray(mask[::-1], np.uint8).tobytes())
        return self._mask

    def occupied_tiles(self, position: moderngl.Texture, max_depth: float = 0.0) -> np.ndarray:
        """(th, tw) bools: the tiles of the G-buffer texture `position` holding geometry (nearer than
        `max_depth` when > 0). Reads back a bit per pixel (`occupied_pixels`)."""
        tw, th = self.tile_grids[0]
        position.use(0)
        set_uniforms(self.occupancy, u_position=0, u_size=(self.width, self.height), u_tiles=(tw, th),
                     u_max_depth=max_depth if max_depth > 0 else 3.0e38)
        self.occupied.bind_to_storage_buffer(0)
        self.occupancy.run(-(-tw // 8), -(-th // 8))
        self.ctx.memory_barrier()
        self._occupied_bits = np.frombuffer(self.occupied.read(size=8 * tw * th), np.uint8).reshape(th, tw, 8)
        return self._occupied_bits.any(axis=2)

    def occupied_pixels(self) -> np.ndarray:
        """(height, width) bools, top row first: the pixels holding geometry that the last `occupied_tiles` found."""
        if self._occupied_bits is None:
            raise RuntimeError("QuadGenerator.occupied_pixels: occupied_tiles has not run")
        th, tw = self._occupied_bits.shape[:2]
        bits = np.unpackbits(self._occupied_bits, axis=2, bitorder="little").reshape(th, tw, TILE, TILE)
        return bits.transpose(0, 2, 1, 3).reshape(th * TILE, tw * TILE)[:self.height, :self.width].astype(bool)

    def active_tiles(self, camera: Camera, mask: np.ndarray | None = None, inner: Camera | None = None,
                     occupied: np.ndarray | None = None) -> list[np.ndarray]:
        """Per Quad Map level, the (ty << 16) | tx codes of the TILE x TILE tiles the passes must run on: those
        holding a pixel of `mask`, marked in `occupied` ((th, tw) bools) and, with `inner`, not wholly inside that
        camera's frustum (the create pass writes nothing but empty entries there); at level l, the tiles above
        those of level 0."""
        tw, th = self.tile_grids[0]
        active = np.ones((th, tw), bool) if occupied is None else occupied.copy()
        if mask is not None:
            padded = np.zeros((th * TILE, tw * TILE), bool)
            padded[:self.height, :self.width] = mask
            active &= padded.reshape(th, TILE, tw, TILE).any(axis=(1, 3))
        if inner is not None:
            active &= ~self._inside_tiles(camera, inner)
        return tile_levels(active, self.levels)

    def listed_pixels(self, mask: np.ndarray, codes: np.ndarray) -> np.ndarray | None:
        """The (y << 16) | x of `mask`'s pixels in the level-0 tiles `codes`, row by row: what the plane and create
        passes run on under a mask, and the merge passes on the entries above them (the other pixels of those
        tiles get no quad; on llvmpipe a tile's masked-out pixels cost as much as its kept ones). None where they
        are half the tiles' pixels or more: the tiles themselves cost no more then."""
        tw, th = self.tile_grids[0]
        active = np.zeros((th, tw), bool)
        active[codes >> 16, codes & 0xFFFF] = True
        ys, xs = np.nonzero(mask)
        keep = active[ys // TILE, xs // TILE]
        if 2 * int(keep.sum()) >= len(codes) * TILE * TILE:
            return None
        return (ys[keep].astype(np.uint32) << np.uint32(16)) | xs[keep].astype(np.uint32)

    def _inside_tiles(self, camera: Camera, inner: Camera) -> np.ndarray:
        """(th, tw) bools: tiles whose every pixel centre is a pixel or more inside the part of `inner`'s frustum
        the create pass leaves out (`inner_rect`), so no pixel of theirs gets a quad."""
        tw, th = self.tile_grids[0]
        x, y, w, h = inner_rect(camera, inner, margin_px=1)
        def inside(count: int, size: int, lo: int, n: int) -> np.ndarray:   # tiles' first and last pixels in lo..lo+n-1
            first = np.arange(count) * TILE
            last = np.minimum(first + TILE - 1, size - 1)
            return (first >= lo) & (last <= lo + n - 1) if n > 0 else np.zeros(count, bool)
        return inside(th, self.height, y, h)[:, None] & inside(tw, self.width, x, w)[None, :]

    def _run_tiles(self, prog, base: int, count: int) -> None:
        """Dispatch `prog` on `count` tiles of the list from entry `base`."""
        gx = min(count, MAX_GROUPS_X)
        set_uniforms(prog, u_tile_base=base, u_tile_count=count, u_tile_stride=gx)
        prog.run(gx, -(-count // gx))

    def _run_pixels(self, prog, base: int, count: int) -> None:
        """Dispatch `prog` on `count` entries of `self.pixels` from entry `base`, TILE * TILE a workgroup."""
        self.pixels.bind_to_storage_buffer(8)
        groups = -(-count // (TILE * TILE))
        gx = min(groups, MAX_GROUPS_X)
        set_uniforms(prog, u_pixel_base=base, u_pixel_count=count, u_tile_stride=gx)
        prog.run(gx, -(-groups // gx))

    def _write_entry_lists(self, listed: np.ndarray) -> np.ndarray:
        """`listed` (level 0) and, for each Quad Map level above, the entries holding one of them, into
        `self.pixels`; their first places (levels + 1 of them). The merge pass of level l runs on level l's list:
        an entry holding none of the listed pixels has only empty children, so it would stay empty."""
        ys, xs = (listed >> np.uint32(16)).astype(np.intp), (listed & np.uint32(0xFFFF)).astype(np.intp)
        lists = [listed]
        for level in range(1, self.levels):
            held = np.zeros(self.sizes[level][::-1], bool)      # marking a grid: a third of np.unique's time
            held[ys >> level, xs >> level] = True
            yy, xx = np.nonzero(held)
            lists.append((yy.astype(np.uint32) << np.uint32(16)) | xx.astype(np.uint32))
        data = np.concatenate(lists).astype(np.uint32)
        if data.nbytes > self.pixels.size:
            self.pixels.release()
            self.pixels = self.ctx.buffer(reserve=2 * data.nbytes)
        self.pixels.write(data.tobytes())
        return np.concatenate([[0], np.cumsum([len(x) for x in lists])]).astype(int)

    def _camera_uniforms(self, prog, camera: Camera) -> None:
        f = camera.frustum
        set_uniforms(prog, u_frustum=(f.left, f.right, f.bottom, f.top), u_near=f.near, u_far=f.far,
                     u_size=(self.width, self.height))

    def generate(self, position: moderngl.Texture, normal: moderngl.Texture, camera: Camera, params: QuadParams,
                 mask: np.ndarray | None = None, inner: Camera | None = None) -> tuple[QuadSet, QuadTimings]:
        """Quads for the G-buffer textures `position`/`normal` seen by `camera`. Only pixels where `mask` (a
        boolean (H, W) array, top row first) is set; with `inner`, only pixels outside that camera's frustum."""
        if (camera.width, camera.height) != (self.width, self.height):
            raise ValueError(f"QuadGenerator is for {self.width}x{self.height}, camera is "
                             f"{camera.width}x{camera.height}")
        ctx, timings = self.ctx, QuadTimings()
        max_angle = math.radians(params.max_angle_deg)

        t0 = time.perf_counter()
        # Without sky quads a pixel without geometry gets no quad: only tiles holding some need the passes.
        occupied = None if params.sky else self.occupied_tiles(position, params.max_depth)
        tiles = self.active_tiles(camera, mask, inner, occupied)
        ring = tile_ring(tiles[0], self.tile_grids[0])
        bases = np.concatenate([[0], np.cumsum([len(t) for t in tiles])]).astype(int)
        if len(tiles[0]):
            self.tiles.write(np.concatenate(tiles + [ring]).astype(np.uint32).tobytes())
        # Pixels that may get a quad, where they are few: listed, the passes run on them (listed_pixels). Not with
        # `inner` (the wide view): its plane pass needs the pixels inside the main view next to its own.
        listed = None
        if self.use_pixel_list and inner is None and len(tiles[0]) and (mask is not None or occupied is not None):
            listed = self.listed_pixels(mask if mask is not None else self.occupied_pixels(), tiles[0])
        if listed is not None or len(tiles[0]) < self.tile_grids[0][0] * self.tile_grids[0][1]:
            for buf in self.planes:       # entries the passes do not visit are empty
                buf.clear()
        self.tiles.bind_to_storage_buffer(5)
        position.use(0)
        normal.use(1)
        (self._upload_mask(mask) if mask is not None else self._empty_mask).use(2)
        pixel = dict(u_position=0, u_normal=1, u_mask=2, u_use_mask=mask is not None, u_max_angle=max_angle,
                     u_sky_distance=camera.frustum.far * 0.9 if params.sky else 0.0,
                     u_max_depth=params.max_depth if params.max_depth > 0 else 3.0e38)
        self.pixel_planes.use(3)
        if listed is not None:
            # pixel planes of the listed pixels, the others empty: a listed pixel's neighbours that get a quad
            # are listed too
            self.pixel_planes_buffer.clear()
            if len(listed):
                entry_bases = self._write_entry_lists(listed)
                prog = self.plane_pass
                self.pixel_planes_buffer.bind_to_storage_buffer(7)
                self._camera_uniforms(prog, camera)
                set_uniforms(prog, **pixel)
                self._run_pixels(prog, 0, len(listed))
            ctx.memory_barrier()
            self.pixel_planes.write(self.pixel_planes_buffer)
        elif len(tiles[0]):
            # pixel planes on the create pass's tiles and the ring around them: all a create invocation reads
            prog = self.plane_pass
            self.pixel_planes_buffer.bind_to_storage_buffer(7)
            self._camera_uniforms(prog, camera)
            set_uniforms(prog, u_pixel_count=0, **pixel)
            self._run_tiles(prog, bases[0], len(tiles[0]))
            if len(ring):
                self._run_tiles(prog, bases[-1], len(ring))
            ctx.memory_barrier()
            self.pixel_planes.write(self.pixel_planes_buffer)
        prog = self.create
        self._camera_uniforms(prog, camera)
        fi = inner.frustum if inner is not None else None
        set_uniforms(prog, u_pixel_planes=3, u_exclude_inner=inner is not None,
                     u_inner_frustum=tuple(INNER_KEEP * v for v in fi.unit_extents) if fi else (0.0, 0.0, 0.0, 0.0),
                     u_delta_max=params.delta_max, **pixel)
        self.planes[0].bind_to_storage_buffer(0)
        self.offsets[0].bind_to_storage_buffer(1)
        if listed is not None:
            if len(listed):
                self._run_pixels(prog, 0, len(listed))
        elif len(tiles[0]):
            set_uniforms(prog, u_pixel_count=0)
            self._run_tiles(prog, bases[0], len(tiles[0]))
        ctx.memory_barrier()
        ctx.finish()
        t1 = time.perf_counter()

        # The merge passes append the quads they leave unmerged (quad_append.glsl); the gather pass, those of
        # the last Quad Map.
        self.counter.write(np.zeros(1, np.uint32).tobytes())
        self.counter.bind_to_storage_buffer(4)
        self.gathered.bind_to_storage_buffer(6)
        gather = dict(u_capacity=self.capacity, u_delta_flatten=params.delta_flatten, **params.fovea_uniforms())
        prog = self.merge
        self._camera_uniforms(prog, camera)
        for level in range(1, self.levels):
            (iw, ih), (ow, oh) = self.sizes[level - 1], self.sizes[level]
            self.planes[level - 1].bind_to_storage_buffer(0)
            self.offsets[level - 1].bind_to_storage_buffer(1)
            self.planes[level].bind_to_storage_buffer(2)
            self.offsets[level].bind_to_storage_buffer(3)
            set_uniforms(prog, u_in_size=(iw, ih), u_out_size=(ow, oh), u_out_level=level,
                         u_coarse_passes=params.coarse_passes, u_delta_sim=params.delta_sim,
                         u_delta_max=params.delta_max, u_max_angle=max_angle, **gather)
            if listed is not None:
                if len(listed):
                    self._run_pixels(prog, entry_bases[level], entry_bases[level + 1] - entry_bases[level])
            elif len(tiles[level]):
                set_uniforms(prog, u_pixel_count=0)
                self._run_tiles(prog, bases[level], len(tiles[level]))
            ctx.memory_barrier()
        ctx.finish()
        t2 = time.perf_counter()

        prog, top = self.gather, self.levels - 1
        self._camera_uniforms(prog, camera)
        self.planes[top].bind_to_storage_buffer(0)
        self.offsets[top].bind_to_storage_buffer(3)
        set_uniforms(prog, u_map_size=self.sizes[top], u_level=top, **gather)
        if len(tiles[top]):
            self._run_tiles(prog, bases[top], len(tiles[top]))
        ctx.memory_barrier()
        count = min(int(np.frombuffer(self.counter.read(), np.uint32)[0]), self.capacity)
        rows = np.frombuffer(read_buffer(self.gathered, count * QUAD_FLOATS * 4), np.float32).reshape(count,
                                                                                                       QUAD_FLOATS)
        quads = gathered_to_quadset(rows)
        t3 = time.perf_counter()
        timings.quads, timings.merge, timings.gather = (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3
        return quads, timings


def gathered_to_quadset(rows: np.ndarray) -> QuadSet:
    """Gathered GPU rows -> QuadSet, in a deterministic order (by size, then y, then x)."""
    head = rows[:, :4].view(np.uint32)
    # one stable sort on (size, y, x) packed into a key: np.lexsort's order (2.6 -> 1.5 ms for 20k quads)
    size, y, x = (head[:, k].astype(np.uint64) for k in (2, 1, 0))
    key = (size << np.uint64(40)) | (y << np.uint64(20)) | x
    order = np.argsort(key, kind="stable")
    rows, head = rows[order], head[order]
    flattened = head[:, 3] != 0
    normal = rows[:, 4:7].astype(np.float64)
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    return QuadSet(x=head[:, 0].astype(np.uint16), y=head[:, 1].astype(np.uint16),
                   size_log2=head[:, 2].astype(np.uint8), flattened=flattened,
                   alpha=np.zeros(len(rows), bool), normal=normal.astype(np.float32),
                   depth=rows[:, 7].astype(np.float32), offsets=rows[~flattened, 8:24].astype(np.float16))
