"""Operating points on the QUASAR server (server/quasar.py apply_operating_point, server/foveation.py): switching
mid-stream keeps the stream decodable, and each knob moves what it should."""
from __future__ import annotations

import numpy as np
import pytest

from quadcast.client.quasar import QuasarClient
from quadcast.codec.encoder import VideoSettings
from quadcast.protocol.frame import FrameType, decode_frame_payload, encode_frame_payload
from quadcast.protocol.pose import gaze_direction
from quadcast.protocol.quads import LayerKind, decode_quad_frame
from quadcast.protocol.methods import method_crf
from quadcast.protocol.rate import OperatingPoint, own_point
from quadcast.protocol.session import EncodeFrame
from quadcast.render.camera import Camera, Pose
from quadcast.render.traces import resolve_trace
from quadcast.server.foveation import AtlasFoveation
from quadcast.server.layers import AtlasComposer, AtlasLayout
from quadcast.server.quasar import QuasarServer, QuasarSettings
from quadcast.render.gaze import GazeTrace, GazeTraceError
from quadcast.sim.metrics import compare

W, H = 192, 108
WALK = resolve_trace("builtin:walk")


def walk_pose(t: float) -> Pose:
    return Pose(*WALK.pose_at(WALK.times[0] + t))


def wire(payload):
    return decode_frame_payload(encode_frame_payload(payload))


def _layers(payload, kind):
    return [l for l in decode_quad_frame(payload.geometry).layers if l.kind == kind]


def test_switching_points_mid_stream_stays_decodable(courtyard_renderer):
    server = QuasarServer(courtyard_renderer, QuasarSettings(width=W, height=H, reference_every=100,
                                                             reference_angle_deg=180, reference_distance=100,
                                                             video=VideoSettings(crf=23)))
    client = QuasarClient(W, H, ctx=courtyard_renderer.ctx)
    same_video = OperatingPoint("thresholds", crf=23, quad_scale=4, coarse_passes=5, hidden_layers=1, viewcell_m=0.25)
    new_video = OperatingPoint("crf", crf=35, hidden_layers=0)
    kinds, hidden = [], []
    for k in range(8):
        if k == 3:
            assert server.apply_operating_point(same_video)
            assert server.s.visible.delta_sim == pytest.approx(4 * QuasarSettings().visible.delta_sim)
            assert server.s.hidden.coarse_passes == 6 and server.s.viewcell_radius == 0.25
        if k == 5:
            assert server.apply_operating_point(new_video)
        t = k / 30
        payload = server.encode(walk_pose(t), t)
        kinds.append(payload.frame_type)
        hidden.append(len(_layers(payload, LayerKind.HIDDEN)))
        client.receive(wire(payload))
        assert not client.needs_reference
        image = client.render(walk_pose(t))
        truth = courtyard_renderer.render_color(Camera.perspective(walk_pose(t), W, H), t)
        assert compare(truth, image).ssim > 0.5
    # thresholds, view cell and hidden layers switch without a new reference; a new CRF restarts the H.264 stream,
    # so that frame is a reference (an IDR) and the client goes on decoding
    assert kinds == [FrameType.REFERENCE] + [FrameType.RESIDUAL] * 4 + [FrameType.REFERENCE] + [FrameType.RESIDUAL] * 2
    assert hidden == [3, 3, 3, 1, 1, 0, 0, 0]
    assert server.point is new_video and server.s.video.crf == 35


def test_the_own_point_is_what_the_server_sends_unadapted(courtyard_renderer):
    """`own_point` (the rate controller's point above its ladder) with the session's CRF, view cell and reference
    interval makes the same bytes as a server given no point at all; a ladder-style point does not."""
    def frames(point):
        server = QuasarServer(courtyard_renderer, QuasarSettings(width=W, height=H, viewcell_radius=0.25,
                                                                 reference_every=3))
        try:
            if point is not None:
                assert server.apply_operating_point(point)
            return [(p.video, p.geometry) for p in (server.encode(walk_pose(0.1 * k), 0.1 * k) for k in range(4))]
        finally:
            server.close()
    plain = frames(None)
    assert frames(own_point(None, 0.25, 3)) == plain
    assert frames(OperatingPoint(crf=method_crf("quasar", None), viewcell_m=0.25, reference_every=3,
                                 hidden_layers=1)) != plain


def test_coarser_points_cost_fewer_bytes_and_foveation_keeps_the_centre(courtyard_renderer):
    sizes = {}
    images = {}
    pose, t = walk_pose(1.0), 1.0
    truth = courtyard_renderer.render_color(Camera.perspective(pose, W, H), t)
    for point in (OperatingPoint("uniform"), OperatingPoint("coarse", crf=33, quad_scale=8, coarse_passes=6),
                  OperatingPoint("foveated", fovea_deg=5, fovea_sigma_deg=4, fovea_max_scale=32, fovea_atlas=4)):
        server = QuasarServer(courtyard_renderer, QuasarSettings(width=W, height=H))
        server.apply_operating_point(point)
        payload = server.encode(pose, t)
        client = QuasarClient(W, H, ctx=courtyard_renderer.ctx)
        client.receive(wire(payload))
        sizes[point.name] = (len(payload.video), len(payload.geometry), payload.stats.quads)
        images[point.name] = client.render(pose)
    assert sum(sizes["coarse"][:2]) < 0.8 * sum(sizes["uniform"][:2])
    assert sizes["foveated"][2] < 0.8 * sizes["uniform"][2]           # fewer quads away from the centre
    assert sizes["foveated"][0] < sizes["uniform"][0]                 # and a cheaper atlas
    # the centre (within 5 degrees) is as good as with uniform settings; the whole frame is worse
    centre = Camera.perspective(pose, W, H).eccentricity_deg() <= 5.0
    fov, uni = compare(truth, images["foveated"]), compare(truth, images["uniform"])
    assert np.mean(fov.flip_map[centre]) <= np.mean(uni.flip_map[centre]) + 0.01
    assert fov.flip > uni.flip


def test_atlas_foveation_smooths_only_the_periphery(ctx):
    """The composer's foveated draw (server/atlas_fovea.frag.glsl): each view keeps its pixels near the gaze and is
    smoothed far from it, the view beside it untouched by its blur; the gaze moves the untouched region."""
    rng = np.random.default_rng(0)
    views = [rng.integers(0, 256, (H, W, 3), np.uint8) for _ in range(2)]
    cam = Camera.perspective(Pose([0, 0, 0]), W, H)
    point = OperatingPoint("f", fovea_deg=5, fovea_sigma_deg=5, fovea_max_scale=16, fovea_atlas=4)
    rects = [(0, 0, W, H), (W, 0, W, H)]
    layout = AtlasLayout(2 * W, H, rects[0], rects[1], (), (0, 0, 0, 0))
    textures = [ctx.texture((W, H), 4, np.ascontiguousarray(np.dstack([v, np.full((H, W), 255, np.uint8)])[::-1]))
                for v in views]

    def foveated(gaze):
        fov = AtlasFoveation([(r, cam) for r in rects], point, gaze)
        composer = AtlasComposer(ctx, layout)
        composer.clear()
        for tex, rect in zip(textures, rects):
            composer.draw_foveated(tex, rect, fov.levels, fov.uniforms(fov.cameras[rect]))
        return composer.read()[..., :3], fov

    for gaze in ((0.0, 0.0, -1.0), tuple(gaze_direction((15.0, 5.0)))):
        out, fov = foveated(gaze)
        assert fov.active and set(fov.cameras) == set(rects) and fov.levels == 2
        ecc = cam.eccentricity_deg(gaze)
        for x0, before in zip((0, W), views):
            view, before = out[:, x0:x0 + W].astype(float), before.astype(float)
            assert np.abs(view - before)[ecc <= 4].max() <= 1                  # the fovea kept
            # far out, the noise is smoothed away (4x coarser), from the view's own pixels only
            assert view[ecc > 40].std() < 0.5 * before[ecc > 40].std()
            assert abs(view[ecc > 40].mean() - before.mean()) < 8
    assert not AtlasFoveation([((0, 0, W, H), cam)], OperatingPoint("uniform")).active
    # a view entirely within the fovea is left as it is
    narrow = Camera.perspective(Pose([0, 0, 0]), W, H, 4.0)
    assert not AtlasFoveation([((0, 0, W, H), narrow)], point).active
    with pytest.raises(ValueError, match="camera for a"):
        AtlasFoveation([((0, 0, W // 2, H), cam)], point)


def test_eccentricity_is_the_angle_from_the_gaze():
    cam = Camera.perspective(Pose([0, 0, 0]), 64, 36, 60.0)
    e = cam.eccentricity_deg()
    assert e.shape == (36, 64) and e.min() < 1.5
    assert e[0, 32] == pytest.approx(30.0, abs=1.0)             # top edge: half the vertical field of view
    g = cam.eccentricity_deg(gaze=(0.0, np.tan(np.radians(20)), -1.0))
    assert np.unravel_index(np.argmin(g), g.shape)[0] < 18      # looking up: the gaze point moves up


def test_foveation_follows_the_gaze(courtyard_renderer):
    """With a gaze to the right, the right half of the view keeps more (smaller) quads than the left, and the other
    way round; the atlas foveation moves with it. The gaze comes as a session's decision carries it (the gaze the
    client's newest pose sent), at the decision's operating point."""
    point = OperatingPoint("f", fovea_deg=5, fovea_sigma_deg=4, fovea_max_scale=32, fovea_atlas=4)
    pose, t = walk_pose(1.0), 1.0
    counts = {}
    for side, x_deg in (("right", 20.0), ("left", -20.0)):
        server = QuasarServer(courtyard_renderer, QuasarSettings(width=W, height=H))
        payload = server.encode_decision(EncodeFrame(pose.position, pose.quat, t, False, 0.0, point,
                                                     gaze_deg=(x_deg, 0.0)))
        gaze = tuple(GazeTrace.parse(f"0 {x_deg} 0\n").direction_at(0.0))
        assert server.atlas_foveation.gaze == pytest.approx(gaze)
        assert server.s.visible.gaze == server.s.hidden.gaze == pytest.approx(gaze)
        (visible,) = _layers(payload, LayerKind.VISIBLE)
        x = visible.quads.x.astype(int) + (1 << visible.quads.size_log2.astype(int)) // 2
        counts[side] = (int((x >= W // 2).sum()), int((x < W // 2).sum()))
    assert counts["right"][0] > counts["left"][0] and counts["left"][1] > counts["right"][1]


def test_gaze_traces_parse_and_interpolate(tmp_path):
    g = GazeTrace.parse("# t x y\n0 0 0\n1000 10 -5\n", "g")
    assert g.angles_at(0.5) == pytest.approx([5.0, -2.5]) and g.angles_at(9.0) == pytest.approx([10.0, -5.0])
    d = g.direction_at(0.0)
    assert d == pytest.approx([0.0, 0.0, -1.0])
    d = g.direction_at(1.0)
    assert np.degrees(np.arctan2(d[0], -d[2])) == pytest.approx(10.0) and np.linalg.norm(d) == pytest.approx(1.0)
    for text, match in (("0 0\n", "three finite numbers"), ("0 0 0\n0 1 1\n", "does not follow"),
                        ("0 95 0\n", "within"), ("a b c\n", "expected numbers"), ("", "no gaze samples")):
        with pytest.raises(GazeTraceError, match=match):
            GazeTrace.parse(text, "g")
    with pytest.raises(GazeTraceError, match="nope"):
        GazeTrace.load(tmp_path / "nope")
