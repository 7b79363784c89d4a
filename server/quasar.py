"""QUASAR's server (§3): per frame, layered G-buffers for the predicted pose, quads for every layer, reference or
residual frames (§3.5), the colour atlas as H.264 and the quads as a columnar zstd blob."""
from __future__ import annotations

import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from quadcast.protocol.frame import FramePayload, FrameType, Method
from quadcast.protocol.methods import method_video
from quadcast.protocol.quads import LayerKind, QuadFrame, QuadLayer, QuadSet, encode_quad_frame
from quadcast.render.camera import Camera, Pose
from quadcast.render.quadcache import QuadCache
from quadcast.render.quadmesh import MeshLayer, MeshView, QuadMesh
from quadcast.render.renderer import DeferredRenderer, GBuffer
from quadcast.server.farfield import FarField
from quadcast.server.layers import AtlasComposer, AtlasLayout, LayerRenderer, wide_camera
from quadcast.server.method import MethodServer
from quadcast.server.quads import QuadGenerator, QuadParams, QuadTimings, grow_mask, inner_rect, quad_stats
from quadcast.codec.encoder import AtlasEncoder, VideoSettings
from quadcast.protocol.rate import OperatingPoint


@dataclass
class QuasarSettings:
    width: int = 960
    height: int = 540
    fovy_deg: float = 60.0
    layers: int = 4                      # k: the visible layer + k-1 hidden layers
    viewcell_radius: float = 0.5         # metres
    reference_every: int = 5             # a reference frame every K frames ...
    # ... or when the pose moved this far (m) ... Twice the view cell's radius: a server too slow for the pose rate
    # (the live demo's) sends fewer reference frames at 1 m than at 0.5, for fewer bits at about the same FLIP
    # (lower in four of five runs); at 30 frames/s it seldom triggers (docs/speed.md, stop 47)
    reference_distance: float = 1.0
    reference_angle_deg: float = 15.0    # ... or turned this much since the reference
    visible: QuadParams = field(default_factory=QuadParams)
    hidden: QuadParams = field(default_factory=lambda: QuadParams().relaxed())
    # The wide view (out-of-frame content) at 0.625 of the resolution, 75 deg high: the far field behind everything
    # shows whatever lies beyond it, so its pixels go where a head turn before the next frame looks. 120 deg at 0.5
    # (QuadStream's) spread them 1.6x thinner: on the real-trace benchmark FLIP fell 1-3% on every row at the same
    # or a lower rate (README, "Wide view"). When frames come farther apart (a live server on a slow machine), the
    # view widens, up to wide_fovy_max_deg (same pixels, so the atlas keeps its size), to cover on each side how far
    # the head's rotation strayed from the predicted one while recent frames were shown (set_rotation_miss, from
    # the session core); until that is known, what a head turning at wide_turn_dps sees move in over the mean
    # interval between the last frames' display times.
    wide_fovy_deg: float = 75.0
    wide_fovy_max_deg: float = 120.0
    wide_turn_dps: float = 120.0
    wide_scale: float = 0.625
    hidden_scale: float = 0.5
    # A server slower than the pose rate (the last frames' display times more than hidden_reuse_after_ms apart on
    # average, as in the live demo here) renders the hidden layers every `hidden_every` frames and sends the last
    # ones again in between, as they were: their quads, their camera, and their colour in the atlas from the
    # G-buffers kept since. Frames then take 12% less time on average here, and at equal CPU time FLIP was about the
    # same: better in three of five runs (the real traces' fastest windows and the walk; docs/speed.md, stop 49).
    # 1: every frame.
    hidden_every: int = 2
    hidden_reuse_after_ms: float = 100.0
    far_field: bool = True               # a cube map around the view cell behind everything (server/farfield.py)
    far_scale: float = 0.25              # its face size, relative to the view's height ...
    far_block: int = 16                  # ... in whole blocks of this many pixels (its quads)
    far_split_m: float = 0.0             # > 0: geometry farther than this gets no quads (the far field shows it)
    # ... drawn from meshes with about this fraction of their triangles (DeferredRenderer.coarse_meshes; 1: every
    # one). Its faces are a few dozen pixels across, and llvmpipe pays per triangle: the monastery's six faces 55 ms
    # -> 23 ms; FLIP within 0.0001 of every triangle's, or better, on five of six evals, +0.0006 on the sixth
    # (docs/speed.md, stop 51).
    far_detail: float = 0.1
    # Far-field pixels that, seen from the view cell's edge (viewcell_radius from the cube map's centre), would lie
    # more than this from their own point -- a near object drawn on the far surface behind it -- take the colour of
    # the nearest pixel that would not (server/farfield.py, near_occluders; 0 keeps every colour). A lone object
    # a few metres away otherwise shows a ghost of itself beside its silhouettes. 10 deg: FLIP 0.0393 -> 0.0365 on
    # a lone glTF object, no row of the real-trace benchmark worse (README, "Ghosts in the far field").
    far_occluder_deg: float = 10.0
    connectivity: float = 0.001          # EDP: relative depth gap that is still the same surface
    change_threshold: float = 0.01       # relative depth change that makes a reference pixel "updated"
    # QUASAR's boundary expansion (§3.5.1) of the revealed region, in pixels. Off by default: on the real-trace
    # benchmark one pixel cost 8-13% of the rate for 0.5-0.7% of FLIP (see README, "Boundary expansion").
    reveal_expansion_px: int = 0
    zstd_level: int = 3
    depth_bits: int | None = 12          # quad depths' mantissa bits on the wire (protocol.quads.round_mantissa)
    # ... and those of the hidden layers and the wide view (None: depth_bits), whose flatten and similarity
    # thresholds are already 10x relaxed: 7 bits (0.4%) cost <= 0.0001 FLIP on the real-trace benchmark and 5-6% of
    # the rate (README, "Fill-in depth precision")
    fill_depth_bits: int | None = 7
    video: VideoSettings = field(default_factory=lambda: VideoSettings(**method_video("quasar", None)))

    def __post_init__(self):
        if self.width % 2 or self.height % 2 or self.width < 16 or self.height < 16:
            raise ValueError(f"size must be even and at least 16x16, got {self.width}x{self.height}")
        if not self.viewcell_radius >= 0:
            raise ValueError(f"viewcell radius must be >= 0 m, got {self.viewcell_radius}")
        if self.reference_every < 1:
            raise ValueError(f"reference_every must be >= 1, got {self.reference_every}")
        if self.hidden_every < 1:
            raise ValueError(f"hidden_every must be >= 1, got {self.hidden_every}")
        if not self.hidden_reuse_after_ms >= 0:
            raise ValueError(f"hidden_reuse_after_ms must be >= 0, got {self.hidden_reuse_after_ms}")
        for name in ("depth_bits", "fill_depth_bits"):
            bits = getattr(self, name)
            if bits is not None and not 1 <= bits <= 23:
                raise ValueError(f"{name} must be in 1..23 or None, got {bits}")
        if not 0 <= self.reveal_expansion_px <= 4:
            raise ValueError(f"reveal_expansion_px must be in 0..4, got {self.reveal_expansion_px}")
        if not 0 < self.wide_fovy_deg <= self.wide_fovy_max_deg < 180:
            raise ValueError(f"need 0 < wide_fovy_deg <= wide_fovy_max_deg < 180, got {self.wide_fovy_deg} and "
                             f"{self.wide_fovy_max_deg}")
        if not self.wide_turn_dps >= 0:
            raise ValueError(f"wide_turn_dps must be >= 0, got {self.wide_turn_dps}")
        if self.far_block < 2 or self.far_block & (self.far_block - 1):
            raise ValueError(f"far_block must be a power of 2 >= 2, got {self.far_block}")
        if not 0 < self.far_detail <= 1:
            raise ValueError(f"far_detail must be in (0, 1], got {self.far_detail}")
        if not self.far_occluder_deg >= 0:
            raise ValueError(f"far_occluder_deg must be >= 0, got {self.far_occluder_deg}")

    @property
    def far_size(self) -> int:
        """The far field's face size in pixels (0 without a far field): whole blocks, at least two."""
        if not self.far_field:
            return 0
        b = self.far_block
        return max(2 * b, int(self.height * self.far_scale) // b * b)


@dataclass
class _FrameViews:
    """What one frame rendered (`QuasarServer._render_views`), for its atlas and its quad passes: the main `camera`
    at time `t`; `gbs`, the visible layer's G-buffer and the hidden layers' (on a frame that sends the kept hidden
    layers again, the G-buffers they were made from, which hold their colour); the wide view (`wide_gb` seen by
    `wide_cam`); on a residual frame, the reference view rendered again within `region` where the scene moved
    (`ref_gb`, None where nothing did); on a reference frame, the far field (`fresh_far`)."""

    camera: Camera
    t: float
    is_reference: bool
    gbs: list[GBuffer]
    wide_gb: GBuffer
    wide_cam: Camera
    ref_gb: GBuffer | None = None
    region: tuple[int, int, int, int] = (0, 0, 0, 0)
    fresh_far: FarField | None = None


class QuasarServer(MethodServer):
    name = "quasar"

    def __init__(self, renderer: DeferredRenderer, settings: QuasarSettings | None = None):
        self.s = s = settings or QuasarSettings()
        self.renderer, self.ctx = renderer, renderer.ctx
        probe = wide_camera(self.camera_for(Pose([0, 0, 0])), s.wide_fovy_deg, s.wide_scale)
        self.layout = AtlasLayout.for_view(s.width, s.height, s.layers - 1, (probe.width, probe.height),
                                           s.hidden_scale, s.far_size)
        far = self.camera_for(Pose([0, 0, 0])).frustum.far
        self.far_field = FarField(renderer, s.far_size, s.far_block, 0.9 * far,
                                  s.far_detail) if s.far_field else None
        hidden_size = self.layout.hidden[0][2:] if self.layout.hidden else (s.width, s.height)
        self.layer_renderer = LayerRenderer(renderer, s.width, s.height, s.layers, hidden_size)
        self._generators: dict[tuple[int, int], QuadGenerator] = {}
        self.generator = self.generator_for(s.width, s.height)
        self.wide_generator = self.generator_for(probe.width, probe.height)
        self.hidden_generator = self.generator_for(*hidden_size)
        self.wide_gbuffer = GBuffer(self.ctx, probe.width, probe.height)
        self.skip_wide_inner = True   # the wide view is neither drawn nor lit where it makes no quads (`inner_rect`)
        self.reference_gbuffer = GBuffer(self.ctx, s.width, s.height)
        self.atlas = AtlasComposer(self.ctx, self.layout)
        self.encoder = AtlasEncoder(self.layout.width, self.layout.height, s.video)
        # at a foveated operating point, the atlas's views coarsened away from the gaze as they are composed
        self.atlas_foveation = None
        # The atlas is coded by x264 on a thread of its own while the quad passes run (it releases the GIL, and
        # llvmpipe leaves cores idle between dispatches); False: coded in turn, after the quads. The same bytes.
        self.code_video_beside_quads = True
        self._video_thread: ThreadPoolExecutor | None = None
        self.cache = QuadCache(s.width, s.height)
        self.mesh = QuadMesh(self.ctx, run_parallax_px=0.0)   # the strict runs (QuadMesh's doc says why)
        self.mesh_view = MeshView(self.ctx, s.width, s.height, depth_only=True)
        self.frame_id = 0
        self.reference_id = -1
        self.reference_camera: Camera | None = None
        self.reference_depth: np.ndarray | None = None
        self.reference_ids: np.ndarray | None = None
        self.frames_since_reference = 0
        self._reference_time = 0.0
        self._display_times: list[float] = []   # the last frames' display times (the wide view's FOV)
        self._force_reference = True
        # the hidden layers last rendered and the frame id they were rendered for (sent again until `hidden_every`
        # frames have passed); None: render them with the next frame
        self._kept_hidden: tuple[int, list[QuadLayer]] | None = None
        self.point: OperatingPoint | None = None      # the operating point applied last (None: the settings as given)
        self.rotation_miss_deg: float | None = None   # set_rotation_miss: the wide view's margin on each side

    def _split(self, params: QuadParams) -> QuadParams:
        """With a far field and a split distance, geometry beyond the split gets no quads (the far field shows it)."""
        s = self.s
        return replace(params, max_depth=s.far_split_m) if s.far_field and s.far_split_m > 0 else params

    @property
    def visible_params(self) -> QuadParams:
        """The visible layer's quad parameters: the settings' (an operating point's, once one is applied)."""
        return self._split(self.s.visible)

    @property
    def hidden_params(self) -> QuadParams:
        """The hidden layers' and wide view's quad parameters."""
        return self._split(self.s.hidden)

    def generator_for(self, width: int, height: int) -> QuadGenerator:
        """One quad generator per layer size (they hold the Quad Maps)."""
        if (width, height) not in self._generators:
            self._generators[(width, height)] = QuadGenerator(self.ctx, width, height)
        return self._generators[(width, height)]

    def camera_for(self, pose: Pose) -> Camera:
        return Camera.perspective(pose, self.s.width, self.s.height, self.s.fovy_deg)

    def request_reference(self) -> None:
        self._force_reference = True

    WARM_UP_FOVEATION = "sigma=5,max=32,atlas=4"
    """The foveated point a warm-up's last frame is made at again (its CRF the settings'), so that the atlas's
    foveated pass (server/atlas_fovea.frag.glsl, sampling mip levels) is compiled before a session's first foveated
    frame needs it: at 480x270 with Mesa's shader cache empty that frame took 198-219 ms without it and 108-131 with
    it, the next five 67-127 either way (docs/speed.md, stop 58)."""

    def warm_up(self, frames: list[tuple[Pose, float]]) -> None:
        # no layer of a warm-up's small frames reaches QuadMesh's run threshold: find runs in every layer, so that
        # their passes are compiled too
        self.mesh.min_run_quads = 0
        super().warm_up(frames)
        if frames:
            self.apply_operating_point(OperatingPoint.parse(f"crf={self.s.video.crf},{self.WARM_UP_FOVEATION}"))
            self.encode(*frames[-1])

    def apply_operating_point(self, point: OperatingPoint) -> bool:
        """Make the next frames at ``point`` (see :class:`quadcast.protocol.rate.OperatingPoint`). Every knob keeps
        the atlas size. Quad thresholds, view cell, hidden layers and reference interval take effect with the next
        frame (each frame's quads stand on their own); a new CRF restarts the H.264 stream, so the next frame is a
        reference frame (an IDR); atlas foveation needs nothing from the stream."""
        from quadcast.server.foveation import AtlasFoveation
        if self.point is not None and self.point.same_settings(point):
            self.point = point
            return True
        if not hasattr(self, "_base_settings"):
            self._base_settings = self.s
        base, q = self._base_settings, point.quad_scale
        fovea = dict(fovea_deg=point.fovea_deg, fovea_sigma_deg=point.fovea_sigma_deg, fovea_gamma=point.fovea_gamma,
                     fovea_max_scale=point.fovea_max_scale)

        def scaled(params, coarse):
            return replace(params, delta_sim=params.delta_sim * q, delta_flatten=params.delta_flatten * q,
                           coarse_passes=coarse, gaze=self.s.visible.gaze, **fovea)
        video = replace(base.video, crf=point.crf)
        restart = video != self.s.video
        self.s = replace(self.s, visible=scaled(base.visible, point.coarse_passes),
                         hidden=scaled(base.hidden, point.coarse_passes + 1), viewcell_radius=point.viewcell_m,
                         reference_every=point.reference_every, video=video)
        self.layer_renderer.use_hidden_layers(min(point.hidden_layers, base.layers - 1))
        if restart:
            self.encoder.close()
            self.encoder = AtlasEncoder(self.layout.width, self.layout.height, video)
            self._force_reference = True
        self.atlas_foveation = None
        if point.foveated and point.fovea_atlas > 1:
            from quadcast.server.layers import resized
            main = self.camera_for(Pose([0, 0, 0]))
            wide = wide_camera(main, base.wide_fovy_deg, base.wide_scale)
            L = self.layout
            views = [(L.reference, main), (L.current, main), (L.wide, wide)]
            views += [(rect, resized(main, *rect[2:])) for rect in L.hidden]
            foveation = AtlasFoveation(views, point, self.s.visible.gaze)
            if foveation.active:
                self.atlas_foveation = foveation
        self.point = point
        return True

    def set_gaze(self, gaze) -> None:
        """The viewer's gaze, a view-space direction, for the next frames: foveation centres on it."""
        g = tuple(float(v) for v in gaze)
        if g == self.s.visible.gaze:
            return
        self.s = replace(self.s, visible=replace(self.s.visible, gaze=g), hidden=replace(self.s.hidden, gaze=g))
        if self.atlas_foveation is not None:
            self.atlas_foveation = self.atlas_foveation.with_gaze(g)

    def _needs_reference(self, camera: Camera) -> bool:
        ref = self.reference_camera
        return (self._force_reference or ref is None or self.frames_since_reference >= self.s.reference_every
                or camera.pose.distance_to(ref.pose) > self.s.reference_distance
                or camera.pose.angle_to_deg(ref.pose) > self.s.reference_angle_deg)

    def set_rotation_miss(self, degrees: float | None) -> None:
        if degrees is not None and not (np.isfinite(degrees) and degrees >= 0):
            raise ValueError(f"QuasarServer.set_rotation_miss: expected degrees >= 0 or None, got {degrees!r}")
        self.rotation_miss_deg = None if degrees is None else float(degrees)

    def _wide_fovy(self, t: float) -> float:
        """Record that the frame being made is displayed at `t`, and return its wide view's vertical FOV: the
        view's own plus, on each side, the rotation miss (`set_rotation_miss`) or, while that is unknown, the turn
        `wide_turn_dps` makes in the mean interval between the last nine frames' display times; within
        [wide_fovy_deg, wide_fovy_max_deg]. Display times that go back (a new trace) start the count again."""
        s, times = self.s, self._display_times
        if times and t < times[-1]:
            times.clear()
        times.append(float(t))
        del times[:-9]
        if self.rotation_miss_deg is not None:
            margin = self.rotation_miss_deg
        else:
            margin = s.wide_turn_dps * self._display_interval()
        return float(np.clip(s.fovy_deg + 2.0 * margin, s.wide_fovy_deg, s.wide_fovy_max_deg))

    def _display_interval(self) -> float:
        """The mean interval (s) between the display times `_wide_fovy` recorded last (0 before two)."""
        times = self._display_times
        return (times[-1] - times[0]) / (len(times) - 1) if len(times) > 1 else 0.0

    def _hidden_due(self) -> bool:
        """Whether this frame renders the hidden layers (see QuasarSettings.hidden_every), after `_wide_fovy`."""
        s, kept = self.s, self._kept_hidden
        every = s.hidden_every if self._display_interval() * 1e3 > s.hidden_reuse_after_ms else 1
        return kept is None or len(kept[1]) != len(self.layer_renderer.hidden) or self.frame_id - kept[0] >= every

    def encode(self, pose: Pose, t: float) -> FramePayload:
        ms: dict[str, float] = {}
        timings = QuadTimings()
        camera = self.camera_for(pose)
        is_reference = self._needs_reference(camera)

        t0 = time.perf_counter()
        views = self._render_views(camera, t, is_reference)
        ms["gbuffers"] = (time.perf_counter() - t0) * 1e3

        # The atlas holds every layer's colour, all lit by now; its coding needs nothing the quad passes make.
        t0 = time.perf_counter()
        video_job = self._code_atlas(views)
        video_ms = (time.perf_counter() - t0) * 1e3
        try:
            payload = self._quads_and_geometry(views, timings, ms)
        except BaseException:
            # x264 has taken this frame, which is never sent: the next frame is a reference frame (an IDR)
            self._force_reference = True
            video_job.exception()
            raise
        t0 = time.perf_counter()
        video = video_job.result()
        ms["video"] = video_ms + (time.perf_counter() - t0) * 1e3
        frame_type, geometry, qframe = payload
        stats = quad_stats(qframe, ms, cache_quads=len(self.cache))
        payload = FramePayload(Method.QUASAR, self.frame_id, frame_type, self.reference_id, float(t),
                               camera.pose.position, camera.pose.quat, video.data, geometry,
                               self_contained=is_reference and video.keyframe, stats=stats)
        self.frame_id += 1
        return payload

    def _render_views(self, camera: Camera, t: float, is_reference: bool) -> _FrameViews:
        """Every G-buffer this frame needs, lit, the GPU finished. A frame that renders the hidden layers anew
        (`_hidden_due`) forgets the kept ones here; the reference view's moving region is rendered at `t`."""
        s = self.s
        # Every view's geometry pass first (the sun's shadow map before them), then the passes that sample them
        # (lighting, the peel). Sampling what a pass drew makes llvmpipe wait until it is rasterized; in this order
        # its threads rasterize the earlier views while the later ones are drawn, where a view lit right after its
        # geometry pass waited for that pass alone. The same images in either order.
        self.renderer.render_shadows(t)
        self.layer_renderer.draw_visible(camera, t)
        wide_cam = wide_camera(camera, self._wide_fovy(t), s.wide_scale)
        # Lit only where geometry is: the wide view gets no sky quads (the far field shows the sky). Nor is it drawn
        # where it makes no quads, inside the main view (its colour there is black in the atlas).
        wide_gb = self.renderer.geometry_pass(wide_cam, t, target=self.wide_gbuffer,
                                              exclude=inner_rect(wide_cam, camera) if self.skip_wide_inner else None)
        # The reference view is rendered again where the scene moved since it was last rendered (the animated
        # objects and their shadows, §3.5.2: to find what changed, and for its current colour); elsewhere, and in a
        # static scene everywhere, what the reference frame rendered is still exact.
        ref_gb, region = None, (0, 0, 0, 0)
        if not is_reference:
            region = self.renderer.moving_region(self.reference_camera, (self._reference_time, t))
            if region[2] and region[3]:
                ref_gb = self.renderer.geometry_pass(self.reference_camera, t, target=self.reference_gbuffer,
                                                     region=region)
                self._reference_time = t
        fresh_far = self.far_field if is_reference else None    # rendered again on reference frames only
        if fresh_far is not None:
            fresh_far.draw_geometry(camera.pose.position, t, camera.frustum.near, camera.frustum.far)
        fresh_hidden = self._hidden_due()
        if fresh_hidden:
            self._kept_hidden = None        # until this frame's are made
        gbs = self.layer_renderer.render(camera, t, s.viewcell_radius, s.connectivity, visible_drawn=True,
                                         hidden=fresh_hidden)
        self.renderer.lighting_pass(wide_gb, t, geometry_only=not s.hidden.sky)
        if ref_gb is not None:
            self.renderer.lighting_pass(ref_gb, t, region)
        if fresh_far is not None:
            fresh_far.light(t, s.viewcell_radius, s.far_occluder_deg)
        self.ctx.finish()
        return _FrameViews(camera, t, is_reference, gbs, wide_gb, wide_cam, ref_gb, region, fresh_far)

    def _code_atlas(self, views: _FrameViews) -> Future:
        """Compose this frame's colour atlas, read it back and code it: on the video thread
        (`code_video_beside_quads`), else here. On a reference frame the visible layer becomes the reference view."""
        L, gbs, wide_gb, is_reference = self.layout, views.gbs, views.wide_gb, views.is_reference
        fovea = self.atlas_foveation

        def draw(color, rect):
            camera = fovea.cameras.get(rect) if fovea is not None else None
            if camera is None:
                self.atlas.draw(color, rect)
            else:
                self.atlas.draw_foveated(color, rect, fovea.levels, fovea.uniforms(camera))
        self.atlas.clear()
        draw((gbs[0] if is_reference else self.reference_gbuffer).color, L.reference)
        if not is_reference:
            draw(gbs[0].color, L.current)
        for gb, rect in zip(gbs[1:], L.hidden):
            draw(gb.color, rect)
        draw(wide_gb.color, L.wide)
        if self.far_field is not None:                    # in every frame's atlas: the client samples it there
            for color, rect in zip(self.far_field.colors, L.far):
                self.atlas.draw(color, rect)
        picture = self.atlas.read()
        if self.code_video_beside_quads:
            if self._video_thread is None:
                self._video_thread = ThreadPoolExecutor(1, thread_name_prefix="quasar-x264")
            # the encoder as it is now (apply_operating_point may replace it between frames, never during one)
            return self._video_thread.submit(self.encoder.encode, picture, keyframe=is_reference)
        job: Future = Future()
        try:
            job.set_result(self.encoder.encode(picture, keyframe=is_reference))
        except Exception as exc:
            job.set_exception(exc)
        return job

    def _quads_and_geometry(self, views: _FrameViews, timings: QuadTimings,
                            ms: dict[str, float]) -> tuple[FrameType, bytes, QuadFrame]:
        """The frame's quads for every layer, the client's cache kept (§3.5), and the geometry blob."""
        s, L = self.s, self.layout

        def quads(gb, cam, params, mask=None, generator=None, inner=None):
            q, tm = (generator or self.generator).generate(gb.position, gb.normal, cam, params, mask, inner)
            timings.add(tm)
            return q

        def fill(q: QuadSet) -> QuadSet:
            """A hidden layer's or the wide view's quads, their depths at fill_depth_bits."""
            return q if s.fill_depth_bits is None else q.with_depth_bits(s.fill_depth_bits)

        # "cache": keeping the client's cache -- on a reference frame its reset and the reference view's depths and
        # ids; on a residual frame what changed in it and the mesh draw that finds what it does not cover -- less
        # the quad passes it runs (timed as theirs)
        t0, quad_ms = time.perf_counter(), timings.total
        layers = (self._reference_layers if views.is_reference else self._residual_layers)(views, quads)
        ms["cache"] = (time.perf_counter() - t0) * 1e3 - (timings.total - quad_ms)
        if self._kept_hidden is None:               # rendered this frame (`_hidden_due`): make and keep their quads
            hidden_cam = self.layer_renderer.hidden_camera(views.camera)
            self._kept_hidden = (self.frame_id, [
                QuadLayer(LayerKind.HIDDEN, hidden_cam.width, hidden_cam.height, hidden_cam.to_array(), rect,
                          fill(quads(gb, hidden_cam, self.hidden_params, generator=self.hidden_generator)))
                for gb, rect in zip(views.gbs[1:], L.hidden)])
        layers += self._kept_hidden[1]
        wide_cam = views.wide_cam
        wide = fill(quads(views.wide_gb, wide_cam, self.hidden_params, generator=self.wide_generator,
                          inner=views.camera))
        layers.append(QuadLayer(LayerKind.WIDE, wide_cam.width, wide_cam.height, wide_cam.to_array(), L.wide, wide))
        if views.fresh_far is not None:
            layers += views.fresh_far.layers(L.far)          # sent with reference frames; the client keeps them
        ms.update(quads=timings.quads, merge=timings.merge, gather=timings.gather)

        t0 = time.perf_counter()
        frame_type = FrameType.REFERENCE if views.is_reference else FrameType.RESIDUAL
        qframe = QuadFrame(layers)
        geometry = encode_quad_frame(qframe, s.zstd_level, s.depth_bits)
        ms["zstd"] = (time.perf_counter() - t0) * 1e3
        return frame_type, geometry, qframe

    def _reference_layers(self, views: _FrameViews, quads) -> list[QuadLayer]:
        """A reference frame's visible layer; the client's cache starts again from it, and this view becomes the
        reference view. `quads(gb, camera, params, mask=None)` runs the quad passes."""
        s, camera, gb = self.s, views.camera, views.gbs[0]
        visible = quads(gb, camera, self.visible_params)
        self.cache.reset(visible)
        self.reference_camera = camera
        self.reference_depth = gb.read_depth()
        self.reference_ids = gb.read_object_id()
        # This view's G-buffer becomes the reference view's (later frames re-render only what moves in it).
        self.reference_gbuffer, self.layer_renderer.visible = gb, self.reference_gbuffer
        self._reference_time = views.t
        self.reference_id = self.frame_id
        self.frames_since_reference = 1  # frames sent since, and including, the reference
        self._force_reference = False
        return [QuadLayer(LayerKind.VISIBLE, s.width, s.height, camera.to_array(), self.layout.reference, visible)]

    def _residual_layers(self, views: _FrameViews, quads) -> list[QuadLayer]:
        """A residual frame's updated layer (what changed in the reference view, §3.5.2) and revealed layer (what
        the cached mesh does not cover at this pose, §3.5.1), the client's cache kept. `quads` as above."""
        s, L, camera, ref_cam, ref_gb = self.s, self.layout, views.camera, self.reference_camera, views.ref_gb
        updated = QuadSet.empty()
        if ref_gb is not None:
            # Geometry that changed in the reference view since it was cached (§3.5.2), within the region.
            x, y, w, h = views.region
            rows, cols = slice(y, y + h), slice(x, x + w)
            depth_now, ids_now = ref_gb.read_depth(views.region), ref_gb.read_object_id(views.region)
            depth_ref, ids_ref = self.reference_depth[rows, cols], self.reference_ids[rows, cols]
            with np.errstate(invalid="ignore"):
                changed_here = (ids_now != ids_ref) | ~(
                    np.abs(depth_now - depth_ref) <= s.change_threshold * np.minimum(depth_now, depth_ref))
            changed_here &= ~(np.isinf(depth_now) & np.isinf(depth_ref))
            if changed_here.any():
                changed = np.zeros_like(self.reference_ids, bool)
                changed[rows, cols] = changed_here
                updated = quads(ref_gb, ref_cam, self.visible_params, mask=changed)
                depth_ref[changed_here] = depth_now[changed_here]
                ids_ref[changed_here] = ids_now[changed_here]
            self.cache.update(updated)
        # Geometry revealed at the new pose: not covered by the cached mesh (§3.5.1), grown by reveal_expansion_px
        # (QUASAR's boundary expansion; off by default).
        self.mesh.build([MeshLayer(self.cache.quads, ref_cam, L.reference, edit=self.cache.edit)],
                        (L.width, L.height))
        self.mesh_view.render(self.mesh, camera)
        mesh_depth = self.mesh_view.read_depth()
        depth = views.gbs[0].read_depth()
        with np.errstate(invalid="ignore"):
            revealed = np.isinf(mesh_depth) | (depth < mesh_depth * (1 - s.change_threshold))
        for _ in range(s.reveal_expansion_px):
            revealed = grow_mask(revealed)
        if self.far_field is not None and s.far_split_m > 0:
            revealed &= ~(depth > s.far_split_m)       # far geometry (and revealed sky) is the far field's
        rev = quads(views.gbs[0], camera, self.visible_params, mask=revealed) if revealed.any() else QuadSet.empty()
        self.frames_since_reference += 1
        return [QuadLayer(LayerKind.UPDATED, s.width, s.height, ref_cam.to_array(), L.reference, updated),
                QuadLayer(LayerKind.REVEALED, s.width, s.height, camera.to_array(), L.current, rev)]

    def close(self) -> None:
        if self._video_thread is not None:
            self._video_thread.shutdown(wait=True)
            self._video_thread = None
        self.encoder.close()
