"""The far field (after continuous near-far partitioning, seeds/002): a low-resolution cube map around the view cell.

On every reference frame the server renders six views from the reference pose's position -- a cube map of
everything around the view cell, colour and range, each face a little wider than 90° so neighbouring faces
overlap (`FACE_OVERLAP`) -- and sends it as six quad layers (`LayerKind.FAR`) whose
colour sits in the video atlas. Each face is a grid of `block` x `block`-pixel quads forming one continuous
surface at the range of what the face sees (the farthest depth around each grid corner, so near occluders are
pushed back onto what lies behind them), with 16 depth offsets per quad so that neighbouring quads share their
corners: no cracks, whatever the eye's pose. The client keeps the far field with its reference frame and draws it
behind the quad mesh, so any head rotation shows content -- the sky, or geometry no layer caught -- and geometry
beyond the split distance (`QuadParams.max_depth`) needs no quads at all.

A face's blocks are wide (about 18 degrees at 16 pixels), so where a near object stands before something far, the
surface lies at the far depth and the object's colour is drawn there: seen from beside the cube map's centre it
appears beside the object itself, a ghost of it in the sky or on the wall behind, wherever a gap in the quad mesh
or a head turn shows the far field (a lone object a few metres away shows its ghost beside every silhouette the
head moves past). So the pixels that would move too far against their surface (`near_occluders`: seen from a
given offset, by more than a given angle) take the colour of the nearest pixel on the surface (`fill_from_nearest`)
before the faces go into the atlas.
"""
from __future__ import annotations

import numpy as np
from scipy import ndimage

from quadcast.protocol.quads import LayerKind, QuadLayer, QuadSet, pack_normals, unpack_normals
from quadcast.render.camera import Camera, Frustum, Pose
from quadcast.render.renderer import DeferredRenderer, GBuffer, read_texture

__all__ = ["FACE_DIRECTIONS", "FarField", "face_cameras", "fill_from_nearest", "near_occluders", "range_grid_faces",
           "range_grid_quads"]

# Each face: (the direction it looks at, its up vector), world space (+Y up).
FACE_DIRECTIONS = (((1, 0, 0), (0, 1, 0)), ((-1, 0, 0), (0, 1, 0)), ((0, 1, 0), (0, 0, 1)),
                   ((0, -1, 0), (0, 0, -1)), ((0, 0, 1), (0, 1, 0)), ((0, 0, -1), (0, 1, 0)))


# How far each face reaches past the cube's edges, as a fraction of its half-width at unit distance (0.1: about
# 2.7 degrees). Two faces see the range at their shared edge each from its own image, so their edge vertices can
# lie at different depths along the same rays, and an eye away from the cube's centre sees a seam open between
# them; overlapping faces cover it.
FACE_OVERLAP = 0.1


def face_cameras(position, size: int, near: float, far: float) -> list[Camera]:
    """The six square cameras of a cube map at `position`: 90° faces widened by `FACE_OVERLAP` on every side."""
    p = np.asarray(position, np.float64)
    e = (1.0 + FACE_OVERLAP) * near
    frustum = Frustum(-e, e, -e, e, near, far)
    return [Camera(Pose.look_at(p, p + np.asarray(d, np.float64), up), frustum, size, size)
            for d, up in FACE_DIRECTIONS]


def range_grid_quads(camera: Camera, depth: np.ndarray, block: int, max_depth: float) -> QuadSet:
    """One continuous surface over a face: `block`-pixel quads whose corners lie, along their rays, at the
    farthest view depth (at most `max_depth`; sky counts as `max_depth`) within a block of each grid corner;
    the lattice points between corners are interpolated bilinearly in view depth."""
    return range_grid_faces(camera, np.asarray(depth)[None], block, max_depth)[0]


def _farthest_corners(depths: np.ndarray, block: int, max_depth: float) -> tuple[np.ndarray, np.ndarray]:
    """The faces' depths (faces, h, w) with sky and what lies beyond at `max_depth`, and the depth at every block
    corner (faces, h / block + 1, w / block + 1): the farthest of the blocks around it."""
    f, h, w = depths.shape
    if w % block or h % block or block & (block - 1):
        raise ValueError(f"far field: a {w}x{h} face is not a whole number of {block}-pixel blocks (a power of 2)")
    gx, gy = w // block, h // block
    z = np.where(np.isfinite(depths), np.minimum(depths, max_depth), max_depth)
    blocks = z.reshape(f, gy, block, gx, block).max(axis=(2, 4))
    padded = np.pad(blocks, ((0, 0), (1, 1), (1, 1)), mode="edge")
    return z, np.maximum.reduce([padded[:, :-1, :-1], padded[:, :-1, 1:], padded[:, 1:, :-1], padded[:, 1:, 1:]])


def near_occluders(depths: np.ndarray, block: int, max_depth: float, offset: float, angle_deg: float) -> np.ndarray:
    """Where the far field's faces (view depths (faces, h, w), as `range_grid_faces` takes them) show something
    far nearer than the surface it is drawn on: (faces, h, w) bool, true where an eye `offset` metres from the cube
    map's centre would see the pixel's colour more than `angle_deg` away from where the pixel's own point lies
    (offset * (1/depth - 1/surface depth) radians; the surface between a block's corners taken bilinear in depth).
    A near object before a far background is drawn at the background's depth: these pixels are its ghost."""
    if not (offset > 0 and angle_deg > 0):
        return np.zeros(np.shape(depths), bool)
    z, corners = _farthest_corners(np.asarray(depths), block, max_depth)
    f, h, w = z.shape

    def lerp(n):     # each pixel centre's corner to the left of / above it, and the weight of the next one
        u = (np.arange(n) + 0.5) / block
        i = np.minimum(u.astype(int), n // block - 1)
        return i, u - i
    ix, fx = lerp(w)
    iy, fy = lerp(h)
    rows = corners[:, :, ix] * (1 - fx) + corners[:, :, ix + 1] * fx                       # (f, gy+1, w)
    surface = rows[:, iy] * (1 - fy)[:, None] + rows[:, iy + 1] * fy[:, None]              # (f, h, w)
    return offset * (1.0 / z - 1.0 / surface) > np.radians(angle_deg)


def fill_from_nearest(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """`image` (h, w, ...) with every pixel where `mask` (h, w) is true taken from the nearest one where it is not
    (unchanged where the mask holds everywhere or nowhere)."""
    image, mask = np.asarray(image), np.asarray(mask, bool)
    if mask.shape != image.shape[:2]:
        raise ValueError(f"fill_from_nearest: a {mask.shape} mask for a {image.shape[:2]} image")
    if not mask.any() or mask.all():
        return image.copy()
    _, (iy, ix) = ndimage.distance_transform_edt(mask, return_indices=True)
    return image[iy, ix]


def range_grid_faces(camera: Camera, depths: np.ndarray, block: int, max_depth: float) -> list[QuadSet]:
    """`range_grid_quads` of several faces at once: `depths` (faces, h, w), each seen by a camera with `camera`'s
    frustum and size (a cube map's faces), whose view-space rays are the same: they are worked out once."""
    f, h, w = depths.shape
    gx, gy = w // block, h // block
    corners = _farthest_corners(depths, block, max_depth)[1]                                  # (f, gy+1, gx+1)
    # Depth at the 3x3 lattice of every quad (half-block steps): bilinear between its corners.
    fine = np.empty((f, 2 * gy + 1, 2 * gx + 1))
    fine[:, ::2, ::2] = corners
    fine[:, 1::2, ::2] = 0.5 * (corners[:, :-1] + corners[:, 1:])
    fine[:, :, 1::2] = 0.5 * (fine[:, :, :-2:2] + fine[:, :, 2::2])
    jy, ix = np.mgrid[0:gy, 0:gx]
    ix, jy = ix.ravel(), jy.ravel()
    half = block / 2
    # The plane of each quad faces the camera through the quad's centre, at the centre's lattice depth.
    centre_z = fine[:, 2 * jy + 1, 2 * ix + 1]                                                # (f, quads)
    centre_ray = camera.image_rays((ix + 0.5) * block, (jy + 0.5) * block)
    normal = unpack_normals(*pack_normals(-centre_ray)).astype(np.float64)   # as the client will see it
    centre_point = centre_ray * (centre_z / -centre_ray[:, 2])[..., None]
    d = np.stack([np.einsum("ij,ij->i", normal, p) for p in centre_point])   # a face at a time: one face's sums
    # the 16 offsets at once: sub-quad s (0 TL, 1 TR, 2 BL, 3 BR), corner c (same order), as row 4 s + c
    s, c = np.divmod(np.arange(16), 4)
    a, b = ((s & 1) + (c & 1))[:, None], ((s >> 1) + (c >> 1))[:, None]
    r = camera.image_rays(ix * block + a * half, jy * block + b * half)              # (16, quads, 3)
    t_surface = fine[:, 2 * jy + b, 2 * ix + a] / -r[..., 2]
    t_plane = d[:, None, :] / np.minimum(np.einsum("ij,sij->si", normal, r), -1e-3)
    offsets = (t_surface - t_plane).transpose(0, 2, 1).astype(np.float16)
    n = len(ix)
    normal32 = normal.astype(np.float32)
    return [QuadSet(x=ix * block, y=jy * block, size_log2=np.full(n, int(np.log2(block))),
                    flattened=np.zeros(n, bool), alpha=np.zeros(n, bool), normal=normal32.copy(),
                    depth=centre_z[k].astype(np.float32), offsets=np.ascontiguousarray(offsets[k]))
            for k in range(f)]


class FarField:
    """Renders the cube map of a view cell and makes its quad layers (see the module docstring)."""

    def __init__(self, renderer: DeferredRenderer, size: int, block: int, max_depth: float, detail: float = 1.0):
        """`detail` < 1 draws the faces from the scene's coarse meshes (`DeferredRenderer.coarse_meshes`): a face
        is `size` pixels across 90°, too few to show every triangle of a detailed scene, and llvmpipe pays for each
        one (the monastery's six 64x64 faces: 55 ms with every triangle, 23 ms at 0.1; docs/speed.md, stop 51)."""
        self.renderer, self.size, self.block, self.max_depth = renderer, size, block, max_depth
        self.detail = float(detail)
        renderer.coarse_meshes(self.detail)      # made now, not in the first reference frame
        self.gbuffers = [GBuffer(renderer.ctx, size, size) for _ in FACE_DIRECTIONS]
        self.cameras: list[Camera] = []
        self._depths: np.ndarray | None = None     # the faces' view depths, read by `light` for `layers`
        self.occluded = 0.0                         # the share of the faces' pixels `light` recoloured

    def draw_geometry(self, position, t: float, near: float, far: float) -> None:
        """The six faces' geometry passes at `position`, time `t` (kept on the GPU until the next call); `light`
        lights them. All six first, so that llvmpipe rasterizes each face while the next is drawn (see
        QuasarServer.encode)."""
        self.cameras = face_cameras(position, self.size, near, far)
        for camera, gb in zip(self.cameras, self.gbuffers):
            self.renderer.geometry_pass(camera, t, target=gb, detail=self.detail)

    def light(self, t: float, occluder_offset: float = 0.0, occluder_deg: float = 0.0) -> None:
        """The six faces' lighting passes, after `draw_geometry`; then the pixels that, seen from
        `occluder_offset` metres beside the centre, would lie more than `occluder_deg` from their own point
        (`near_occluders`; 0: none) take the colour of the nearest pixel that would not (`fill_from_nearest`)."""
        for gb in self.gbuffers:
            self.renderer.lighting_pass(gb, t)
        self._depths = np.stack([gb.read_depth() for gb in self.gbuffers])
        mask = near_occluders(self._depths, self.block, self.max_depth, occluder_offset, occluder_deg)
        self.occluded = float(mask.mean())
        for gb, face in zip(self.gbuffers, mask):
            if face.any() and not face.all():
                colour = fill_from_nearest(read_texture(gb.color, 4, "u1"), face)
                gb.color.write(np.ascontiguousarray(colour[::-1]))      # GL rows: bottom first

    def layers(self, rects) -> list[QuadLayer]:
        """The faces' quad layers, their colour at `rects` in the atlas."""
        depths = self._depths if self._depths is not None else np.stack([gb.read_depth() for gb in self.gbuffers])
        self._depths = None
        faces = range_grid_faces(self.cameras[0], depths, self.block, self.max_depth)   # one frustum and size
        return [QuadLayer(LayerKind.FAR, self.size, self.size, camera.to_array(), rect, quads)
                for camera, rect, quads in zip(self.cameras, rects, faces)]

    @property
    def colors(self):
        return [gb.color for gb in self.gbuffers]
