"""The QuadStream-like baseline (QUASAR §4.1.1–4.1.2, after Hladky et al. 2022): quads from the centre view and
the 8 corners of a box viewcell, each view masked by the quads of the views before it (with 1-pixel boundary
expansion, since the views are not pixel-aligned), plus a wide-FOV view. No temporal compression: every frame is
self-contained. Colour uses the same linear atlas as QUASAR (QuadStream bin-packs; QUASAR §3.4.1 found linear
packing 1.5–2x cheaper to encode), one full-size tile per view."""
from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field

import numpy as np

from quadcast.protocol.frame import FramePayload, FrameType, Method
from quadcast.protocol.quads import LayerKind, QuadFrame, QuadLayer, encode_quad_frame
from quadcast.render.camera import Camera, Pose
from quadcast.render.quadmesh import MeshLayer, MeshView, QuadMesh
from quadcast.render.renderer import DeferredRenderer, GBuffer
from quadcast.server.layers import AtlasComposer, AtlasLayout, wide_camera
from quadcast.server.method import MethodServer
from quadcast.server.quads import QuadGenerator, QuadParams, QuadTimings, grow_mask, quad_stats
from quadcast.codec.encoder import AtlasEncoder, VideoSettings


@dataclass
class QuadStreamSettings:
    width: int = 960
    height: int = 540
    fovy_deg: float = 60.0
    viewcell_half: float = 0.5      # the box viewcell's half side (m): corner views at (±h, ±h, ±h)
    params: QuadParams = field(default_factory=lambda: QuadParams(coarse_passes=0))
    wide_fovy_deg: float = 120.0
    wide_scale: float = 0.5
    covered_tolerance: float = 0.01  # relative depth within which a pixel counts as already covered
    zstd_level: int = 3
    depth_bits: int | None = 12          # quad depths' mantissa bits on the wire (protocol.quads.round_mantissa)
    video: VideoSettings = field(default_factory=VideoSettings)


def _grid_layout(width: int, height: int, views: int, wide: tuple[int, int]) -> list[tuple[int, int, int, int]]:
    cols = 3
    rects = [((i % cols) * width, (i // cols) * height, width, height) for i in range(views)]
    rows = -(-views // cols)
    rects.append((0, rows * height, *wide))
    return rects


class QuadStreamServer(MethodServer):
    name = "quadstream"

    def __init__(self, renderer: DeferredRenderer, settings: QuadStreamSettings | None = None):
        self.s = s = settings or QuadStreamSettings()
        self.renderer, self.ctx = renderer, renderer.ctx
        self.generator = QuadGenerator(self.ctx, s.width, s.height)
        probe = wide_camera(self.camera_for(Pose([0, 0, 0])), s.wide_fovy_deg, s.wide_scale)
        self.wide_generator = QuadGenerator(self.ctx, probe.width, probe.height)
        self.gbuffers = [GBuffer(self.ctx, s.width, s.height) for _ in range(9)]
        self.wide_gbuffer = GBuffer(self.ctx, probe.width, probe.height)
        self.rects = _grid_layout(s.width, s.height, 9, (probe.width, probe.height))
        aw = max(x + w for x, _, w, _ in self.rects)
        ah = max(y + h for _, y, _, h in self.rects)
        self.layout = AtlasLayout(aw + aw % 2, ah + ah % 2, self.rects[0], self.rects[0], tuple(self.rects[1:9]),
                                  self.rects[9])
        self.atlas = AtlasComposer(self.ctx, self.layout)
        self.encoder = AtlasEncoder(self.layout.width, self.layout.height, s.video)
        self.mesh = QuadMesh(self.ctx, run_parallax_px=0.0)   # the strict runs (QuadMesh's doc says why)
        self.mesh_view = MeshView(self.ctx, s.width, s.height, depth_only=True)
        self.frame_id = 0
        self._keyframe = True

    def camera_for(self, pose: Pose) -> Camera:
        return Camera.perspective(pose, self.s.width, self.s.height, self.s.fovy_deg)

    def request_reference(self) -> None:
        self._keyframe = True

    def warm_up(self, frames: list[tuple[Pose, float]]) -> None:
        # no layer of a warm-up's small frames reaches QuadMesh's run threshold: find runs in every layer, so that
        # their passes are compiled too
        self.mesh.min_run_quads = 0
        super().warm_up(frames)

    def encode(self, pose: Pose, t: float) -> FramePayload:
        s, ctx = self.s, self.ctx
        ms = {"gbuffers": 0.0}
        timings = QuadTimings()
        h = s.viewcell_half
        cameras = [self.camera_for(pose)] + [self.camera_for(pose.offset_local(c))
                                             for c in itertools.product((-h, h), repeat=3)]
        layers: list[QuadLayer] = []
        mesh_layers: list[MeshLayer] = []
        for i, (cam, gb) in enumerate(zip(cameras, self.gbuffers)):
            t0 = time.perf_counter()
            self.renderer.gbuffer(cam, t, target=gb)
            ctx.finish()
            ms["gbuffers"] += (time.perf_counter() - t0) * 1e3
            mask = None
            if mesh_layers:  # only what the earlier views' quads do not already cover, grown by one pixel
                self.mesh.build(mesh_layers, (self.layout.width, self.layout.height))
                self.mesh_view.render(self.mesh, cam)
                covered_depth, depth = self.mesh_view.read_depth(), gb.read_depth()
                with np.errstate(invalid="ignore"):
                    new = ~(np.abs(covered_depth - depth) <= s.covered_tolerance * depth)
                new &= np.isfinite(depth)
                mask = grow_mask(new)
            params = s.params if i == 0 else QuadParams(**{**s.params.__dict__, "sky": False})
            quads, tm = self.generator.generate(gb.position, gb.normal, cam, params, mask)
            timings.add(tm)
            kind = LayerKind.VISIBLE if i == 0 else LayerKind.HIDDEN
            layers.append(QuadLayer(kind, s.width, s.height, cam.to_array(), self.rects[i], quads))
            mesh_layers.append(MeshLayer(quads, cam, self.rects[i]))
        t0 = time.perf_counter()
        wide_cam = wide_camera(cameras[0], s.wide_fovy_deg, s.wide_scale)
        self.renderer.gbuffer(wide_cam, t, target=self.wide_gbuffer)
        ms["gbuffers"] += (time.perf_counter() - t0) * 1e3
        wide, tm = self.wide_generator.generate(self.wide_gbuffer.position, self.wide_gbuffer.normal, wide_cam,
                                                QuadParams(**{**s.params.__dict__, "sky": False}), inner=cameras[0])
        timings.add(tm)
        layers.append(QuadLayer(LayerKind.WIDE, wide_cam.width, wide_cam.height, wide_cam.to_array(), self.rects[9],
                                wide))
        ms.update(quads=timings.quads, merge=timings.merge, gather=timings.gather)

        t0 = time.perf_counter()
        qframe = QuadFrame(layers)
        geometry = encode_quad_frame(qframe, s.zstd_level, s.depth_bits)
        ms["zstd"] = (time.perf_counter() - t0) * 1e3
        t0 = time.perf_counter()
        self.atlas.clear()
        for gb, rect in zip(self.gbuffers, self.rects):
            self.atlas.draw(gb.color, rect)
        self.atlas.draw(self.wide_gbuffer.color, self.rects[9])
        video = self.encoder.encode(self.atlas.read(), keyframe=self._keyframe)
        self._keyframe = False
        ms["video"] = (time.perf_counter() - t0) * 1e3
        payload = FramePayload(Method.QUADSTREAM, self.frame_id, FrameType.REFERENCE, self.frame_id, float(t),
                               pose.position, pose.quat, video.data, geometry, self_contained=video.keyframe,
                               stats=quad_stats(qframe, ms))
        self.frame_id += 1
        return payload

    def close(self) -> None:
        self.encoder.close()
