"""The deferred renderer every part shares: G-buffer pass, sun shadow map, lighting pass.

`DeferredRenderer(scene).render(camera, t)` returns a `RenderedFrame` of numpy images (lit sRGB colour, linear
depth, view-space normal, object id). `gbuffer(camera, t)` does the same passes but leaves the results on the GPU
(`GBuffer`), for the server's compute shaders. Results are deterministic for a given scene, camera and time.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import moderngl
import numpy as np
import trimesh

from quadcast.render.camera import Camera, gl_matrix
from quadcast.render.gl import (can_copy_textures, copy_texture, gl_context, program, set_uniforms,
                                write_changed_uniforms)
from quadcast.render.scene import Scene

HERE = Path(__file__).resolve().parent

COARSE_MIN_TRIANGLES = 256
"""`DeferredRenderer.coarse_meshes` keeps at least this many triangles of a mesh: decimating a small one saves
nothing."""

CullFn = Callable[[moderngl.Texture], None]
"""A cull step for a draw routine (`DeferredRenderer.geometry_pass`, `quadcast.render.quadmesh.MeshView.render`):
called with the target's depth attachment after it is cleared to 1, it writes depth 0 where nothing may be drawn
(e.g. `quadcast.client.stereo.StereoSynthesizer.cull`'s mask) and may bind another framebuffer; the routine then
rebinds its own and draws with depth test LESS, so only the pixels left at depth 1 are drawn."""


class MaterialProgram:
    """A geometry-pass program (its fragment shader includes render/material.glsl) built once per albedo source
    (`ALBEDO`: 0 the texture at mesh UVs, 1 triplanar, 2 none), so that a draw runs only its object's way of sampling:
    `variant(source)` is the program to draw with. `set_uniforms` sets a uniform on all of them (`get` returns a
    member that writes to each), so callers treat it as one program."""

    def __init__(self, ctx: moderngl.Context, vertex: Path, fragment: Path, **defines):
        self.variants = tuple(program(ctx, vertex, fragment, ALBEDO=source, **defines) for source in range(3))

    def variant(self, source: int) -> moderngl.Program:
        return self.variants[source]

    def get(self, name: str, default=None):
        members = [m for m in (p.get(name, None) for p in self.variants) if m is not None]
        return _Members(members) if members else default


class _Members:
    """One uniform of each of a `MaterialProgram`'s programs, set together."""

    def __init__(self, members: list):
        self._members = members

    def write(self, data: bytes) -> None:
        for m in self._members:
            m.write(data)

    @property
    def value(self):
        return self._members[0].value

    @value.setter
    def value(self, value) -> None:
        for m in self._members:
            m.value = value


@dataclass
class RenderedFrame:
    """One rendered view as numpy arrays, top row first."""

    color: np.ndarray      # (H, W, 3) uint8, sRGB
    depth: np.ndarray      # (H, W) float32, linear view depth in metres; inf where nothing was hit
    normal: np.ndarray     # (H, W, 3) float32, view space, facing the camera
    object_id: np.ndarray  # (H, W) int32, 0 where nothing was hit


def read_texture(tex: moderngl.Texture, components: int, dtype: str) -> np.ndarray:
    """A texture's level 0 as a numpy array, flipped so the top row comes first."""
    data = np.frombuffer(tex.read(), dtype=np.dtype(dtype))
    shape = (tex.height, tex.width, components) if components > 1 else (tex.height, tex.width)
    return data.reshape(shape)[::-1].copy()


class GBuffer:
    """GPU-resident render targets of one view: albedo, view normal, view position, object id, depth, lit colour."""

    def __init__(self, ctx: moderngl.Context, width: int, height: int):
        self.ctx, self.width, self.height = ctx, width, height
        self._linear_depth: tuple | None = None      # (texture, framebuffer, vertex array, program), on first use
        self.albedo = ctx.texture((width, height), 4, dtype="f2")
        self.normal = ctx.texture((width, height), 4, dtype="f2")
        self.position = ctx.texture((width, height), 4, dtype="f4")
        self.object_id = ctx.texture((width, height), 1, dtype="i4")
        self.depth = ctx.depth_texture((width, height))
        self.color = ctx.texture((width, height), 4, dtype="f1")
        for tex in (self.albedo, self.normal, self.position, self.object_id, self.color):
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.geometry_fbo = ctx.framebuffer([self.albedo, self.normal, self.position, self.object_id], self.depth)
        self.color_fbo = ctx.framebuffer([self.color])
        self.color_depth_fbo = ctx.framebuffer([self.color], self.depth)    # lighting where geometry is
        self.camera: Camera | None = None
        self.culled = False      # the last geometry pass was culled: its depth does not tell where geometry is

    def clear(self) -> None:
        self.geometry_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)

    def read_color(self) -> np.ndarray:
        return read_texture(self.color, 4, "u1")[..., :3]

    def read_depth(self, region: tuple[int, int, int, int] | None = None) -> np.ndarray:
        """Linear view depth in metres (inf where nothing was hit); of `region` (x, y, w, h from the top-left)
        only, when given. The whole view is converted on the GPU (render/linear_depth.frag.glsl) and read as one
        float per pixel."""
        if region is None:
            if self._linear_depth is None:
                tex = self.ctx.texture((self.width, self.height), 1, dtype="f4")
                prog = program(self.ctx, HERE / "fullscreen.vert.glsl", HERE / "linear_depth.frag.glsl")
                self._linear_depth = (tex, self.ctx.framebuffer([tex]), self.ctx.vertex_array(prog, []), prog)
            tex, fbo, vao, prog = self._linear_depth
            fbo.use()
            self.ctx.disable(moderngl.DEPTH_TEST | moderngl.BLEND)
            self.position.use(0)
            set_uniforms(prog, u_position=0, u_z=0.0)
            vao.render(moderngl.TRIANGLES, vertices=3)
            return read_texture(tex, 1, "f4")
        pos = self._read(2, 4, "f4", region)
        return np.where(pos[..., 3] > 0, -pos[..., 2], np.inf).astype(np.float32)

    def _read(self, attachment: int, components: int, dtype: str, region) -> np.ndarray:
        if region is None:
            tex = self.geometry_fbo.color_attachments[attachment]
            return read_texture(tex, components, dtype)
        x, y, w, h = region
        data = self.geometry_fbo.read(viewport=(x, self.height - y - h, w, h), components=components,
                                      attachment=attachment, dtype=dtype)
        shape = (h, w, components) if components > 1 else (h, w)
        return np.frombuffer(data, np.dtype(dtype)).reshape(shape)[::-1].copy()

    def read_depth_buffer(self) -> np.ndarray:
        """The raw [0, 1] depth buffer."""
        return read_texture(self.depth, 1, "f4")

    def read_normal(self) -> np.ndarray:
        return read_texture(self.normal, 4, "f2")[..., :3].astype(np.float32)

    def read_object_id(self, region: tuple[int, int, int, int] | None = None) -> np.ndarray:
        return self._read(3, 1, "i4", region)

    def read(self) -> RenderedFrame:
        return RenderedFrame(self.read_color(), self.read_depth(), self.read_normal(), self.read_object_id())

    def release(self) -> None:
        if self._linear_depth is not None:
            for obj in self._linear_depth[:3]:
                obj.release()
            self._linear_depth = None
        for obj in (self.geometry_fbo, self.color_fbo, self.color_depth_fbo, self.albedo, self.normal, self.position,
                    self.object_id, self.depth, self.color):
            obj.release()


def _box_corners(lo, hi) -> np.ndarray:
    """(8, 3) float64: the corners of the box from `lo` to `hi`."""
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])], np.float64)


class _GpuMesh:
    def __init__(self, ctx, mesh, shadow_prog, white, texture: moderngl.Texture | None = None):
        """A mesh's buffers; `texture`, when given, is its material's texture already uploaded (a coarse mesh's)."""
        pos = mesh.positions
        uvs = mesh.uvs if mesh.uvs is not None else np.zeros((len(pos), 2), np.float32)
        # One buffer per attribute: llvmpipe is far slower with a padded interleaved layout in the shadow pass.
        self.positions = ctx.buffer(pos.astype("f4").tobytes())
        self.normals = ctx.buffer(mesh.normals.astype("f4").tobytes())
        self.uvs = ctx.buffer(uvs.astype("f4").tobytes())
        self.ibo = ctx.buffer(mesh.indices.astype("u4").tobytes())
        self._vaos: dict[int, moderngl.VertexArray] = {}
        self.ctx = ctx
        self.box_corners = _box_corners(pos.min(axis=0), pos.max(axis=0))     # object space
        self.shadow_vao = ctx.vertex_array(shadow_prog, [(self.positions, "3f", "in_position")], self.ibo)
        mat = mesh.material
        if texture is not None:
            self.texture = texture
        elif mat.texture is not None:
            img = np.ascontiguousarray(mat.texture[::-1])  # GL's first row is the bottom one
            self.texture = ctx.texture((img.shape[1], img.shape[0]), img.shape[2], img.tobytes())
            self.texture.build_mipmaps()
            self.texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
        else:
            self.texture = white
        # its material's uniforms as the geometry pass writes them (render/material.glsl), (name, bytes) pairs
        self.material_uniforms = (
            ("u_texture", struct.pack("i", 0)), ("u_base_color", np.asarray(mat.base_color, np.float32).tobytes()),
            ("u_uv_scale", struct.pack("f", mat.uv_scale)), ("u_specular", struct.pack("f", mat.specular)),
            ("u_shininess", struct.pack("f", max(mat.shininess, 1.0))),
            ("u_emissive", np.asarray(mat.emissive, np.float32).tobytes()))
        # where its albedo comes from (render/material.glsl's ALBEDO): no texture, triplanar or the mesh's UVs
        self.albedo_source = 2 if mat.texture is None else 1 if mat.uv_mode == "triplanar" or mesh.uvs is None else 0
        self.material = mat
        self._mesh = mesh
        self._orientation: int | None = None

    @property
    def orientation(self) -> int:
        """+1 if the mesh is closed (watertight once coincident vertices are merged, consistently wound) with its
        faces wound counter-clockwise seen from outside, -1 if closed and wound the other way, 0 if open: only a
        closed mesh's back faces can never be seen from outside it. A mesh of several closed parts is judged part
        by part (the sign of each one's volume): parts wound different ways -- one of them inside out, or a shell
        around a cavity -- make it 0, as no one cull direction fits them all. Worked out on first use."""
        if self._orientation is None:
            self._orientation = _closed_orientation(
                trimesh.Trimesh(self._mesh.positions, self._mesh.indices, process=True))
        return self._orientation

    def vao_for(self, prog: moderngl.Program) -> moderngl.VertexArray:
        """A vertex array binding this mesh to `prog` (a VAO renders with the program it was made for)."""
        key = prog.glo
        if key not in self._vaos:
            attrs = [(buf, fmt, name) for buf, fmt, name in ((self.positions, "3f", "in_position"),
                                                            (self.normals, "3f", "in_normal"),
                                                            (self.uvs, "2f", "in_uv")) if name in prog]
            self._vaos[key] = self.ctx.vertex_array(prog, attrs, self.ibo)
        return self._vaos[key]


def _closed_orientation(tm: trimesh.Trimesh) -> int:
    """`_GpuMesh.orientation` of a merged trimesh: +1 / -1 if it is watertight and consistently wound and every
    connected part's signed volume has that sign, else 0."""
    if not (len(tm.faces) and tm.is_watertight and tm.is_winding_consistent):
        return 0
    parts = trimesh.graph.connected_component_labels(tm.face_adjacency, node_count=len(tm.faces))
    a, b, c = (tm.triangles[:, k] for k in range(3))
    volumes = np.bincount(parts, np.einsum("ij,ij->i", a, np.cross(b, c)))   # 6x each part's signed volume
    return 1 if (volumes > 0).all() else -1 if (volumes < 0).all() else 0


def _gl_rect(region: tuple[int, int, int, int], height: int) -> tuple[int, int, int, int]:
    """A (x, y, w, h) rect with y from the top row, in GL's bottom-left convention."""
    x, y, w, h = region
    return (int(x), int(height - y - h), int(w), int(h))


def _ndc_rect(ndc: np.ndarray, width: int, height: int, margin_px: int) -> tuple[int, int, int, int]:
    """The pixels (x, y, w, h, y from the top row) of a `width` x `height` image that hold normalised device
    coordinates `ndc` ((n, 2), y up), `margin_px` more on each side, within the image; (0, 0, 0, 0) when none."""
    if not len(ndc):
        return (0, 0, 0, 0)
    x0, x1 = (ndc[:, 0].min() + 1) / 2 * width - margin_px, (ndc[:, 0].max() + 1) / 2 * width + margin_px
    y0, y1 = (1 - ndc[:, 1].max()) / 2 * height - margin_px, (1 - ndc[:, 1].min()) / 2 * height + margin_px
    x0, y0 = max(0, int(np.floor(x0))), max(0, int(np.floor(y0)))
    x1, y1 = min(width, int(np.ceil(x1))), min(height, int(np.ceil(y1)))
    return (x0, y0, x1 - x0, y1 - y0) if x1 > x0 and y1 > y0 else (0, 0, 0, 0)


def _clip_to_near(clip: np.ndarray, near: float) -> np.ndarray:
    """The clip-space points ((n, 4), w the view depth) of a convex volume's part in front of the near plane
    (w >= `near`), as points whose hull it is: the points in front and, on the plane, where each segment from one
    in front to one behind crosses it (among them the clipped hull's every corner, and all within it)."""
    w = clip[:, 3]
    front, behind = clip[w >= near], clip[w < near]
    if not len(behind) or not len(front):
        return front
    a, b = front[:, None, :], behind[None, :, :]
    s = (a[..., 3] - near) / (a[..., 3] - b[..., 3])             # in [0, 1): w falls from >= near to < near
    return np.concatenate([front, (a + s[..., None] * (b - a)).reshape(-1, 4)])


def _has_area(rect: tuple[int, int, int, int] | None) -> bool:
    """Whether `rect` (x, y, w, h) is given and covers at least one pixel."""
    return rect is not None and rect[2] > 0 and rect[3] > 0


@dataclass
class _Placement:
    """Where a renderer's objects are at time `t` (DeferredRenderer._objects_at)."""

    t: float
    models: list[np.ndarray]          # model matrices, one per object
    model_bytes: list[bytes]          # the same as uploaded (gl_matrix)
    boxes: np.ndarray                 # (n, 8, 4) world-space bounding-box corners
    mirrored: list[bool]              # whether a model matrix turns the winding over (negative determinant)


class DeferredRenderer:
    """Renders a `Scene` from any `Camera` at any time; G-buffers are allocated per image size and reused."""

    def __init__(self, scene: Scene, ctx: moderngl.Context | None = None, shadow_size: int = 2048,
                 static_shadow_cache: bool = True):
        self.scene = scene
        self.ctx = ctx or gl_context()
        ctx = self.ctx
        self.geometry_prog = MaterialProgram(ctx, HERE / "gbuffer.vert.glsl", HERE / "gbuffer.frag.glsl")
        self.shadow_prog = program(ctx, HERE / "shadow.vert.glsl", HERE / "shadow.frag.glsl")
        # the lighting pass shades the pixels with geometry and the sky pass the others, picked by depth; a culled
        # G-buffer's empty pixels are told by position instead, with the sky's colour in the lighting shader
        self.lighting_prog = program(ctx, HERE / "fullscreen.vert.glsl", HERE / "lighting.frag.glsl")
        self.lighting_sky_prog = program(ctx, HERE / "fullscreen.vert.glsl", HERE / "lighting.frag.glsl",
                                         SKY_BRANCH=1)
        self.sky_prog = program(ctx, HERE / "fullscreen.vert.glsl", HERE / "sky.frag.glsl")
        self._fullscreen = {prog: ctx.vertex_array(prog, [])
                            for prog in (self.lighting_prog, self.lighting_sky_prog, self.sky_prog)}
        self.white = ctx.texture((1, 1), 4, bytes([255, 255, 255, 255]))
        self.meshes = [_GpuMesh(ctx, o.mesh, self.shadow_prog, self.white)
                       for o in scene.objects]
        self.shadow_size = shadow_size
        self.cull_lights = True      # leave out point lights that cannot reach the view (lighting_pass)
        self.shadow_map = ctx.depth_texture((shadow_size, shadow_size))
        self.shadow_map.compare_func = "<="
        self.shadow_map.filter = (moderngl.LINEAR, moderngl.LINEAR)
        self.shadow_map.repeat_x = self.shadow_map.repeat_y = False
        self.shadow_fbo = ctx.framebuffer(depth_attachment=self.shadow_map)
        self._shadow_time: float | None = None
        self._animated_casters = any(o.cast_shadow and o.animation is not None for o in scene.objects)
        # Where some casters move, the others' depth is drawn once (for the sun as it is) and copied into the shadow
        # map before the moving ones are drawn: the same map (the depth test keeps the nearest caster in any order)
        # for a copy instead of a clear and every static caster drawn again (the courtyard: 3.8 ms against 22.8).
        self._static_shadow = None
        if static_shadow_cache and self._animated_casters and can_copy_textures():
            self._static_shadow = ctx.depth_texture((shadow_size, shadow_size))
            self._static_shadow_fbo = ctx.framebuffer(depth_attachment=self._static_shadow)
        self._static_shadow_key = None   # the sun's projection the static casters' depth was drawn with
        self._moved_rect: tuple[int, int, int, int] | None = None   # the shadow-map texels moving casters last wrote
        self._placement: _Placement | None = None       # the objects' matrices and boxes at one time
        self._light_vp: tuple | None = None             # (the sun's parameters, its shadow-map projection)
        self._floor: float | None = None                # the scene's lowest point (moving_region's shadows)
        self._animated_objects = [i for i, o in enumerate(scene.objects) if o.animation is not None]
        self._gbuffers: dict[tuple[int, int], GBuffer] = {}
        self._coarse: dict[float, list[_GpuMesh]] = {}   # coarse_meshes, per detail
        self._object_ids = [struct.pack("i", o.object_id) for o in scene.objects]   # as the geometry pass writes them

    # ----------------------------------------------------------------------------------------- passes
    def light_view_projection(self) -> np.ndarray:
        """The sun's shadow-map projection (kept while the sun stays as it is)."""
        sun = self.scene.sun
        key = (*np.asarray(sun.direction, np.float64), float(sun.shadow_extent),
               *np.asarray(sun.shadow_center, np.float64))
        if self._light_vp is None or self._light_vp[0] != key:
            matrix = self._light_view_projection(sun)
            matrix.flags.writeable = False
            self._light_vp = (key, matrix)
        return self._light_vp[1]

    @staticmethod
    def _light_view_projection(sun) -> np.ndarray:
        d = np.asarray(sun.direction, np.float64) / np.linalg.norm(sun.direction)
        e = sun.shadow_extent
        from quadcast.render.camera import Pose
        eye = np.asarray(sun.shadow_center, np.float64) - d * 2 * e
        up = (0.0, 1.0, 0.0) if abs(d[1]) < 0.99 else (1.0, 0.0, 0.0)
        view = Pose.look_at(eye, sun.shadow_center, up).view_matrix()
        near, far = 0.0, 4 * e
        ortho = np.array([[1 / e, 0, 0, 0], [0, 1 / e, 0, 0],
                          [0, 0, -2 / (far - near), -(far + near) / (far - near)], [0, 0, 0, 1]])
        return ortho @ view

    def forget_shadow_map(self) -> None:
        """Where shadow casters move, make the next pass draw the shadow map again, as a renderer that has not
        drawn this frame yet would (the benchmarks' full render of a frame the server has just rendered for the
        same time). A static scene's shadow map is drawn once and kept."""
        if self._animated_casters:
            self._shadow_time = None

    def render_shadows(self, t: float) -> None:
        """The sun's shadow map at time t (skipped when it is already current)."""
        # The shadow map depends on t only through animated shadow casters: a static scene renders it once.
        if self._shadow_time == t or (self._shadow_time is not None and not self._animated_casters):
            return
        light_vp = self.light_view_projection()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.disable(moderngl.CULL_FACE)
        self.ctx.depth_func = "<"
        placed = self._objects_at(t)
        casters = [(obj, gm, model) for obj, gm, model in zip(self.scene.objects, self.meshes, placed.models)
                   if obj.cast_shadow]
        if self._static_shadow is not None:
            if self._static_shadow_key is not light_vp:
                self._draw_casters(self._static_shadow_fbo, light_vp, [c for c in casters if c[0].animation is None])
                self._static_shadow_key = light_vp
                self._moved_rect = None
            # Only the texels the moving casters wrote last time differ from the static casters' depth: those are
            # copied back (the whole map when unknown), then the moving casters are drawn where they are now.
            copy_texture(self.ctx, self._static_shadow, self.shadow_map, rect=self._moved_rect)
            self._draw_casters(self.shadow_fbo, light_vp, [c for c in casters if c[0].animation is not None],
                               clear=False)
            self._moved_rect = self._shadow_rect(light_vp, [box for obj, box in zip(self.scene.objects, placed.boxes)
                                                            if obj.cast_shadow and obj.animation is not None])
        else:
            self._draw_casters(self.shadow_fbo, light_vp, casters)
        self._shadow_time = t

    def _shadow_rect(self, light_vp: np.ndarray, boxes: list[np.ndarray]) -> tuple[int, int, int, int]:
        """The shadow-map texels (x, y, w, h, GL's bottom-left origin) that casters within `boxes` ((8, 4) world
        corners each) can write: the texels around their corners' projection, a texel more on each side."""
        ndc = (np.concatenate(boxes) @ light_vp.T)[:, :2] if boxes else np.zeros((0, 2))   # orthographic: w = 1
        return _gl_rect(_ndc_rect(ndc, self.shadow_size, self.shadow_size, 1), self.shadow_size)

    def _draw_casters(self, fbo: moderngl.Framebuffer, light_vp: np.ndarray, casters: list,
                      clear: bool = True) -> None:
        """Draw (object, mesh, model matrix) casters' depth into a shadow-map framebuffer (depth test on)."""
        fbo.use()
        if clear:
            fbo.clear(depth=1.0)
        for _, gm, model in casters:
            self.shadow_prog["u_light_mvp"].write(gl_matrix(light_vp @ model))
            gm.shadow_vao.render(moderngl.TRIANGLES)

    def moving_region(self, camera: Camera, times, margin_px: int = 6) -> tuple[int, int, int, int]:
        """The image rectangle (x, y, w, h, from the top-left corner) outside which the scene looks the same from
        `camera` at every time in `times`: the bounding boxes of the animated objects at those times and their
        sun shadows (each box swept along the sunlight down to the lowest point of the scene, which contains every
        surface its shadow can fall on). (0, 0, 0, 0) when nothing animated shows. A box or shadow reaching behind
        the camera counts with its part in front of the near plane (`_clip_to_near`), what GL draws of it."""
        scene, w, h = self.scene, camera.width, camera.height
        sun = np.asarray(scene.sun.direction, np.float64)
        sun = sun / np.linalg.norm(sun)
        if self._floor is None:
            self._floor = float(scene.bounds()[0][1])
        floor = self._floor
        view_projection = camera.view_projection().T
        visible = []      # clip-space points in front of the near plane whose hull holds what moved there
        for obj, gm in zip(scene.objects, self.meshes):
            if obj.animation is None:
                continue
            for t in times:
                world = (np.c_[gm.box_corners, np.ones(8)] @ obj.model_matrix(t).T)[:, :3]
                if sun[1] < -1e-6 and obj.cast_shadow:   # the box swept down to the floor: one convex volume
                    world = np.concatenate([world, world + ((floor - world[:, 1]) / sun[1])[:, None] * sun])
                visible.append(_clip_to_near(np.c_[world, np.ones(len(world))] @ view_projection,
                                             camera.frustum.near))
        clip = np.concatenate(visible) if visible else np.zeros((0, 4))
        return _ndc_rect(clip[:, :2] / clip[:, 3:4], w, h, margin_px)

    def gbuffer_for(self, width: int, height: int) -> GBuffer:
        key = (int(width), int(height))
        if key not in self._gbuffers:
            self._gbuffers[key] = GBuffer(self.ctx, *key)
        return self._gbuffers[key]

    def _objects_at(self, t: float) -> "_Placement":
        """Every object's model matrix (and its uploaded bytes) and world-space box at time t: a static object's
        worked out once, an animated one's again for each new t (all passes of a frame share them)."""
        placed = self._placement
        if placed is None:
            n = len(self.scene.objects)
            placed = self._placement = _Placement(t, [None] * n, [b""] * n, np.empty((n, 8, 4)), [False] * n)
            objects = range(n)
        elif self._animated_objects and placed.t != t:
            objects = self._animated_objects
        else:
            return placed
        for i in objects:
            m = placed.models[i] = self.scene.objects[i].model_matrix(t)
            placed.model_bytes[i] = gl_matrix(m)
            placed.boxes[i] = np.c_[self.meshes[i].box_corners, np.ones(8)] @ m.T
            placed.mirrored[i] = bool(np.linalg.det(m[:3, :3]) < 0)
        placed.t = t
        return placed

    def coarse_meshes(self, detail: float) -> list["_GpuMesh"]:
        """Every object's mesh with about `detail` (0, 1] of its triangles (`Mesh.simplified`; at least
        `COARSE_MIN_TRIANGLES`, a smaller mesh whole), for views too small to show them all; made on first use.
        Each object's box grows to hold both meshes, so culling by box stays exact for either."""
        if not 0 < detail <= 1:
            raise ValueError(f"mesh detail must be in (0, 1], got {detail}")
        if detail == 1:
            return self.meshes
        if detail not in self._coarse:
            coarse = []
            for o, gm in zip(self.scene.objects, self.meshes):
                count = len(o.mesh.indices)
                target = max(int(round(detail * count)), COARSE_MIN_TRIANGLES)
                if target >= count:
                    coarse.append(gm)
                    continue
                cm = _GpuMesh(self.ctx, o.mesh.simplified(target), self.shadow_prog, self.white, gm.texture)
                corners = np.concatenate([gm.box_corners, cm.box_corners])
                gm.box_corners = cm.box_corners = _box_corners(corners.min(axis=0), corners.max(axis=0))
                coarse.append(cm)
            self._coarse[detail] = coarse
            self._placement = None      # the boxes may have grown
        return self._coarse[detail]

    def _box_clip(self, camera: Camera, t: float) -> np.ndarray:
        """(n_objects, 8, 4): each object's bounding-box corners at time t in `camera`'s clip space."""
        return self._objects_at(t).boxes @ camera.view_projection().T

    def visible_objects(self, camera: Camera, t: float) -> np.ndarray:
        """(n_objects,) bools: the objects whose bounding box is not wholly outside one plane of the camera's
        frustum at time t. The others cannot draw a fragment: skipping them leaves the image as it is."""
        x, y, z, w = np.moveaxis(self._box_clip(camera, t), -1, 0)
        outside = ((x < -w).all(1) | (x > w).all(1) | (y < -w).all(1) | (y > w).all(1)
                   | (z < -w).all(1) | (z > w).all(1))
        return ~outside

    def objects_within(self, camera: Camera, t: float, rect: tuple[int, int, int, int]) -> np.ndarray:
        """(n_objects,) bools: the objects whose bounding box lies wholly in front of the eye and projects inside
        `rect` (x, y, w, h, pixels from the top-left corner of `camera`'s image) at time t, so that every fragment
        they draw is in `rect`."""
        x, y, _, w = np.moveaxis(self._box_clip(camera, t), -1, 0)
        front = (w > 0).all(1)
        w = np.where(w > 0, w, 1.0)
        px, py = (x / w * 0.5 + 0.5) * camera.width, (0.5 - y / w * 0.5) * camera.height
        rx, ry, rw, rh = rect
        return front & (px.min(1) >= rx) & (px.max(1) <= rx + rw) & (py.min(1) >= ry) & (py.max(1) <= ry + rh)

    def draw_geometry(self, camera: Camera, t: float, prog: MaterialProgram | None = None,
                      closed_back_faces: bool = True, exclude: tuple[int, int, int, int] | None = None,
                      detail: float = 1.0) -> None:
        """Draw every object with `prog` (the G-buffer program unless given; each object with the variant for its
        albedo source) into the bound framebuffer; objects wholly outside the camera's frustum are skipped
        (`visible_objects`), and with `exclude` (a rect, see `geometry_pass`) those wholly inside it
        (`objects_within`). `closed_back_faces=False` leaves out the back faces of closed meshes
        (`_GpuMesh.orientation`), which no eye outside them can see. `detail` < 1 draws the coarse meshes
        (`coarse_meshes`)."""
        meshes = self.coarse_meshes(detail)
        prog = prog or self.geometry_prog
        set_uniforms(prog, u_view=gl_matrix(camera.view_matrix()), u_proj=gl_matrix(camera.projection_matrix()))
        visible = self.visible_objects(camera, t)
        if _has_area(exclude):
            visible &= ~self.objects_within(camera, t, exclude)
        placed = self._objects_at(t)
        for object_id, gm, shown, model, mirrored in zip(self._object_ids, meshes, visible, placed.model_bytes,
                                                         placed.mirrored):
            if not shown:
                continue
            if not closed_back_faces:
                sign = -gm.orientation if mirrored else gm.orientation
                if sign:
                    self.ctx.enable(moderngl.CULL_FACE)
                    self.ctx.cull_face = "back" if sign > 0 else "front"
                else:
                    self.ctx.disable(moderngl.CULL_FACE)
            gm.texture.use(0)
            variant = prog.variant(gm.albedo_source)
            write_changed_uniforms(variant, gm.material_uniforms)
            write_changed_uniforms(variant, (("u_model", model), ("u_object_id", object_id)))
            gm.vao_for(variant).render(moderngl.TRIANGLES)
        if not closed_back_faces:
            self.ctx.disable(moderngl.CULL_FACE)
            self.ctx.cull_face = "back"

    def geometry_pass(self, camera: Camera, t: float, target: GBuffer | None = None,
                      prog: MaterialProgram | None = None, cull: CullFn | None = None,
                      region: tuple[int, int, int, int] | None = None,
                      closed_back_faces: bool = True,
                      exclude: tuple[int, int, int, int] | None = None, detail: float = 1.0) -> GBuffer:
        """Fill a G-buffer (the renderer's own for this size unless `target` is given). `prog` may replace the
        G-buffer program with a `MaterialProgram` of its own (e.g. the server's depth peeling); bind its
        extra textures to units >= 4 before calling. `cull` (see `CullFn`) restricts the pass to the pixels it
        leaves at depth 1; culled pixels stay cleared, which the lighting pass shades as (cheap) sky. `region`
        (x, y, w, h, pixels from the top-left corner) renders only there: the rest of the G-buffer keeps what it
        held. `exclude` (x, y, w, h, from the top-left; with `region` None) leaves that rectangle cleared, with
        nothing hit and depth 1, so a `geometry_only` lighting pass skips it too; objects wholly inside it are not
        drawn. `closed_back_faces=False` and `detail`: see `draw_geometry`."""
        gb = target or self.gbuffer_for(camera.width, camera.height)
        gb.geometry_fbo.use()
        if region is None:
            gb.clear()
        else:
            gb.geometry_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0, viewport=_gl_rect(region, gb.height))
            gb.geometry_fbo.scissor = _gl_rect(region, gb.height)
        excluded = _has_area(exclude)
        if excluded:
            if region is not None:
                raise ValueError("geometry_pass: give `region` or `exclude`, not both")
            # depth 0 there: the depth test drops those fragments before they are shaded
            gb.geometry_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=0.0, viewport=_gl_rect(exclude, gb.height))
        if cull is not None:
            cull(gb.depth)
            gb.geometry_fbo.use()
        self.ctx.enable(moderngl.DEPTH_TEST)
        self.ctx.depth_func = "<"
        self.ctx.disable(moderngl.CULL_FACE | moderngl.BLEND)
        self.draw_geometry(camera, t, prog, closed_back_faces, exclude=exclude if excluded else None, detail=detail)
        gb.geometry_fbo.scissor = None
        if excluded:
            gb.geometry_fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0, viewport=_gl_rect(exclude, gb.height))
        gb.camera = camera
        gb.culled = cull is not None
        return gb

    def lighting_pass(self, gb: GBuffer, t: float, region: tuple[int, int, int, int] | None = None,
                      geometry_only: bool = False) -> None:
        """Shade the G-buffer into its colour (only within `region`, as in `geometry_pass`, when given): the pixels
        with geometry, which the depth test against the G-buffer's depth picks (a branch in the shader would not save
        their cost on llvmpipe), then the sky on the others (render/sky.frag.glsl). With `geometry_only` the rest is
        black instead. In a culled G-buffer (`geometry_pass(cull=...)`, depth 0 where culled) the shader tells sky by
        position, and without `geometry_only` shades every pixel."""
        camera = gb.camera
        self.render_shadows(t)
        scene, view = self.scene, camera.view_matrix()
        prog = self.lighting_sky_prog if gb.culled else self.lighting_prog
        by_depth = geometry_only or not gb.culled
        fbo = gb.color_depth_fbo if by_depth else gb.color_fbo
        if geometry_only:      # the colour only: the depth is the test's
            gb.color_fbo.clear(0.0, 0.0, 0.0, 1.0, viewport=None if region is None else _gl_rect(region, gb.height))
        fbo.use()
        fbo.scissor = None if region is None else _gl_rect(region, gb.height)
        if by_depth:
            self.ctx.enable(moderngl.DEPTH_TEST)
            self.ctx.depth_func = ">"            # the far plane (u_z = 1) lies behind every pixel with geometry
            fbo.depth_mask = False
        else:
            self.ctx.disable(moderngl.DEPTH_TEST)
        gb.albedo.use(0)
        gb.normal.use(1)
        gb.position.use(2)
        self.shadow_map.use(3)
        sun_dir = view[:3, :3] @ (np.asarray(scene.sun.direction) / np.linalg.norm(scene.sun.direction))
        # A point light lights nothing beyond its radius (lighting.frag.glsl's window is 0 there, and so is what it
        # adds): one whose sphere lies outside the view's frustum is left out, the same image for less work.
        lights = [(light, (view @ np.r_[light.position, 1.0])[:3]) for light in scene.point_lights]
        lights = [(light, at) for light, at in lights
                  if not (self.cull_lights and camera.frustum.sphere_outside(at, 1.01 * light.radius + 0.01))]
        n = len(lights)
        pad = scene.MAX_POINT_LIGHTS - n
        light_pos = np.array([at for _, at in lights] + [[0, 0, 0]] * pad, "f4")
        light_col = np.array([np.asarray(l.color) * l.intensity for l, _ in lights] + [[0, 0, 0]] * pad, "f4")
        light_rad = np.array([l.radius for l, _ in lights] + [1.0] * pad, "f4")
        inv_view, sky = gl_matrix(np.linalg.inv(view)), tuple(float(c) for c in scene.sky)
        set_uniforms(prog, u_albedo=0, u_normal=1, u_position=2, u_shadow_map=3, u_inv_view=inv_view,
                     u_extents=camera.frustum.unit_extents,
                     u_light_vp=gl_matrix(self.light_view_projection()),
                     u_sun_dir_view=tuple(float(c) for c in sun_dir),
                     u_sun_color=tuple(float(c) for c in np.asarray(scene.sun.color) * scene.sun.intensity),
                     u_ambient=tuple(float(c) for c in scene.ambient), u_sky=sky,
                     u_shadow_texel=1.0 / self.shadow_size, u_num_lights=n,
                     u_light_pos=light_pos.tobytes(), u_light_color=light_col.tobytes(),
                     u_light_radius=light_rad.tobytes(), u_z=1.0 if by_depth else 0.0)
        self._fullscreen[prog].render(moderngl.TRIANGLES, vertices=3)
        if not (geometry_only or gb.culled):
            self.ctx.depth_func = "<="           # ... and the pixels left at the far plane, where nothing was drawn
            set_uniforms(self.sky_prog, u_inv_view=inv_view, u_extents=camera.frustum.unit_extents, u_sky=sky, u_z=1.0)
            self._fullscreen[self.sky_prog].render(moderngl.TRIANGLES, vertices=3)
        fbo.scissor = None
        if by_depth:
            fbo.depth_mask = True
            self.ctx.depth_func = "<"
            self.ctx.disable(moderngl.DEPTH_TEST)

    def gbuffer(self, camera: Camera, t: float = 0.0, target: GBuffer | None = None,
                region: tuple[int, int, int, int] | None = None, geometry_only: bool = False,
                exclude: tuple[int, int, int, int] | None = None) -> GBuffer:
        """Geometry and lighting passes (only within `region`, or not in `exclude`, see `geometry_pass`;
        `geometry_only`, see `lighting_pass`); the results stay on the GPU."""
        gb = self.geometry_pass(camera, t, target, region=region, exclude=exclude)
        self.lighting_pass(gb, t, region, geometry_only)
        return gb

    def render(self, camera: Camera, t: float = 0.0) -> RenderedFrame:
        """Render one view and read it back."""
        return self.gbuffer(camera, t).read()

    def render_color(self, camera: Camera, t: float = 0.0) -> np.ndarray:
        gb = self.gbuffer(camera, t)
        return gb.read_color()

    def finish(self) -> None:
        self.ctx.finish()
