"""Warm-ups (issue 14, live): a spare session worker runs a few small frames of every method served before any
session claims it, and the live client receives and draws made-up frames before it connects, so that llvmpipe has
compiled the shaders before a real frame needs them."""
from __future__ import annotations

import asyncio
import math

import numpy as np

from quadcast.methods import make_server
from quadcast.protocol.frame import decode_frame_payload
from quadcast.protocol.session import EncodeFrame
from quadcast.render import quadmesh
from quadcast.render.camera import Pose
from quadcast.render.scene import load_scene
from quadcast.render.gl import WARM_UP_SIZE
from quadcast.render.worker import ProcessWorker
from quadcast.server.app import PipelineSpec, SessionHost, warm_up_path
from quadcast.server.quadstream import QuadStreamServer, QuadStreamSettings
from quadcast.server.quasar import QuasarServer, QuasarSettings


def test_warm_up_path_walks_forward_from_the_spawn_point_turning_left(courtyard):
    spawn = courtyard.spawn
    path = warm_up_path(courtyard, frames=3, dt=0.1)
    assert [t for _, t in path] == [0.0, 0.1, 0.2]
    np.testing.assert_allclose(path[0][0].position, spawn.position)
    yaw = math.radians(spawn.yaw_deg)
    forward = np.array([-math.sin(yaw), 0.0, -math.cos(yaw)])     # yaw 0 looks down -Z, positive turns left
    steps = [float(np.dot(b.position - a.position, forward)) for (a, _), (b, _) in zip(path, path[1:])]
    assert all(s > 0.1 for s in steps)
    angles = [a.angle_to_deg(b) for (a, _), (b, _) in zip(path, path[1:])]
    np.testing.assert_allclose(angles, 4.0, atol=1e-6)


def test_warm_ups_of_the_mesh_methods_find_runs_in_their_small_layers(courtyard_renderer, monkeypatch):
    """At the warm-up's size no layer reaches QuadMesh's run threshold, so without lowering it the warm-up would
    leave the runs' five passes for a session's first frames to compile."""
    merged = []
    original = quadmesh.QuadMesh._merge_runs
    monkeypatch.setattr(quadmesh.QuadMesh, "_merge_runs",
                        lambda self, layer, buf, edit=None: (merged.append(len(layer.quads)),
                                                             original(self, layer, buf, edit))[1])
    w, h = WARM_UP_SIZE
    path = warm_up_path(courtyard_renderer.scene)
    for server in (QuasarServer(courtyard_renderer, QuasarSettings(width=w, height=h)),
                   QuadStreamServer(courtyard_renderer, QuadStreamSettings(width=w, height=h))):
        merged.clear()
        try:
            server.warm_up(path)
        finally:
            server.close()
        assert merged and max(merged) < quadmesh.MIN_RUN_QUADS, type(server).__name__


def test_a_quasar_warm_up_also_draws_a_foveated_atlas_at_its_own_crf(courtyard_renderer, monkeypatch):
    """A session whose point foveates the atlas (`--point ...,atlas=N`, the ladder's fov* points) would otherwise
    compile server/atlas_fovea.frag.glsl on its first frame: the warm-up makes its last frame again at a foveated
    point, without restarting the video stream (the same CRF)."""
    from quadcast.server import layers
    drawn = []
    original = layers.AtlasComposer.draw_foveated
    monkeypatch.setattr(layers.AtlasComposer, "draw_foveated",
                        lambda self, color, rect, levels, uniforms: (drawn.append(tuple(rect)),
                                                                     original(self, color, rect, levels, uniforms))[1])
    w, h = WARM_UP_SIZE
    server = QuasarServer(courtyard_renderer, QuasarSettings(width=w, height=h))
    encoder = server.encoder
    try:
        server.warm_up(warm_up_path(courtyard_renderer.scene))
        assert drawn, "no view of the warm-up's atlas was foveated"
        assert server.encoder is encoder and server.point.foveated and server.point.crf == server.s.video.crf
        assert server.frame_id == len(warm_up_path(courtyard_renderer.scene)) + 1
    finally:
        server.close()


def test_a_spare_worker_warms_up_every_method_served_then_serves_a_session():
    """The real worker process: booted with warm-up pipelines, it reports their times, then builds a session's
    pipeline of another size and encodes its frames."""
    def spec(method, w, h):
        return PipelineSpec(make_server, "builtin:courtyard", method, w, h, 60.0, 0.5, 5, None)

    async def run():
        warm = (spec("quasar", *WARM_UP_SIZE), spec("atw", *WARM_UP_SIZE))
        worker = ProcessWorker(SessionHost, ("builtin:courtyard", warm), "warm-up-test")
        try:
            await worker.start(120.0)
            times = await worker.call("warm_up_times")
            await worker.call("build", spec("quasar", 96, 54))
            frames = []
            for pose, t in warm_up_path(load_scene("builtin:courtyard"), frames=2):
                data, _ = await worker.call("encode", EncodeFrame(pose.position, pose.quat, t, False, 0.0))
                frames.append(decode_frame_payload(data))
            return times, frames
        finally:
            worker.close()

    times, frames = asyncio.run(run())
    assert set(times) == {"quasar", "atw"} and all(ms > 0 for ms in times.values())
    assert [f.frame_id for f in frames] == [0, 1]       # the session's own numbering: the warm-up left nothing
    assert frames[0].self_contained


def test_a_client_warm_up_runs_its_draws_and_edits_then_leaves_the_client_as_it_was(ctx, courtyard_renderer,
                                                                                     monkeypatch):
    """QuasarClient.warm_up receives and draws made-up frames on a throwaway client on the same context: the cache's
    edit (quads freed), the runs in its small layers and the current view's colour all run; the client itself is
    still waiting for its first frame, and then takes a real one."""
    from quadcast.client.quasar import QuasarClient
    calls = {"runs": 0, "freed": 0, "current": 0}
    merge, edit, current = (quadmesh.QuadMesh._merge_runs, quadmesh.QuadMesh._edit,
                            quadmesh.QuadMesh.set_current_view)

    def spy_merge(self, layer, buf, e=None):
        calls["runs"] += 1
        return merge(self, layer, buf, e)

    def spy_edit(self, layer, buf, atlas_size):
        calls["freed"] += layer.edit.kept is not None and not layer.edit.kept.all()
        return edit(self, layer, buf, atlas_size)

    def spy_current(self, camera, atlas_rect=None):
        calls["current"] += camera is not None
        return current(self, camera, atlas_rect)

    monkeypatch.setattr(quadmesh.QuadMesh, "_merge_runs", spy_merge)
    monkeypatch.setattr(quadmesh.QuadMesh, "_edit", spy_edit)
    monkeypatch.setattr(quadmesh.QuadMesh, "set_current_view", spy_current)
    client = QuasarClient(96, 54, ctx=ctx)
    try:
        client.warm_up()
        assert calls["runs"] >= 2 and calls["freed"] >= 1 and calls["current"] >= 1, calls
        assert client.atlas is None and client.needs_reference and client.last_frame_id == -1
        assert not client.render(Pose(np.zeros(3))).any()                       # black before a payload
        server = QuasarServer(courtyard_renderer, QuasarSettings(width=96, height=54))
        try:
            pose, t = warm_up_path(courtyard_renderer.scene, frames=1)[0]
            client.receive(server.encode(pose, t))
        finally:
            server.close()
        assert client.last_frame_id == 0 and client.render(pose).any()
    finally:
        client.close()


def test_a_stereo_client_warm_up_runs_both_yoro_row_passes_at_its_own_size(ctx, monkeypatch):
    """With `stereo`, the warm-up also makes the client's MeshStereo (YORO's row pass is compiled for the display
    width) and runs its synthesis with and without the edge reject; the first stereo frame uses that one."""
    from quadcast.client.quasar import QuasarClient
    from quadcast.client.stereo import StereoSynthesizer
    ran = []
    synthesize = StereoSynthesizer.synthesize

    def spy(self, color, depth, camera, edge_mask=True):
        ran.append((self.width, self.height, edge_mask))
        return synthesize(self, color, depth, camera, edge_mask)

    monkeypatch.setattr(StereoSynthesizer, "synthesize", spy)
    plain, stereo = QuasarClient(96, 54, ctx=ctx), QuasarClient(96, 54, ctx=ctx)
    try:
        plain.warm_up()
        assert plain._stereo is None and ran == []
        stereo.warm_up(stereo=True)
        assert sorted(ran) == [(96, 54, False), (96, 54, True)]
        made = stereo._stereo
        frame = stereo.stereo_frame(Pose(np.zeros(3)), "yoro")
        assert stereo._stereo is made and not frame.left.any()               # the same one; black before a payload
    finally:
        plain.close()
        stereo.close()


def test_baseline_client_warm_ups_draw_a_made_up_frame_and_leave_the_client_as_it_was(ctx, courtyard_renderer,
                                                                                    monkeypatch):
    """ATW and MeshWarp (60 and 120 degrees) clients receive and draw one made-up frame on a throwaway client of their
    kind at WARM_UP_SIZE (MeshWarp's with its depth, drawn as its mesh); the client itself still waits for its first
    frame, then takes a real one."""
    from quadcast.client.baselines import ATWClient, MeshWarpClient
    from quadcast.methods import make_client
    from quadcast.protocol.methods import MethodConfig
    drawn = []
    for cls in (ATWClient, MeshWarpClient):
        def spy(self, pose, draw=cls._draw):
            drawn.append((self.name, self.width, self.height, getattr(self, "_depth_tex", None) is not None))
            return draw(self, pose)
        monkeypatch.setattr(cls, "_draw", spy)
    pose, t = warm_up_path(courtyard_renderer.scene, frames=1)[0]
    config = MethodConfig(width=96, height=54)
    for name in ("atw", "meshwarp", "meshwarp120"):
        drawn.clear()
        client = make_client(name, config, ctx)
        try:
            client.warm_up()
            assert drawn == [(client.name, *WARM_UP_SIZE, name != "atw")]
            assert client.frame is None and client.needs_reference and not client.render(pose).any()
            server = make_server(name, courtyard_renderer, config)
            try:
                client.receive(server.encode(pose, t))
            finally:
                server.close()
            assert client.render(pose).any()
        finally:
            client.close()


def test_a_warmed_up_worker_sends_what_a_cold_one_sends(ctx):
    """The warm-up's renderer is kept for the session's pipeline (same context, so the compiled shaders are there):
    what the session sends is byte for byte what a worker without a warm-up sends."""
    def spec(w, h):
        return PipelineSpec(make_server, "builtin:courtyard", "quasar", w, h, 60.0, 0.5, 5, None)

    sent = []
    for warm_up in ((), (spec(*WARM_UP_SIZE),)):
        host = SessionHost("builtin:courtyard", warm_up)
        try:
            assert (host.renderer is None) == (not warm_up)
            host.build(spec(96, 54))
            sent.append([host.encode(EncodeFrame(pose.position, pose.quat, t, False, 0.0))[0]
                         for pose, t in warm_up_path(host.scene, frames=4, dt=0.2)])
        finally:
            host.close()
    assert sent[0] == sent[1]


def test_a_live_client_whose_warm_up_fails_goes_on_without_it(tmp_path, caplog):
    """The client's warm-up is only a head start (and its made-up frames need x264, which a client otherwise does
    not): if it fails, the client logs why and connects all the same; without --no-warm-up it is run."""
    import types

    from quadcast.client.app import ClientConfig, LiveClient
    from quadcast.client.method import MethodClient

    warmed = []

    class Failing(MethodClient):
        name = "quasar"

        def receive(self, payload):
            pass

        def render(self, pose):
            return np.zeros((2, 2, 3), np.uint8)

        def coverage(self):
            raise NotImplementedError

        def warm_up(self, stereo=False):
            warmed.append(stereo)
            raise RuntimeError("no encoder here")

    for warm_up in (True, False):
        client = LiveClient(ClientConfig(host="127.0.0.1", port=1, out=str(tmp_path), warm_up=warm_up),
                            lambda method, config, ctx: Failing())
        client.worker = types.SimpleNamespace(ctx=None)
        with caplog.at_level("WARNING", logger="quadcast.client"):
            client._setup()
    assert warmed == [False]                                             # not a --stereo client
    assert "warm-up failed, going on without it: RuntimeError: no encoder here" in caplog.text
