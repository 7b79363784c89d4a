"""Holes (client.method.Coverage): every method client says what its last render covered, the hole metric counts
a known uncovered region exactly, and views with zero quads, only sky or an object without ground work for every
method (they used to crash quasar and quadstream: moderngl cannot map an empty buffer range)."""
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from quadcast.client.baselines import ATWClient, MeshWarpClient
from quadcast.client.method import Coverage, PixelCoverage
from quadcast.client.quasar import QuasarClient
from quadcast.codec.encoder import AtlasEncoder
from quadcast.methods import make_client, make_server
from quadcast.protocol.frame import FramePayload, FrameType, Method
from quadcast.protocol.methods import METHODS, MethodConfig
from quadcast.protocol.quads import LayerKind, QuadFrame, QuadLayer, QuadSet, encode_quad_frame
from quadcast.render.camera import Camera, Pose
from quadcast.render.renderer import DeferredRenderer
from quadcast.render.scene import load_scene
from quadcast.server.baselines import ATWServer, MeshWarpServer
from quadcast.server.quads import QuadGenerator, QuadParams

W, H = 64, 32
LOOK_DOWN_Z = Pose([0.0, 1.6, 0.0])                                   # inside the courtyard's fountain bowl
SKY = Pose([0.0, 60.0, 0.0], Rotation.from_euler("x", 90, degrees=True).as_quat())   # straight up, high above


def test_coverage_figures_and_validation():
    drawn = np.zeros((4, 5), bool)
    drawn[1:3, 1:4] = True
    smeared = np.zeros((4, 5), bool)
    smeared[0] = True
    c = Coverage.from_masks(drawn, smeared)
    assert c.hole_pixels == 20 - 6 and c.holes == pytest.approx(14 / 20)
    assert c.empty_fraction == pytest.approx(9 / 20) and c.smeared_fraction == pytest.approx(5 / 20)
    assert c.figures() == {"holes": c.holes, "holes_empty": c.empty_fraction, "holes_smeared": c.smeared_fraction,
                           "holes_interior": 0.0}
    # A crack inside the view (not touching the border) vs the border region.
    inner = np.ones((6, 7), bool)
    inner[2:4, 3] = False           # a 2-pixel crack
    inner[:, 0] = False             # a border strip
    assert Coverage.from_masks(inner).interior_fraction == pytest.approx(2 / 42)
    assert Coverage.from_masks(np.ones((3, 3), bool)).interior_fraction == 0.0
    assert (c.hole_mask == ~drawn).all()
    assert Coverage.empty(5, 4).holes == 1.0
    for bad in (np.zeros((4, 5), np.float32), np.zeros(5, np.uint8), np.full((2, 2), 3, np.uint8)):
        with pytest.raises(ValueError, match="Coverage.pixels"):
            Coverage(bad)


def test_quasar_holes_count_the_pixels_no_quad_covers_exactly(ctx):
    """One 16x16 quad in a 64x32 view, seen from its own pose: exactly 64*32 - 256 pixels are holes."""
    camera = Camera.perspective(Pose([1.0, 1.5, 2.0]), W, H)
    quads = QuadSet(x=[16], y=[8], size_log2=[4], flattened=[True], alpha=[False], normal=[[0.0, 0.0, 1.0]],
                    depth=[5.0], offsets=np.zeros((0, 16)))
    layer = QuadLayer(LayerKind.VISIBLE, W, H, camera.to_array(), (0, 0, W, H), quads)
    encoder = AtlasEncoder(W, H)
    video = encoder.encode(np.full((H, W, 3), 200, np.uint8), keyframe=True)
    encoder.close()
    payload = FramePayload(Method.QUASAR, 0, FrameType.REFERENCE, 0, 0.0, camera.pose.position, camera.pose.quat,
                           video.data, encode_quad_frame(QuadFrame([layer])), self_contained=True)
    client = QuasarClient(W, H, ctx=ctx)
    assert client.coverage().holes == 1.0                  # nothing rendered yet
    client.render(camera.pose)
    assert client.coverage().holes == 1.0                  # before the first payload: black, all holes
    client.receive(payload)
    image = client.render(camera.pose)
    away = Pose([1.0, 1.5, 2.0], Rotation.from_euler("y", 90, degrees=True).as_quat())   # the quad out of view
    client.stereo_frame(away)                              # draws into the view `coverage` reads
    c = client.coverage()
    assert c.hole_pixels == W * H - 16 * 16
    expected = np.ones((H, W), bool)
    expected[8:24, 16:32] = False
    assert (c.hole_mask == expected).all() and c.empty_fraction == c.holes and c.interior_fraction == 0
    assert (image[~expected] > 150).all() and (image[expected] == 0).all()
    client.render(away)
    assert client.coverage().holes == 1.0


@pytest.mark.parametrize("kind", ["atw", "meshwarp"])
def test_baseline_holes_are_what_lies_outside_the_frame_exactly(courtyard_renderer, ctx, kind):
    """The server renders half the display's field of view (tan), so its frame covers exactly the central
    32x16 pixels; outside, ATW smears edge pixels: holes = 3/4, all smeared."""
    server_fovy = 2 * math.degrees(math.atan(math.tan(math.radians(30.0)) / 2))
    pose = Pose([0.0, 1.6, 6.0])
    if kind == "atw":
        server, client = ATWServer(courtyard_renderer, W, H, server_fovy), ATWClient(W, H, 60.0, server_fovy, ctx)
    else:
        server = MeshWarpServer(courtyard_renderer, W, H, server_fovy)
        client = MeshWarpClient(W, H, 60.0, server_fovy, ctx)
    client.receive(server.encode(pose, 0.0))
    client.render(pose)
    c = client.coverage()
    expected = np.ones((H, W), bool)
    expected[8:24, 16:48] = False
    assert (c.hole_mask == expected).all()
    assert c.hole_pixels == W * H - 32 * 16 and c.smeared_fraction == c.holes and c.empty_fraction == 0
    # Turned right by 10 degrees, the frame's content moves left on the display.
    client.render(Pose(pose.position, Rotation.from_euler("y", -10, degrees=True).as_quat()))
    columns = np.nonzero(~client.coverage().hole_mask.all(axis=0))[0]        # those showing some content
    assert columns.min() < 16 and columns.max() < 47
    server.close()
    client.close()


def test_zero_quads_give_an_empty_quadset(courtyard_renderer, ctx):
    """A sky-only G-buffer with sky quads off gathers nothing: an empty QuadSet, not a failed buffer read."""
    camera = Camera.perspective(SKY, W, H)
    gb = courtyard_renderer.gbuffer(camera, 0.0)
    quads, _ = QuadGenerator(ctx, W, H).generate(gb.position, gb.normal, camera, QuadParams(sky=False))
    assert len(quads) == 0 and quads.offsets.shape == (0, 16)


@pytest.fixture(scope="module")
def object_renderer(tmp_path_factory, ctx):
    """A glTF object without ground, made here with trimesh: a box on a column, floating in the sky."""
    path = tmp_path_factory.mktemp("gltf") / "object.glb"
    trimesh.util.concatenate([trimesh.creation.box(extents=[1.0, 1.0, 1.0]).apply_translation([0, 1.5, 0]),
                              trimesh.creation.cylinder(radius=0.2, height=1.0).apply_translation([0, 0.5, 0])]
                             ).export(path)
    scene = load_scene(path)
    return DeferredRenderer(scene, ctx), Pose(scene.spawn.position)


def _views(courtyard_renderer, object_renderer):
    renderer, spawn = object_renderer
    return {"zero quads (inside the fountain)": (courtyard_renderer, LOOK_DOWN_Z),
            "sky only": (courtyard_renderer, SKY), "glTF object without ground": (renderer, spawn)}


@pytest.mark.parametrize("method", METHODS)
def test_every_method_encodes_and_shows_empty_sky_and_groundless_views(courtyard_renderer, object_renderer, ctx,
                                                                       method):
    cfg = MethodConfig(width=W, height=H)
    for name, (renderer, pose) in _views(courtyard_renderer, object_renderer).items():
        server, client = make_server(method, renderer, cfg), make_client(method, cfg, ctx)
        turned = Pose(pose.position, (pose.rotation * Rotation.from_euler("y", 5, degrees=True)).as_quat())
        for k, p in enumerate((pose, turned, turned)):       # quasar: a reference, then residual frames
            client.receive(server.encode(p, k / 30))
            image = client.render(p)
            assert image.shape == (H, W, 3), name
            c = client.coverage()
            assert c.pixels.shape == (H, W) and 0.0 <= c.holes <= 1.0, name
        if name == "sky only":
            # The sky is content: every method shows it where its frame reaches.
            assert c.holes < 0.5, (method, c.holes)
        server.close()
        client.close()


def test_pixel_coverage_values_are_the_shader_alpha_levels():
    """client/baselines.py reads alpha 1 as DRAWN, 0.5 as SMEARED and 0 as EMPTY; the enum keeps that order."""
    assert [int(v) for v in PixelCoverage] == [0, 1, 2]
