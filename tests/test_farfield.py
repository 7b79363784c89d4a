"""The far field (server/farfield.py): a continuous range surface per cube face, sent with reference frames and
drawn by the client behind everything, so that turning away from what was sent still shows content."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from quadcast.protocol.quads import LayerKind, QuadFrame, decode_quad_frame, encode_quad_frame
from quadcast.render.camera import Camera, Pose
from quadcast.server.farfield import face_cameras, range_grid_faces, range_grid_quads


def _corner_points(camera: Camera, quads) -> dict:
    """Every mesh vertex of the quads as render/quad.glsl makes it: {image point: view-space point}."""
    f = camera.frustum
    out: dict = {}

    def ray(px, py):
        r = np.array([f.left + (f.right - f.left) * px / camera.width,
                      f.top + (f.bottom - f.top) * py / camera.height, -f.near])
        return r / np.linalg.norm(r)
    offsets = quads.offsets.astype(np.float64).reshape(-1, 4, 4)
    for i in range(len(quads)):
        size = 1 << int(quads.size_log2[i])
        x0, y0, n = float(quads.x[i]), float(quads.y[i]), quads.normal[i].astype(np.float64)
        centre = ray(x0 + size / 2, y0 + size / 2)
        d = n @ (centre * (quads.depth[i] / -centre[2]))
        for s in range(4):
            for c in range(4):
                a, b = (s & 1) + (c & 1), (s >> 1) + (c >> 1)
                p = (x0 + a * size / 2, y0 + b * size / 2)
                r = ray(*p)
                t = d / min(n @ r, -1e-3) + offsets[i, s, c]
                out.setdefault(p, []).append(r * t)
    return out


def test_range_grid_is_one_continuous_surface_at_the_farthest_depth():
    cam = face_cameras((0.0, 1.6, 0.0), 64, 0.1, 100.0)[0]
    yy, xx = np.mgrid[0:64, 0:64]
    depth = np.where(xx < 20, 3.0, 30.0).astype(np.float32) + 0.01 * yy     # a near wall beside a far one
    depth[:8, 40:] = np.inf                                                 # and some sky
    quads = range_grid_quads(cam, depth, 16, max_depth=90.0)
    assert len(quads) == 16 and not quads.flattened.any()
    points = _corner_points(cam, quads)
    # shared corners coincide, up to the float16 rounding of the offsets (2^-11 of the largest, twice)
    tolerance = 2 * 2.0 ** -11 * float(np.abs(quads.offsets.astype(np.float64)).max()) + 1e-4
    for p, pts in points.items():
        spread = max(np.linalg.norm(q - pts[0]) for q in pts)
        assert spread < tolerance, f"the quads meeting at {p} disagree by {spread} m"
    # each grid corner lies at the farthest depth of the blocks around it (sky counts as max_depth)
    for (px, py), pts in points.items():
        if px % 16 or py % 16:
            continue
        i, j = int(px // 16), int(py // 16)
        window = depth[max(0, 16 * j - 16):16 * j + 16, max(0, 16 * i - 16):16 * i + 16]
        expect = min(90.0, float(np.max(np.where(np.isfinite(window), window, 90.0))))
        assert -pts[0][2] == pytest.approx(expect, abs=tolerance + 1e-3 * expect), (px, py)


def test_faces_worked_out_together_are_each_face_alone():
    """`range_grid_faces` (the six faces at once, as FarField.layers makes them) gives every face the very quads
    `range_grid_quads` gives it alone: batching shares the rays, never another face's depths."""
    cams = face_cameras((0.5, 1.6, -2.0), 32, 0.1, 100.0)
    rng = np.random.default_rng(3)
    depths = rng.uniform(0.5, 120.0, (6, 32, 32)).astype(np.float32)
    depths[2, :10] = np.inf                                                  # sky on one face
    depths[4] = 7.0                                                          # one flat face
    together = range_grid_faces(cams[0], depths, 16, 90.0)
    assert len(together) == 6
    for cam, depth, quads in zip(cams, depths, together):
        alone = range_grid_quads(cam, depth, 16, 90.0)
        for name in ("x", "y", "size_log2", "flattened", "alpha", "normal", "depth", "offsets"):
            assert np.array_equal(getattr(quads, name), getattr(alone, name)), name
    with pytest.raises(ValueError, match="whole number of 16-pixel blocks"):
        range_grid_faces(cams[0], depths[:, :30, :30], 16, 90.0)


def test_far_layers_round_trip_the_quad_blob():
    cams = face_cameras((1.0, 2.0, -3.0), 32, 0.1, 100.0)
    from quadcast.protocol.quads import QuadLayer
    layers = [QuadLayer(LayerKind.FAR, 32, 32, c.to_array(), (32 * i, 0, 32, 32),
                        range_grid_quads(c, np.full((32, 32), 10.0 + i, np.float32), 16, 90.0))
              for i, c in enumerate(cams)]
    frame = decode_quad_frame(encode_quad_frame(QuadFrame(layers)), size=(64, 36))
    assert [l.kind for l in frame.layers] == [LayerKind.FAR] * 6
    assert all(len(l.quads) == 4 for l in frame.layers)


def test_the_six_faces_cover_every_direction_once():
    cams = face_cameras((0.0, 0.0, 0.0), 8, 0.1, 100.0)
    dirs = Rotation.random(500, random_state=1).apply([0.0, 0.0, -1.0])
    for d in dirs:
        inside = 0
        for c in cams:
            v = c.view_matrix()[:3, :3] @ d
            if v[2] < 0 and abs(v[0] / -v[2]) <= 1 and abs(v[1] / -v[2]) <= 1:
                inside += 1
        assert inside >= 1


@pytest.mark.parametrize("yaw", [0.0, 100.0, 180.0])
def test_turning_away_from_what_was_sent_still_shows_the_far_field(courtyard_renderer, yaw):
    """A reference frame sent facing one way, shown facing another: with the far field no pixel stays black."""
    from quadcast.client.quasar import QuasarClient
    from quadcast.server.quasar import QuasarServer, QuasarSettings
    w, h = 192, 108
    sent = Pose([0.0, 1.6, 4.0])
    shown = Pose(sent.position, (Rotation.from_quat(sent.quat) * Rotation.from_euler("y", yaw, degrees=True)).as_quat())
    black = {}
    for far in (True, False):
        server = QuasarServer(courtyard_renderer, QuasarSettings(width=w, height=h, far_field=far))
        client = QuasarClient(w, h, ctx=courtyard_renderer.ctx)
        client.receive(server.encode(sent, 0.0))
        image = client.render(shown)
        black[far] = float((image.max(axis=2) == 0).mean())
        server.close()
    assert black[True] == 0.0, black
    if yaw >= 100:
        assert black[False] > 0.3, black          # without it, turning away shows nothing


def test_no_pixel_is_left_uncovered_where_cube_faces_meet(courtyard_renderer):
    """Looking up into the sky across the cube's vertical edges (yaw 45 degrees off a face) and its top edges: the
    far field alone covers every pixel -- its faces overlap, so no seam opens between them at any pose."""
    from quadcast.client.quasar import QuasarClient
    from quadcast.server.quasar import QuasarServer, QuasarSettings
    w, h = 160, 96
    server = QuasarServer(courtyard_renderer, QuasarSettings(width=w, height=h))
    client = QuasarClient(w, h, ctx=courtyard_renderer.ctx)
    client.receive(server.encode(Pose([0.0, 1.6, 4.0]), 0.0))
    uncovered = []
    for yaw in (45.0, 135.0, -45.0, -135.0):
        for pitch in (10.0, 30.0, 60.0):
            for dx, dz in ((0.5, 0.0), (-0.5, 0.0), (0.0, 0.5), (0.0, -0.5)):
                shown = Pose.from_euler([dx, 1.6, 4.0 + dz], pitch, yaw)
                client.render(shown)
                uncovered.append(int((~np.isfinite(client.view.read_depth())).sum()))
    server.close()
    assert sum(uncovered) == 0, uncovered


def test_a_far_field_of_coarse_meshes_draws_fewer_triangles_and_sees_the_same_surroundings(ctx):
    """`FarField(detail=0.1)` draws the scene's coarse meshes (a 20,480-triangle sphere as about a tenth of them,
    small meshes whole): its faces see the same range and colour as with every triangle, near enough for a
    background behind everything; the objects' boxes grow to hold both meshes."""
    from quadcast.render.renderer import DeferredRenderer
    from quadcast.render.scene import scene_from_dict
    from quadcast.server.farfield import FarField
    from quadcast.server.quasar import QuasarSettings
    scene = scene_from_dict({"models": [
        {"primitive": "sphere", "radius": 2.0, "position": [0, 1, -6], "color": [0.8, 0.3, 0.2]},
        {"primitive": "plane", "size": [40, 40], "color": [0.5, 0.6, 0.5]}], "sun": {"direction": [-0.3, -1, -0.2]}})
    sphere = scene.objects[0].mesh
    sphere_full = trimesh.creation.icosphere(subdivisions=5)
    scene.objects[0].mesh = type(sphere)("sphere", sphere_full.vertices * 2.0, sphere_full.vertex_normals,
                                         sphere_full.faces, sphere.material)
    renderer = DeferredRenderer(scene, ctx)
    with pytest.raises(ValueError, match="detail"):
        renderer.coarse_meshes(0.0)
    with pytest.raises(ValueError, match="far_detail must be in"):
        QuasarSettings(far_detail=1.5)
    assert renderer.coarse_meshes(1.0) is renderer.meshes
    full, coarse = FarField(renderer, 64, 16, 100.0), FarField(renderer, 64, 16, 100.0, detail=0.1)
    big, plane = renderer.coarse_meshes(0.1)
    assert 1500 < len(big._mesh.indices) < 2600 and plane is renderer.meshes[1]
    lo, hi = renderer.meshes[0].box_corners.min(0), renderer.meshes[0].box_corners.max(0)
    assert (big._mesh.positions >= lo - 1e-6).all() and (big._mesh.positions <= hi + 1e-6).all()
    seen = []
    for far in (full, coarse):
        far.draw_geometry([0.0, 1.6, 0.0], 0.0, 0.1, 100.0)
        far.light(0.0)
        seen.append((np.stack([gb.read_depth() for gb in far.gbuffers]),
                     np.stack([gb.read_color() for gb in far.gbuffers]).astype(float)))
    (z_full, c_full), (z_coarse, c_coarse) = seen
    hit = np.isfinite(z_full) & np.isfinite(z_coarse)
    assert (np.isfinite(z_full) == np.isfinite(z_coarse)).mean() > 0.99
    assert np.median(np.abs(z_coarse[hit] - z_full[hit]) / z_full[hit]) < 0.01
    assert np.abs(c_coarse - c_full).mean() < 3.0 and not np.array_equal(c_coarse, c_full)


def test_near_occluders_are_near_objects_drawn_on_a_far_surface():
    """A near object before the sky lies on the sky's surface (every block around it reaches the sky): seen from
    half a metre beside the centre its pixels would move 14 degrees against it. Sky, a wall, and an object just
    before a wall are not flagged; no offset or no angle flags nothing."""
    from quadcast.server.farfield import near_occluders
    depth = np.full((1, 64, 64), np.inf, np.float32)
    depth[0, 20:40, 20:44] = 2.0                                            # an object 2 m away, then sky
    flagged = near_occluders(depth, 16, 90.0, 0.5, 10.0)[0]
    assert flagged.shape == (64, 64)
    assert flagged[20:40, 20:44].all() and not flagged[np.isinf(depth[0])].any()
    wall = np.full((1, 64, 64), 7.0, np.float32)
    assert not near_occluders(wall, 16, 90.0, 0.5, 10.0).any()
    before_wall = wall.copy()
    before_wall[0, 20:40, 20:44] = 6.0                                       # 0.7 degrees against the wall
    assert not near_occluders(before_wall, 16, 90.0, 0.5, 10.0).any()
    assert not near_occluders(depth, 16, 90.0, 0.0, 10.0).any()
    assert not near_occluders(depth, 16, 90.0, 0.5, 0.0).any()
    assert not near_occluders(depth, 16, 90.0, 0.5, 30.0).any()             # 14 degrees is within 30
    assert near_occluders(depth, 16, 90.0, 1.5, 30.0)[0, 20:40, 20:44].all()   # 42 degrees from 1.5 m


def test_fill_from_nearest_takes_each_masked_pixel_from_the_nearest_other():
    from quadcast.server.farfield import fill_from_nearest
    image = np.zeros((4, 6, 3), np.uint8)
    image[:, :3] = (0, 0, 255)
    image[:, 3:] = (255, 0, 0)
    mask = np.zeros((4, 6), bool)
    mask[1:3, 2:4] = True                     # two columns: the left one nearest blue, the right one nearest red
    out = fill_from_nearest(image, mask)
    assert (out[1:3, 2] == (0, 0, 255)).all() and (out[1:3, 3] == (255, 0, 0)).all()
    assert np.array_equal(out[~mask], image[~mask])
    assert np.array_equal(fill_from_nearest(image, np.ones((4, 6), bool)), image)   # nothing to take from
    with pytest.raises(ValueError, match="mask"):
        fill_from_nearest(image, mask[:, :5])


def test_the_far_field_shows_no_ghost_of_a_near_object(ctx):
    """A red box 2 m before the server's eye, with sky behind it: its colour is in the far field's faces only
    without the occluder fill (`QuasarSettings.far_occluder_deg` 0), where an eye beside the centre would see it
    beside the box itself."""
    from quadcast.render.renderer import DeferredRenderer, read_texture
    from quadcast.render.scene import scene_from_dict
    from quadcast.server.quasar import QuasarServer, QuasarSettings
    scene = scene_from_dict({"models": [{"primitive": "box", "extents": [1, 1, 1], "position": [0, 1.6, -2.0],
                                         "color": [0.9, 0.05, 0.05]}], "sun": {"direction": [-0.3, -1, -0.2]}})
    renderer = DeferredRenderer(scene, ctx)
    red = {}
    for deg in (0.0, 10.0):
        server = QuasarServer(renderer, QuasarSettings(width=160, height=90, far_occluder_deg=deg))
        server.encode(Pose([0.0, 1.6, 0.0]), 0.0)
        faces = np.stack([read_texture(c, 4, "u1")[..., :3].astype(int) for c in server.far_field.colors])
        red[deg] = int(((faces[..., 0] - faces[..., 1] > 40) & (faces[..., 0] - faces[..., 2] > 40)).sum())
        assert server.far_field.occluded > 0 if deg else server.far_field.occluded == 0
        server.close()
    assert red[0.0] > 20 and red[10.0] == 0, red
    with pytest.raises(ValueError, match="far_occluder_deg"):
        QuasarSettings(far_occluder_deg=-1.0)
