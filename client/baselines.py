"""Client halves of the ATW and MeshWarp baselines (QUASAR §4.1.1-4.1.2): decode, then re-project on the GPU.

`ATWClient` shows the last decoded frame re-oriented to the current head rotation (a homography in
`atw.frag.glsl`; translation is ignored, so near objects swim). Outside the frame it repeats the closest edge pixel.

`MeshWarpClient` also decodes the frame's depth (`quadcast.protocol.depth`) and draws it as a grid mesh with **one vertex per
depth pixel** (`meshwarp.vert.glsl` builds the vertices from the depth texture and `gl_VertexID`, so nothing but a
static index buffer lives in a vertex buffer). Like QUASAR's MeshWarp, the mesh stays **connected**: triangles across
depth discontinuities are stretched, not dropped, so disocclusions show smeared colour rather than holes; sky pixels
are vertices at infinity. Whatever the mesh does not cover (outside the server's frustum) is filled with the ATW
re-orientation of the frame first.

Coverage (`MethodClient.coverage`): the passes write alpha -- 1 where they show the frame's content, 0.5 where
ATW repeats edge pixels outside the frame -- and `render` reads it back with the colour.

Both render at the display's own size and field of view. `receive` validates everything before it changes the
displayed state: a payload of the wrong method or with a bad pose or depth blob raises ProtocolError, undecodable
video raises VideoError, and the last good frame keeps being shown. A non-IDR access unit while the video decoder
waits for a keyframe changes nothing (see `needs_reference`). Before any frame `render` returns black.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from quadcast.client.method import Coverage, MethodClient, PixelCoverage
from quadcast.codec.decoder import AtlasDecoder
from quadcast.codec.encoder import AtlasEncoder
from quadcast.codec.picture import YuvPicture
from quadcast.protocol.depth import DEFAULT_MAX_DEPTH_PIXELS, decode_depth, encode_depth
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import FrameType, FramePayload, Method
from quadcast.protocol.methods import MAX_ATLAS_VIEWS, meshwarp_render_size
from quadcast.render.atlas_texture import AtlasTexture
from quadcast.render.camera import Camera, Frustum, Pose, gl_matrix
from quadcast.render.gl import RENDER_DIR, WARM_UP_SIZE, gl_context, program, set_uniforms
from quadcast.render.renderer import read_texture

__all__ = ["ATWClient", "MeshWarpClient", "rotation_homography"]

HERE = Path(__file__).resolve().parent
DISPLAY_NEAR, DISPLAY_FAR = 0.05, 1000.0  # display camera for the mesh pass (beyond the server's 100 m far plane)


def _k(frustum: Frustum) -> np.ndarray:
    """3x3 intrinsics: view-space direction d -> (ndc_x * w, ndc_y * w, w) with w = -d_z."""
    p = frustum.projection_matrix()
    return np.array([[p[0, 0], 0.0, p[0, 2]], [0.0, p[1, 1], p[1, 2]], [0.0, 0.0, -1.0]])


def rotation_homography(frame_pose: Pose, frame_frustum: Frustum, pose: Pose, frustum: Frustum) -> np.ndarray:
    """3x3 map from display NDC (x, y, 1) to the frame's homogeneous NDC for a rotation-only re-projection."""
    rel = frame_pose.rotation.as_matrix().T @ pose.rotation.as_matrix()
    return _k(frame_frustum) @ rel @ np.linalg.inv(_k(frustum))


def _mat3(m: np.ndarray) -> bytes:
    return np.ascontiguousarray(np.asarray(m, np.float32).T).tobytes()


def _payload_pose(payload: FramePayload, method: Method) -> Pose:
    if not isinstance(payload, FramePayload):
        raise ProtocolError(f"payload: expected a FramePayload, got {type(payload).__name__}")
    if payload.method != method:
        raise ProtocolError(f"payload.method: expected {method.name}, got {Method(payload.method).name}")
    try:
        return Pose(payload.position, payload.quat)
    except (ValueError, TypeError) as exc:
        raise ProtocolError(f"payload pose: {exc}") from None


@dataclass
class _Frame:
    """The displayed state: the last good frame's pose and its GPU textures."""

    pose: Pose
    width: int
    height: int
    frame_id: int


class _BaselineClient(MethodClient):
    """Shared part: video decoder, decoded-frame texture, the display framebuffer and the ATW warp pass."""

    method: Method

    def __init__(self, width: int, height: int, fovy: float, server_fovy: float | None,
                 ctx: moderngl.Context | None):
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"{type(self).__name__}: display size must be positive, got {width}x{height}")
        self.width, self.height = int(width), int(height)
        self.fovy = float(fovy)
        self.server_fovy = float(fovy if server_fovy is None else server_fovy)
        Frustum.symmetric(self.fovy, 1.0)
        Frustum.symmetric(self.server_fovy, 1.0)  # both raise ValueError for a bad field of view
        self.ctx = ctx or gl_context()
        # planes, sampled by the shaders (render/atlas_texture.py)
        self.decoder = AtlasDecoder(max_pixels=MAX_ATLAS_VIEWS * self.width * self.height, output="yuv420")
        self.frame: _Frame | None = None
        self._frame_tex = AtlasTexture(self.ctx)
        self._out = self.ctx.texture((self.width, self.height), 4, dtype="f1")
        self._out_depth = self.ctx.depth_renderbuffer((self.width, self.height))
        self._fbo = self.ctx.framebuffer([self._out], self._out_depth)
        self._atw = program(self.ctx, RENDER_DIR / "fullscreen.vert.glsl", HERE / "atw.frag.glsl")
        self._fullscreen = self.ctx.vertex_array(self._atw, [])
        self._coverage = Coverage.empty(self.width, self.height)

    @property
    def needs_reference(self) -> bool:
        """True while the video decoder waits for an IDR (before the first one and after an error)."""
        return self.decoder.needs_keyframe

    def camera(self, pose: Pose, near: float = 0.1, far: float = 100.0) -> Camera:
        """The display camera at `pose`."""
        return Camera.perspective(pose, self.width, self.height, self.fovy, near, far)

    def frame_frustum(self) -> Frustum:
        """The frustum the current frame was rendered with (server fovy, the decoded image's aspect)."""
        return Frustum.symmetric(self.server_fovy, self.frame.width / self.frame.height)

    def _upload_texture(self, tex: moderngl.Texture | None, img: np.ndarray, components: int, dtype: str,
                        flt: int) -> moderngl.Texture:
        h, w = img.shape[:2]
        if tex is None or tex.size != (w, h):
            if tex is not None:
                tex.release()
            tex = self.ctx.texture((w, h), components, dtype=dtype, alignment=1)
            tex.filter = (flt, flt)
            tex.repeat_x = tex.repeat_y = False
        tex.write(np.ascontiguousarray(img[::-1]).tobytes())  # GL's first row is the bottom one
        return tex

    def _commit_color(self, payload: FramePayload, pose: Pose, picture: YuvPicture) -> None:
        self._frame_tex.write(picture)
        self.frame = _Frame(pose, picture.width, picture.height, int(payload.frame_id))

    def _draw_atw(self, pose: Pose) -> None:
        h = rotation_homography(self.frame.pose, self.frame_frustum(), pose, self.camera(pose).frustum)
        set_uniforms(self._atw, u_h=_mat3(h), **self._frame_tex.use(0))
        self._fullscreen.render(moderngl.TRIANGLES, vertices=3)

    def _draw(self, pose: Pose) -> None:
        raise NotImplementedError

    def _frame_size(self) -> tuple[int, int]:
        """The size of the frames this client's server sends."""
        return self.width, self.height

    def _geometry(self, width: int, height: int) -> bytes:
        """The geometry blob of a made-up frame (`warm_up`): none."""
        return b""

    def warm_up(self, stereo: bool = False) -> None:
        """Receive and draw one made-up frame (x264-coded grey, and MeshWarp's depth: a slanted wall with sky above
        it) on a throwaway client of this kind at :data:`WARM_UP_SIZE` on this client's context, then drop it, so
        that llvmpipe has compiled the shaders before the first real frame (docs/speed.md, stop 54). This client
        is untouched; it has no stereo of its own."""
        probe = type(self)(*WARM_UP_SIZE, self.fovy, self.server_fovy, ctx=self.ctx)
        try:
            w, h = probe._frame_size()
            with AtlasEncoder(w, h) as encoder:
                video = encoder.encode(YuvPicture.grey(w, h), keyframe=True).data
            pose = Pose(np.zeros(3))
            probe.receive(FramePayload(self.method, 0, FrameType.REFERENCE, 0, 0.0, pose.position, pose.quat, video,
                                       probe._geometry(w, h), self_contained=True))
            probe.render(pose.offset_local([0.05, 0.0, 0.0]))
        finally:
            probe.close()

    def render(self, pose: Pose) -> np.ndarray:
        """The displayed image (height, width, 3) uint8, top row first, for the current `pose`."""
        if self.frame is None:
            self._coverage = Coverage.empty(self.width, self.height)
            return np.zeros((self.height, self.width, 3), np.uint8)
        self._fbo.use()
        self._fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        self._draw(pose)
        rgba = read_texture(self._out, 4, "u1")
        # The passes write what each pixel shows as alpha: 1 drawn, 0.5 smeared edge pixels, 0 (clear) nothing.
        alpha = rgba[..., 3]
        self._coverage = Coverage(np.where(alpha >= 192, PixelCoverage.DRAWN, np.where(
            alpha >= 64, PixelCoverage.SMEARED, PixelCoverage.EMPTY)).astype(np.uint8))
        return np.ascontiguousarray(rgba[..., :3])

    def coverage(self) -> Coverage:
        """From the last render's alpha: the frame's content where the warp (and MeshWarp's mesh) lands inside the
        frame, smeared edge pixels where ATW samples outside it."""
        return self._coverage

    def close(self) -> None:
        self.decoder.close()
        for obj in (self._fbo, self._out, self._out_depth, self._frame_tex):
            if obj is not None:
                obj.release()
        self._frame_tex = None
        self.frame = None


class ATWClient(_BaselineClient):
    """Asynchronous time warp: the last frame, re-oriented (rotation only) to the current pose.

    `server_fovy` is the vertical field of view the server renders with (default: the display's `fovy`).
    """

    name = "atw"
    method = Method.ATW

    def __init__(self, width: int, height: int, fovy: float = 60.0, server_fovy: float | None = None,
                 ctx: moderngl.Context | None = None):
        super().__init__(width, height, fovy, server_fovy, ctx)

    def receive(self, payload: FramePayload) -> None:
        pose = _payload_pose(payload, self.method)
        picture = self.decoder.decode(payload.video, payload.frame_id)  # raises VideoError
        if picture is not None:
            self._commit_color(payload, pose, picture)

    def _draw(self, pose: Pose) -> None:
        self.ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        self._draw_atw(pose)


class MeshWarpClient(_BaselineClient):
    """MeshWarp: the last frame's depth as a connected grid mesh (one vertex per pixel), textured with its colour.

    `server_fovy` is the vertical field of view the server renders with (60, or 120 for QUASAR's wide variant).
    """

    name = "meshwarp"
    method = Method.MESHWARP

    def __init__(self, width: int, height: int, fovy: float = 60.0, server_fovy: float = 60.0,
                 ctx: moderngl.Context | None = None, max_depth_pixels: int = DEFAULT_MAX_DEPTH_PIXELS):
        super().__init__(width, height, fovy, server_fovy, ctx)
        self.max_depth_pixels = int(max_depth_pixels)
        self.depth_size = meshwarp_render_size(self.width, self.height, self.server_fovy)   # what the server sends
        self._mesh_prog = program(self.ctx, HERE / "meshwarp.vert.glsl", HERE / "meshwarp.frag.glsl")
        self._depth_tex: moderngl.Texture | None = None
        self._grid: tuple[tuple[int, int], moderngl.Buffer, moderngl.VertexArray] | None = None

    def receive(self, payload: FramePayload) -> None:
        pose = _payload_pose(payload, self.method)
        # Video first (raises VideoError): the decoder follows the stream even if the depth turns out bad.
        picture = self.decoder.decode(payload.video, payload.frame_id)
        depth = decode_depth(payload.geometry, max_pixels=self.max_depth_pixels, size=self.depth_size)
        if picture is None:
            return
        if depth.shape != (picture.height, picture.width):
            raise ProtocolError(f"payload.geometry: depth map is {depth.shape[1]}x{depth.shape[0]}, "
                                f"the video frame {picture.width}x{picture.height}")
        if min(depth.shape) < 2:
            raise ProtocolError(f"payload.geometry: depth map {depth.shape[1]}x{depth.shape[0]} is too small "
                                "for a mesh")
        self._commit_color(payload, pose, picture)
        self._depth_tex = self._upload_texture(self._depth_tex, np.where(np.isfinite(depth), depth, 0.0)
                                               .astype(np.float32), 1, "f4", moderngl.NEAREST)

    def _frame_size(self) -> tuple[int, int]:
        return self.depth_size

    def warm_up(self, stereo: bool = False) -> None:
        """The shared warm-up, then this client's grid mesh for the frames its server sends (a static index
        buffer, which the first frame would otherwise build)."""
        super().warm_up(stereo)
        self._grid_vao(*self.depth_size)

    def _geometry(self, width: int, height: int) -> bytes:
        depth = np.broadcast_to(np.linspace(3.0, 6.0, width, dtype=np.float32), (height, width)).copy()
        depth[: height // 4] = np.inf
        return encode_depth(depth)

    def _grid_vao(self, w: int, h: int) -> moderngl.VertexArray:
        """A static index buffer of (w-1)(h-1) quads, two triangles each, over vertex ids row * w + column."""
        if self._grid is None or self._grid[0] != (w, h):
            if self._grid is not None:
                self._grid[2].release()
                self._grid[1].release()
            v = (np.arange(h - 1)[:, None] * w + np.arange(w - 1)[None, :]).reshape(-1).astype(np.uint32)
            idx = np.stack([v, v + 1, v + w, v + 1, v + w + 1, v + w], axis=1)
            ibo = self.ctx.buffer(idx.tobytes())
            vao = self.ctx.vertex_array(self._mesh_prog, [], index_buffer=ibo, index_element_size=4)
            self._grid = ((w, h), ibo, vao)
        return self._grid[2]

    def _draw(self, pose: Pose) -> None:
        ctx = self.ctx
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        self._draw_atw(pose)  # in-fill for whatever the mesh leaves uncovered
        ctx.enable(moderngl.DEPTH_TEST)
        ctx.depth_func = "<"
        cam = self.camera(pose, DISPLAY_NEAR, DISPLAY_FAR)
        mvp = cam.projection_matrix() @ cam.view_matrix() @ self.frame.pose.camera_to_world()
        samplers = self._frame_tex.use(0)
        self._depth_tex.use(2)
        set_uniforms(self._mesh_prog, u_depth=2, **samplers, u_mvp=gl_matrix(mvp),
                     u_extents=self.frame_frustum().unit_extents)
        self._grid_vao(self.frame.width, self.frame.height).render(moderngl.TRIANGLES)
        ctx.disable(moderngl.DEPTH_TEST)

    def close(self) -> None:
        if self._grid is not None:
            self._grid[2].release()
            self._grid[1].release()
            self._grid = None
        if self._depth_tex is not None:
            self._depth_tex.release()
            self._depth_tex = None
        super().close()
