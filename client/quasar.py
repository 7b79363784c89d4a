"""QUASAR's client (§3.6): decode payloads, keep the cached reference frame, rebuild the layered mesh, render it
from the user's current pose."""
from __future__ import annotations

import concurrent.futures
import time

import moderngl
import numpy as np

from quadcast.client.method import Coverage, MethodClient
from quadcast.client.stereo import STEREO_MODES, MeshStereo, StereoFrame
from quadcast.codec.decoder import AtlasDecoder, VideoError
from quadcast.codec.encoder import AtlasEncoder
from quadcast.codec.picture import YuvPicture
from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import FramePayload, FrameType, Method
from quadcast.protocol.methods import MAX_ATLAS_VIEWS
from quadcast.protocol.quads import LayerKind, QuadFrame, QuadLayer, QuadSet, decode_quad_frame, encode_quad_frame
from quadcast.render.atlas_texture import AtlasTexture
from quadcast.render.camera import DEFAULT_IPD_M, Camera, Frustum, Pose
from quadcast.render.gl import WARM_UP_SIZE, gl_context
from quadcast.render.quadcache import QuadCache
from quadcast.render.quadmesh import MeshLayer, MeshView, QuadMesh


# Fill-in layers sit farther along the eye rays (hidden 0.3%; wide FOV 2%, its relaxed half-resolution planes are
# coarser), so where they overlap the main layer at about the same depth (the wide view overlaps the frame's
# border; relaxed hidden-layer planes graze visible surfaces) the main layer shows.
FILL_DEPTH_SCALE = {LayerKind.HIDDEN: 1.003, LayerKind.WIDE: 1.02, LayerKind.FAR: 2.0}
"""How far behind the main layer each fill-in layer is drawn (a factor on view depth along the eye ray): the
far field lies behind everything."""


def warm_up_frames(method: Method, width: int, height: int) -> list[tuple[FramePayload, Pose]]:
    """Two made-up frames of a `width` x `height` client, and the pose to draw each at: a reference frame (a grey
    wall 5 m in front of the camera as 2-pixel quads, every seventh with depth offsets) and a residual frame that
    updates the middle of the cached wall (freeing the quads it covers) and reveals a strip. Their atlas is coded
    by x264 like a server's."""
    camera = Camera.perspective(Pose(np.zeros(3)), width, height)

    def wall(x0, x1, y0, y1, size_log2=1, depth=5.0):
        s = 1 << size_log2
        xs, ys = np.meshgrid(np.arange(x0, x1, s), np.arange(y0, y1, s))
        n = xs.size
        flattened = np.arange(n) % 7 != 0
        return QuadSet(xs.ravel(), ys.ravel(), np.full(n, size_log2), flattened, np.zeros(n, bool),
                       np.tile([0.0, 0.0, 1.0], (n, 1)), np.full(n, depth), np.zeros((int((~flattened).sum()), 16)))

    def layer(kind, quads, rect):
        return QuadLayer(kind, width, height, camera.to_array(), rect, quads)

    reference, current = (0, 0, width, height), (width, 0, width, height)
    frames = [(FrameType.REFERENCE, [layer(LayerKind.VISIBLE, wall(0, width, 0, height), reference)]),
              (FrameType.RESIDUAL, [layer(LayerKind.UPDATED, wall(width // 4, width // 2, height // 4, height // 2),
                                          reference),
                                    layer(LayerKind.REVEALED, wall(0, width // 8, 0, height, depth=4.0), current)])]
    grey = YuvPicture.grey(2 * width, height)
    out = []
    with AtlasEncoder(2 * width, height) as encoder:
        for frame_id, (frame_type, layers) in enumerate(frames):
            video = encoder.encode(grey, keyframe=frame_type == FrameType.REFERENCE).data
            out.append((FramePayload(method, frame_id, frame_type, 0, 0.1 * frame_id, camera.pose.position,
                                     camera.pose.quat, video, encode_quad_frame(QuadFrame(layers)),
                                     self_contained=frame_type == FrameType.REFERENCE), camera.pose))
    return out


class QuasarClient(MethodClient):
    """Also the QuadStream baseline's client (`method=Method.QUADSTREAM`): its frames are all references."""

    name = "quasar"

    def __init__(self, width: int, height: int, fovy_deg: float = 60.0, ctx: moderngl.Context | None = None,
                 max_quads: int = 8 << 20, method: Method = Method.QUASAR, crack_fill: bool = True):
        """`crack_fill=False` shows the one-pixel cracks between the mesh's quads (see `MeshView`)."""
        self.method = Method(method)
        self.name = self.method.name.lower()
        self.ctx = ctx or gl_context()
        self.width, self.height = width, height
        self.frustum = Frustum.symmetric(fovy_deg, width / height)
        # budgets from the size this client asked for: quad layers of that size, an atlas of at most
        # MAX_ATLAS_VIEWS such pictures (anything declaring more is refused before it is decoded), decoded to
        # planes that the mesh's draws sample and convert (render/atlas_texture.py, render/atlas_colour.glsl)
        self.decoder = AtlasDecoder(max_pixels=MAX_ATLAS_VIEWS * width * height, output="yuv420")
        self.mesh = QuadMesh(self.ctx)
        self.crack_fill = bool(crack_fill)
        self.view = MeshView(self.ctx, width, height, crack_fill=self.crack_fill)
        self.max_quads = max_quads
        self.cache: QuadCache | None = None
        self.reference_id = -1
        self.reference_camera: Camera | None = None
        self.far_layers: list[MeshLayer] = []
        self.atlas_texture = AtlasTexture(self.ctx)
        self._video_thread = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix=f"{self.name}-video")
        self._needs_reference = True
        self.last_frame_id = -1
        self.stats: dict = {}
        self._stereo: MeshStereo | None = None  # made on the first stereo frame
        self._coverage = Coverage.empty(width, height)

    @property
    def atlas(self) -> AtlasTexture | None:
        """The decoded atlas's planes, once a frame arrived."""
        return self.atlas_texture if self.atlas_texture.size is not None else None

    @property
    def needs_reference(self) -> bool:
        return self._needs_reference

    def receive(self, payload: FramePayload) -> None:
        """Apply one payload. On any defect raise ProtocolError/VideoError and keep showing the last good state.

        The atlas decodes on a thread of its own (FFmpeg runs without the GIL) while this one parses the geometry
        and works out the cache's next state; nothing the display shows changes until both are done and valid.
        A frame whose geometry is refused after its video was decoded leaves the decoder past it, so the client
        then needs a reference frame, as after a refused video."""
        ms: dict[str, float] = {}
        if payload.method != self.method:
            raise ProtocolError(f"{self.name} client got a {payload.method.name} payload")
        is_reference = payload.frame_type == FrameType.REFERENCE
        if not is_reference and (payload.reference_id != self.reference_id or self.cache is None):
            self._needs_reference = True
            raise ProtocolError(f"residual frame {payload.frame_id} needs reference {payload.reference_id}, "
                                f"the client has {self.reference_id if self.reference_id >= 0 else 'none'}")
        decoding = self._video_thread.submit(self.decoder.decode, payload.video, payload.frame_id)
        try:
            t0 = time.perf_counter()
            frame = decode_quad_frame(payload.geometry, max_quads=self.max_quads, size=(self.width, self.height))
            ms["zstd"] = (time.perf_counter() - t0) * 1e3
            kinds = [l.kind for l in frame.layers]
            if is_reference and LayerKind.VISIBLE not in kinds:
                raise ProtocolError("reference frame has no visible layer")
            t0 = time.perf_counter()
            # the cache's next state, kept only if the whole frame is good
            if is_reference:
                visible = frame.layers[kinds.index(LayerKind.VISIBLE)]
                cache = QuadCache(visible.width, visible.height)
                cache.reset(visible.quads)
            elif LayerKind.UPDATED in kinds:
                update = self.cache.plan_update(frame.layers[kinds.index(LayerKind.UPDATED)].quads)
            quad_ms = (time.perf_counter() - t0) * 1e3
        except BaseException:
            concurrent.futures.wait([decoding])
            self._needs_reference = True
            raise
        try:
            t0 = time.perf_counter()
            image = decoding.result()
            ms["video"] = (time.perf_counter() - t0) * 1e3      # what the frame waited for it
            ms["video_decode"] = self.decoder.decode_ms           # its own time, mostly beside the work above
            if image is None:
                raise VideoError(f"frame {payload.frame_id}: the video decoder is waiting for a keyframe")
            cameras = self._layer_cameras(frame)
            self._check_rects(frame, image.width, image.height)
        except BaseException:
            self._needs_reference = True    # the decoder is past this frame, or waits for the next IDR
            raise
        layers = list(zip(frame.layers, cameras))

        t0 = time.perf_counter()
        if is_reference:
            self.cache = cache
            self.reference_camera = cameras[kinds.index(LayerKind.VISIBLE)]
            self.reference_rect = visible.atlas_rect
            # The far field comes with reference frames and stays until the next one (its colour is in every
            # frame's atlas); the same MeshLayer objects, so the mesh keeps its buffers.
            self.far_layers = [MeshLayer(l.quads, cam, l.atlas_rect, FILL_DEPTH_SCALE[LayerKind.FAR])
                               for l, cam in layers if l.kind == LayerKind.FAR]
            self.reference_id = payload.frame_id
        elif LayerKind.UPDATED in kinds:
            self.cache.apply(update)
        mesh_layers = [MeshLayer(self.cache.quads, self.reference_camera, self.reference_rect, edit=self.cache.edit,
                                 cached=True)]
        mesh_layers += [MeshLayer(l.quads, cam, l.atlas_rect, FILL_DEPTH_SCALE.get(l.kind, 1.0)) for l, cam in layers
                        if l.kind in (LayerKind.REVEALED, LayerKind.HIDDEN, LayerKind.WIDE)]
        mesh_layers += self.far_layers
        ms["quad_update"] = quad_ms + (time.perf_counter() - t0) * 1e3

        t0 = time.perf_counter()
        self.atlas_texture.write(image)
        self.mesh.build(mesh_layers, (image.width, image.height))
        # a residual frame's revealed layer is cut from its own view of the scene, whose colour the atlas holds:
        # the cached surfaces that view saw are drawn with it too (QuadMesh.set_current_view)
        revealed = [(l, cam) for l, cam in layers if l.kind == LayerKind.REVEALED]
        if revealed:
            self.mesh.set_current_view(revealed[0][1], revealed[0][0].atlas_rect)
        else:
            self.mesh.set_current_view(None)
        self.ctx.finish()
        ms["mesh"] = (time.perf_counter() - t0) * 1e3
        self._needs_reference = False
        self.last_frame_id = payload.frame_id
        self.stats = {"ms": ms, "cache_quads": len(self.cache), "cache_bytes": self.cache.nbytes,
                      "mesh_quads": self.mesh.quad_count}

    @staticmethod
    def _layer_cameras(frame: QuadFrame) -> list[Camera]:
        """Each layer's camera; ProtocolError naming the layer if one is not a camera."""
        out = []
        for i, layer in enumerate(frame.layers):
            try:
                out.append(Camera.from_array(layer.camera, layer.width, layer.height))
            except ValueError as exc:
                raise ProtocolError(f"layer {i}: bad camera: {exc}") from None
        return out

    @staticmethod
    def _check_rects(frame: QuadFrame, atlas_w: int, atlas_h: int) -> None:
        """ProtocolError if a layer's atlas rect leaves the decoded video."""
        for i, layer in enumerate(frame.layers):
            x, y, w, h = layer.atlas_rect
            if x + w > atlas_w or y + h > atlas_h:
                raise ProtocolError(f"layer {i}: atlas rect {layer.atlas_rect} outside the {atlas_w}x{atlas_h} video")

    def warm_up(self, stereo: bool = False) -> None:
        """Receive and draw :func:`warm_up_frames` on a client of :data:`WARM_UP_SIZE` on this client's context, whose
        mesh finds runs in every layer (none of those small layers would reach QuadMesh's threshold), then drop it:
        on llvmpipe this client's first frame then does not wait for its shaders to compile (docs/speed.md, stop
        53). `stereo`: also make this client's MeshStereo (default eyes), whose YORO shaders are compiled for this
        client's width and run once there (stop 54). This client's frame state is untouched; the throwaway
        client's GL objects (under 2 MB) stay on the context."""
        probe = QuasarClient(*WARM_UP_SIZE, ctx=self.ctx, method=self.method)
        probe.mesh.min_run_quads = 0
        try:
            for payload, pose in warm_up_frames(self.method, *WARM_UP_SIZE):
                probe.receive(payload)
                probe.render(pose)
                probe.coverage()
        finally:
            probe.close()
        if stereo:
            self._mesh_stereo()

    def close(self) -> None:
        """Stop the decoding thread (the GL objects go with the context)."""
        self._video_thread.shutdown(wait=True)

    def render(self, pose: Pose) -> np.ndarray:
        t0 = time.perf_counter()
        camera = Camera(pose, self.frustum, self.width, self.height)
        if self.atlas is None:
            self._coverage = Coverage.empty(self.width, self.height)
            return np.zeros((self.height, self.width, 3), np.uint8)
        self.view.render(self.mesh, camera, self.atlas)
        image = self.view.read_color()
        self._coverage = None    # read from the view when asked for (`coverage`): a display loop seldom needs it
        self.stats.setdefault("ms", {})["render"] = (time.perf_counter() - t0) * 1e3
        return image

    def coverage(self) -> Coverage:
        """Where the last `render` drew a quad (read from the mesh view on the first call after it); nothing
        else fills the display."""
        if self._coverage is None:
            self._coverage = Coverage.from_masks(self.view.read_drawn())
        return self._coverage

    # ------------------------------------------------------------------------------------------------ stereo
    def stereo_frame(self, pose: Pose, mode: str = "yoro", with_rendered: bool = False, dominant: str = "left",
                     ipd: float = DEFAULT_IPD_M, masks: bool = True) -> StereoFrame:
        """Both eyes at head `pose` from one mesh render (client.stereo.MeshStereo): the dominant eye is drawn
        from the quad mesh, the other synthesized from its colour and depth (`mode` "yoro"; "rerender" also
        re-renders the other eye's disoccluded pixels from the mesh; "both" renders both eyes). `with_rendered`
        also renders the other eye normally, for its image and the cost ratio; `masks=False` skips reading back
        the disocclusion masks (the frame's fractions and mask are None). Before any payload, both eyes are black.
        The stage times are also in `stats["stereo_ms"]`."""
        self.coverage()    # the last `render`'s, read before the dominant eye is drawn into the same view
        stereo = self._mesh_stereo(dominant, ipd)
        head = Camera(pose, self.frustum, self.width, self.height)
        if self.atlas is None:
            if mode not in STEREO_MODES:
                raise ValueError(f"stereo mode must be one of {', '.join(STEREO_MODES)}, got {mode!r}")
            black = np.zeros((self.height, self.width, 3), np.uint8)
            return StereoFrame(black, black.copy(), dominant, mode, stereo.eye_cameras(head)[1],
                               {"dominant": 0.0, "synthesize": 0.0, "rerender": 0.0})
        frame = stereo.frame(self.mesh, self.view, self.atlas, head, mode, with_rendered, masks)
        self.stats["stereo_ms"] = dict(frame.ms)
        return frame

    def _mesh_stereo(self, dominant: str = "left", ipd: float = DEFAULT_IPD_M) -> MeshStereo:
        """The MeshStereo for `dominant` and `ipd`, made (and its shaders run once) on first use or when they
        change."""
        stereo = self._stereo
        if stereo is None or stereo.synth.dominant != dominant or stereo.synth.ipd != float(ipd):
            if stereo is not None:
                stereo.release()
            stereo = self._stereo = MeshStereo(self.ctx, self.width, self.height, ipd, dominant,
                                               crack_fill=self.crack_fill)
        return stereo

    def render_stereo(self, pose: Pose, mode: str = "yoro") -> tuple[np.ndarray, np.ndarray]:
        """(left, right) eye images at head `pose`: the left eye rendered, the right one made by `mode` (see
        `stereo_frame`)."""
        frame = self.stereo_frame(pose, mode, masks=False)
        return frame.left, frame.right
