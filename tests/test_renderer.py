import numpy as np
import pytest

from quadcast.render.camera import Camera, Pose
from quadcast.render.renderer import DeferredRenderer
from quadcast.render.scene import scene_from_dict


@pytest.fixture(scope="module")
def plane_renderer(ctx):
    scene = scene_from_dict({"models": [{"primitive": "plane", "size": [40, 40], "rotation_deg": [90, 0, 0],
                                         "position": [0, 0, -4], "color": [0.6, 0.6, 0.6]}],
                             "sun": {"direction": [0, 0, -1]}})
    return DeferredRenderer(scene, ctx)


def test_plane_depth_matches_analytic(plane_renderer):
    """A wall at z = -4 seen from a camera at z = +1 pitched 20 degrees down: depth = 5 / cos(angle) along -Z."""
    pitch = -20.0
    cam = Camera.perspective(Pose.from_euler([0, 0, 1], pitch, 0), 160, 90, fovy_deg=60)
    frame = plane_renderer.render(cam)
    # Analytic: each pixel's ray hits the plane z=-4 at world distance t; view depth = t * (ray . forward).
    h, w = 90, 160
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    f = cam.frustum
    x_v = f.left + (f.right - f.left) * xs / w
    y_v = f.top - (f.top - f.bottom) * ys / h
    dirs_view = np.stack([x_v, y_v, -np.full_like(x_v, f.near)], -1)
    dirs_world = dirs_view @ cam.pose.rotation.as_matrix().T
    t = (-4.0 - 1.0) / dirs_world[..., 2]
    expected = t * f.near  # view depth of the hit: t * |ray's -z component| (= near)
    assert np.allclose(frame.depth, expected, rtol=2e-3)
    # The depth buffer agrees after linearisation.
    gb = plane_renderer.gbuffer(cam)
    assert np.allclose(f.linear_depth(gb.read_depth_buffer()), expected, rtol=1e-2)
    # View-space normal of the wall faces the camera: world +Z rotated into view space.
    n_expected = cam.pose.rotation.inv().apply([0, 0, 1])
    assert np.allclose(frame.normal.reshape(-1, 3).mean(0), n_expected, atol=2e-3)
    assert (frame.object_id == 1).all()


def test_a_surface_whose_normals_give_no_direction_faces_the_eye(ctx):
    """Vertex normals that are zero where the geometry pass draws (set after the scene's repair, as cancelling
    ones would be) give the G-buffer a normal facing the eye, not NaN: NaN normals made NaN quads, and the server
    failed every frame that saw them."""
    from quadcast.server.quasar import QuasarServer, QuasarSettings
    scene = scene_from_dict({"models": [{"primitive": "plane", "size": [40, 40], "rotation_deg": [90, 0, 0],
                                         "position": [0, 0, -4], "color": [0.6, 0.6, 0.6]}],
                             "sun": {"direction": [0, 0, -1]}})
    scene.objects[0].mesh.normals[:] = 0.0
    renderer = DeferredRenderer(scene, ctx)
    pose = Pose([0, 0, 1])
    frame = renderer.render(Camera.perspective(pose, 64, 36, fovy_deg=60))
    assert np.isfinite(frame.normal).all() and np.isfinite(frame.color).all()
    x, y = np.meshgrid(np.arange(64) + 0.5 - 32, 18 - (np.arange(36) + 0.5))
    rays = np.dstack([-x, -y, np.full_like(x, 18 / np.tan(np.radians(30)))])   # from the surface to the eye
    assert np.allclose(frame.normal, rays / np.linalg.norm(rays, axis=2, keepdims=True), atol=2e-3)
    server = QuasarServer(renderer, QuasarSettings(width=64, height=36))
    try:
        payload = server.encode(pose, 0.0)
    finally:
        server.close()
    assert payload.stats.quads > 0


def test_each_object_is_drawn_with_its_own_albedo_source(ctx):
    """The geometry pass draws an object with the program variant for where its albedo comes from (no texture,
    the texture at mesh UVs, triplanar): three walls with one base colour, the same half-red half-blue texture on
    the second (mesh UVs: red on the left) and third (triplanar at 0.2: the texture wraps, blue on the left); the
    untextured wall's albedo is its base colour."""
    from quadcast.render.renderer import read_texture
    walls = [{"primitive": "plane", "size": [2, 2], "rotation_deg": [90, 0, 0], "position": [x, 0, -4],
              "color": [0.6, 0.3, 0.2]} for x in (-2.5, 0.0, 2.5)]
    scene = scene_from_dict({"models": walls, "sun": {"direction": [0, 0, -1]}})
    texture = np.zeros((8, 8, 4), np.uint8)
    texture[..., 3] = 255
    texture[:, :4, 0] = texture[:, 4:, 2] = 255
    _, textured, triplanar = (o.mesh for o in scene.objects)
    textured.material.texture = triplanar.material.texture = texture
    textured.uvs = np.c_[textured.positions[:, 0] / 2 + 0.5, textured.positions[:, 2] / 2 + 0.5].astype(np.float32)
    triplanar.material.uv_mode, triplanar.material.uv_scale = "triplanar", 0.2
    renderer = DeferredRenderer(scene, ctx)
    assert [gm.albedo_source for gm in renderer.meshes] == [2, 0, 1]
    gb = renderer.gbuffer(Camera.perspective(Pose([0, 0, 0]), 96, 24, fovy_deg=30))
    albedo, ids = read_texture(gb.albedo, 4, "f2")[12, :, :3], read_texture(gb.object_id, 1, "i4")[12]
    red, blue = [0.6, 0, 0], [0, 0, 0.2]      # the texture's colours times the base colour; f16 targets
    plain = albedo[ids == 1].astype(np.float32)
    assert len(plain) > 10 and np.allclose(plain, [0.6, 0.3, 0.2], atol=1e-3)
    for k, (left, right) in ((2, (red, blue)), (3, (blue, red))):
        wall = albedo[ids == k].astype(np.float32)
        assert np.allclose(wall[1:5], left, atol=1e-3) and np.allclose(wall[-5:-1], right, atol=1e-3), k


def test_renderers_sharing_a_context_each_draw_their_own_materials(ctx):
    """The geometry pass writes an object's material, model and id uniforms only where they differ from what its
    program last got (`write_changed_uniforms`), and renderers on one context share those programs: two scenes of
    one wall each, of another colour and place (the second's wall is its second object, so another id), drawn in
    turn, each draw shows its own."""
    from quadcast.render.renderer import read_texture

    def wall(x, colour):
        return {"primitive": "plane", "size": [2, 2], "rotation_deg": [90, 0, 0], "position": [x, 0, -4],
                "color": colour}
    behind = {"primitive": "box", "extents": [1, 1, 1], "position": [0, 0, 20], "color": [1, 1, 1]}
    scenes = [{"models": [wall(-0.6, [0.6, 0.3, 0.2])]}, {"models": [behind, wall(0.6, [0.1, 0.2, 0.7])]}]
    renderers = [DeferredRenderer(scene_from_dict({**s, "sun": {"direction": [0, 0, -1]}}), ctx) for s in scenes]
    camera = Camera.perspective(Pose([0, 0, 0]), 64, 16, fovy_deg=30)
    for k, renderer in [*enumerate(renderers)] * 3:
        gb = renderer.gbuffer(camera)
        albedo, ids = read_texture(gb.albedo, 4, "f2")[8, :, :3], read_texture(gb.object_id, 1, "i4")[8]
        mine = renderer.scene.objects[-1]
        drawn = np.flatnonzero(ids > 0)
        assert len(drawn) > 10 and set(ids[drawn]) == {mine.object_id}
        assert np.allclose(albedo[drawn].astype(np.float32), mine.mesh.material.base_color[:3], atol=1e-3)
        assert (drawn.mean() < 32) == (k == 0)        # each wall where its own model matrix puts it


def test_point_lights_that_cannot_reach_the_view_are_left_out_without_changing_the_image(courtyard_renderer):
    """The lighting pass leaves out point lights whose sphere lies outside the view's frustum (`Frustum.sphere_outside`,
    checked here against points sampled inside the frustum): the same lit image as with every light, at views that
    leave some out and one that keeps them all."""
    from quadcast.render.camera import Frustum
    from quadcast.render.renderer import read_texture
    frustum = Frustum.symmetric(60, 16 / 9, 0.1, 40.0)
    rng = np.random.default_rng(5)
    l, r, b, t = frustum.unit_extents
    z = -rng.uniform(0.1, 40.0, 50_000)
    u, v = rng.uniform(size=(2, 50_000))
    inside = np.c_[(l + (r - l) * u) * -z, (b + (t - b) * v) * -z, z]
    verdicts = []
    for _ in range(400):
        centre, radius = rng.uniform([-40, -40, -50], [40, 40, 20]), rng.uniform(0.5, 8.0)
        outside = frustum.sphere_outside(centre, radius)
        assert not (outside and (np.linalg.norm(inside - centre, axis=1) < radius).any()), (centre, radius)
        verdicts.append(outside)
    assert 0 < sum(verdicts) < len(verdicts)
    lights = courtyard_renderer.scene.point_lights
    left_out = []
    # the last view has a light 3 m behind it: outside the frustum, but lighting the ground in front of the eye
    for pose in (Pose.look_at([0, 1.6, 9], [0, 1.6, 20]), Pose.look_at([6, 1.6, 6], [9, 1.6, 9]),
                 Pose.look_at([0, 1.6, 6], [0, 1.5, 0]), Pose.look_at([7, 1.6, 4], [7, 1.0, -4])):
        camera = Camera.perspective(pose, 96, 54)
        view = camera.view_matrix()
        left_out.append(sum(camera.frustum.sphere_outside((view @ np.r_[light.position, 1.0])[:3], light.radius)
                            for light in lights))
        gb = courtyard_renderer.gbuffer(camera, 0.0)
        culled = read_texture(gb.color, 4, "u1")
        courtyard_renderer.cull_lights = False
        try:
            courtyard_renderer.lighting_pass(gb, 0.0)
        finally:
            courtyard_renderer.cull_lights = True
        assert np.array_equal(read_texture(gb.color, 4, "u1"), culled), pose
    assert max(left_out) >= 2 and min(left_out) == 0, left_out


def test_sky_has_infinite_depth_and_id_zero(plane_renderer):
    cam = Camera.perspective(Pose([0, 0, 0], [0, 1, 0, 0]), 64, 36)  # looking away from the wall
    frame = plane_renderer.render(cam)
    assert np.isinf(frame.depth).all() and (frame.object_id == 0).all()
    assert frame.color.mean() > 100  # sky colour, not black


def test_geometry_pass_cull_draws_only_pixels_left_at_depth_one(ctx, plane_renderer):
    """`cull` writes depth 0 over the left half: those pixels stay cleared (lit as sky), the rest is drawn as
    without a cull step."""
    from quadcast.render.renderer import GBuffer
    cam = Camera.perspective(Pose([0, 0, 0]), 64, 36)
    full = plane_renderer.render(cam)
    gb = GBuffer(ctx, 64, 36)
    calls = []

    def cull(depth):
        calls.append(depth)
        fbo = ctx.framebuffer(depth_attachment=depth)
        fbo.use()
        fbo.scissor = (0, 0, 32, 36)
        fbo.clear(depth=0.0)
        fbo.scissor = None
        fbo.release()

    plane_renderer.geometry_pass(cam, 0.0, target=gb, cull=cull)
    plane_renderer.lighting_pass(gb, 0.0)
    assert calls == [gb.depth]
    culled = gb.read()
    assert (culled.object_id[:, :32] == 0).all() and np.isinf(culled.depth[:, :32]).all()
    assert np.array_equal(culled.object_id[:, 32:], full.object_id[:, 32:])
    assert np.array_equal(culled.color[:, 32:], full.color[:, 32:])
    sky = plane_renderer.render(Camera.perspective(Pose([0, 0, 0], [0, 1, 0, 0]), 64, 36)).color
    assert np.array_equal(culled.color[:, :32], sky[:, :32])  # culled pixels shade as sky
    gb.release()


def test_courtyard_frames_are_lit_textured_shadowed_and_deterministic(courtyard_renderer):
    from quadcast.render.traces import resolve_trace
    trace = resolve_trace("builtin:walk")
    p, q = trace.pose_at(2.0)
    cam = Camera.perspective(Pose(p, q), 320, 180)
    a = courtyard_renderer.render(cam, 2.0)
    b = courtyard_renderer.render(cam, 2.0)
    assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth)
    assert a.color.std() > 20                       # not blank
    assert len(np.unique(a.object_id)) > 5          # many objects in view
    floor = a.color[a.object_id == 1].astype(float)  # the ground: textured and partly shadowed
    lum = floor.mean(-1)
    assert lum.std() > 10
    assert np.percentile(lum, 90) > 1.6 * np.percentile(lum, 10)
    # Animation changes the picture over time at a fixed pose looking at the fountain's sculpture.
    fountain = Camera.perspective(Pose.look_at([0, 1.6, 6], [0, 2.2, 0]), 160, 90)
    c0, c1 = courtyard_renderer.render(fountain, 0.0), courtyard_renderer.render(fountain, 0.5)
    assert (np.abs(c0.color.astype(int) - c1.color.astype(int)).max(-1) > 30).mean() > 0.003


def test_lighting_geometry_only_shades_geometry_and_leaves_sky_black(courtyard_renderer):
    """`geometry_only` lighting (the server's hidden layers and wide view) gives the full pass's colour where there
    is geometry and black where there is none, also in a G-buffer that held a lit view before."""
    cam = Camera.perspective(Pose.look_at([0, 1.6, 6], [0, 3.0, 0]), 160, 90)
    full = courtyard_renderer.render(cam, 1.0)
    sky = np.isinf(full.depth)
    assert 0.05 < sky.mean() < 0.95
    gb = courtyard_renderer.gbuffer(cam, 1.0, geometry_only=True)
    got = gb.read_color()
    assert np.array_equal(got[~sky], full.color[~sky])
    assert not got[sky].any()
    assert np.isinf(gb.read_depth()).mean() == sky.mean()


def test_objects_outside_the_frustum_are_skipped_without_changing_the_image(courtyard_renderer, monkeypatch):
    """draw_geometry skips objects whose box is wholly outside the view: the frame is the same as drawing all."""
    cam = Camera.perspective(Pose.look_at([0, 1.6, 6], [0, 1.5, 0]), 160, 90)
    shown = courtyard_renderer.visible_objects(cam, 1.0)
    assert 0 < shown.sum() < len(shown)
    culled = courtyard_renderer.render(cam, 1.0)
    monkeypatch.setattr(courtyard_renderer, "visible_objects", lambda camera, t: np.ones(len(shown), bool))
    full = courtyard_renderer.render(cam, 1.0)
    assert np.array_equal(culled.color, full.color) and np.array_equal(culled.object_id, full.object_id)
    assert set(np.unique(full.object_id)) - {0} <= {o.object_id for o, s in
                                                     zip(courtyard_renderer.scene.objects, shown) if s}


def test_object_boxes_follow_the_animated_objects_from_time_to_time(courtyard_renderer):
    """The objects' model matrices and the frustum test's world boxes are kept per time: an animated object's are
    worked out again for every new t (a frame's passes share them), a static object's never change."""
    r = courtyard_renderer
    assert 0 < len(r._animated_objects) < len(r.scene.objects)
    for t in (1.0, 2.5, 2.5, 0.0, 1.0):
        want = np.stack([np.c_[gm.box_corners, np.ones(8)] @ o.model_matrix(t).T
                         for o, gm in zip(r.scene.objects, r.meshes)])
        placed = r._objects_at(t)
        np.testing.assert_array_equal(placed.boxes, want)
        for o, m in zip(r.scene.objects, placed.models):
            np.testing.assert_array_equal(m, o.model_matrix(t))

def _world_points(cam, depth):
    h, w = depth.shape
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    f = cam.frustum
    x_v = (f.left + (f.right - f.left) * xs / w) / f.near * depth
    y_v = (f.top - (f.top - f.bottom) * ys / h) / f.near * depth
    pv = np.stack([x_v, y_v, -depth], -1)
    return pv @ cam.pose.rotation.as_matrix().T + cam.pose.position


def test_disocclusion_after_half_metre_step(courtyard_renderer):
    """Depth complexity: after a 0.5 m sideways step, part of what is seen was hidden behind nearer surfaces."""
    pose = Pose.from_euler([0, 1.6, 6.0], -5, 0)
    cam_a = Camera.perspective(pose, 160, 90)
    cam_b = cam_a.with_pose(pose.offset_local([0.5, 0, 0]))
    a = courtyard_renderer.render(cam_a, 0.0)
    b = courtyard_renderer.render(cam_b, 0.0)
    finite = np.isfinite(b.depth)
    pts = _world_points(cam_b, np.where(finite, b.depth, 1.0))[finite]
    px = np.floor(cam_a.project(pts)).astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < 160) & (px[:, 1] >= 0) & (px[:, 1] < 90)
    depth_in_a = (pts[inside] - pose.position) @ pose.forward
    seen_depth = a.depth[px[inside, 1], px[inside, 0]]
    hidden = depth_in_a > seen_depth + 0.3
    assert hidden.mean() > 0.005


def _shadowed_pair(animated: bool) -> dict:
    """A floor and a box above it casting a shadow; the box slides along x when `animated`."""
    box = {"primitive": "box", "size": [1, 1, 1], "position": [0, 1.5, -4], "color": [0.8, 0.2, 0.2]}
    if animated:
        box["animation"] = {"type": "translate", "direction": [1, 0, 0], "amplitude": 2.0, "period_s": 4.0}
    return {"models": [{"primitive": "plane", "size": [20, 20], "position": [0, 0, -4], "color": [0.7, 0.7, 0.7]},
                       box],
            "sun": {"direction": [0.2, -1, 0.1], "shadow_extent": 10, "center": [0, 0, -4]}}


@pytest.mark.parametrize("animated", [False, True])
def test_shadow_map_follows_animated_casters_only(ctx, animated):
    """The shadow map is drawn once for a scene without animated casters; a frame at t = 1 after one at t = 0 must
    equal a fresh renderer's frame at t = 1 either way (and, when the caster moves, differ from t = 0)."""
    scene = scene_from_dict(_shadowed_pair(animated))
    cam = Camera.perspective(Pose.look_at([0, 4, 2], [0, 0, -4]), 160, 90)
    reused = DeferredRenderer(scene, ctx)
    first = reused.render_color(cam, 0.0)
    later = reused.render_color(cam, 1.0)
    fresh = DeferredRenderer(scene_from_dict(_shadowed_pair(animated)), ctx).render_color(cam, 1.0)
    assert np.array_equal(later, fresh)
    assert np.array_equal(first, later) != animated


def test_static_casters_depth_is_kept_and_copied_where_casters_move(ctx):
    """With animated casters the static ones' depth is drawn once and copied into the shadow map before the moving
    ones are drawn: at every time the same shadow map and picture as drawing every caster again."""
    scene = scene_from_dict(_shadowed_pair(True))
    cam = Camera.perspective(Pose.look_at([0, 4, 2], [0, 0, -4]), 160, 90)
    cached = DeferredRenderer(scene, ctx)
    drawn = DeferredRenderer(scene_from_dict(_shadowed_pair(True)), ctx, static_shadow_cache=False)
    assert cached._static_shadow is not None and drawn._static_shadow is None
    images = []
    for t in (0.0, 1.0, 2.5, 1.0):
        a, b = cached.render_color(cam, t), drawn.render_color(cam, t)
        assert cached.shadow_map.read() == drawn.shadow_map.read()
        assert np.array_equal(a, b)
        images.append(a)
    assert not np.array_equal(images[0], images[1])      # the box's shadow moved


def test_copy_texture_copies_depth_and_refuses_other_formats(ctx):
    """`copy_texture` copies a depth texture's values as they are, and names the mismatch when sizes or formats
    differ."""
    from quadcast.render.gl import copy_texture
    src, dst = ctx.depth_texture((8, 4)), ctx.depth_texture((8, 4))
    fbo = ctx.framebuffer(depth_attachment=src)
    fbo.use()
    fbo.clear(depth=0.25)
    copy_texture(ctx, src, dst)
    assert np.allclose(np.frombuffer(dst.read(), np.float32), 0.25, atol=1e-6)
    with pytest.raises(ValueError, match="same size and format"):
        copy_texture(ctx, src, ctx.depth_texture((4, 4)))
    with pytest.raises(ValueError, match="same size and format"):
        copy_texture(ctx, src, ctx.texture((8, 4), 1, dtype="f4"))
    big = ctx.depth_texture((16, 8))
    copy_texture(ctx, src, big, at=(8, 4))              # into the top-right quarter (GL's bottom-left origin)
    values = np.frombuffer(big.read(), np.float32).reshape(8, 16)
    assert np.allclose(values[4:, 8:], 0.25, atol=1e-6) and not np.allclose(values[:4], 0.25, atol=1e-6)
    with pytest.raises(ValueError, match="does not fit"):
        copy_texture(ctx, src, big, at=(9, 4))
    # a rectangle of the source, to the same place or to `at`
    other = ctx.depth_texture((16, 8))
    ofbo = ctx.framebuffer(depth_attachment=other)
    ofbo.clear(depth=1.0)
    copy_texture(ctx, big, other, rect=(6, 3, 4, 2))
    values = np.frombuffer(other.read(), np.float32).reshape(8, 16)
    assert np.allclose(values[4, 8:10], 0.25, atol=1e-6)         # the part of the rectangle in the quarter
    assert np.allclose(np.delete(values, np.s_[6:10], axis=1), 1.0)   # nothing outside the rectangle
    assert np.allclose(values[:3], 1.0) and np.allclose(values[5:], 1.0)
    copy_texture(ctx, src, other, rect=(0, 0, 2, 2), at=(14, 6))
    assert np.allclose(np.frombuffer(other.read(), np.float32).reshape(8, 16)[6:, 14:], 0.25, atol=1e-6)
    with pytest.raises(ValueError, match="not within"):
        copy_texture(ctx, src, other, rect=(7, 0, 2, 2))


@pytest.mark.parametrize("eye, target, shows", [
    ([0, 4, 2], [0, 0, -4], "all"),           # the box and its shadow in front
    ([1.2, 1.5, -3.0], [4, 0.5, -2.5], "part"),  # the box's path and shadow reach behind the camera
    ([3, 1.5, -4], [6, 1.5, -4], "none"),      # ... and lie wholly behind it
])
def test_moving_region_holds_every_pixel_that_changes_and_clips_what_lies_behind_the_camera(ctx, eye, target, shows):
    """Between two times, a full render changes only inside moving_region. Where the animated box's path or its
    shadow reaches behind the camera, the region is what lies in front of the near plane: less than the whole
    image, and nothing when all of it is behind."""
    r = DeferredRenderer(scene_from_dict(_shadowed_pair(True)), ctx)
    cam = Camera.perspective(Pose.look_at(eye, target), 160, 90)
    x, y, w, h = r.moving_region(cam, (0.0, 1.0))
    a, b = r.render(cam, 0.0), r.render(cam, 1.0)
    changed = (a.color != b.color).any(-1) | (a.object_id != b.object_id)
    inside = np.zeros_like(changed)
    inside[y:y + h, x:x + w] = True
    assert changed.any() == (shows != "none")
    assert not (changed & ~inside).any()
    if shows == "part":
        assert 0 < w * h < 160 * 90 * 0.8, (x, y, w, h)
    if shows == "none":
        assert w * h == 0


def test_lighting_by_depth_then_the_sky_pass_gives_the_one_pass_image(courtyard_renderer):
    """The lighting pass shades the pixels with geometry (picked by depth) and the sky pass the others: the same
    image, to the bit, as the one pass whose shader tells sky by position, which culled G-buffers still use."""
    r = courtyard_renderer
    cam = Camera.perspective(Pose.look_at([0, 1.6, 6], [0, 3.5, 0]), 160, 90)
    gb = r.geometry_pass(cam, 1.0)
    sky = ~(gb.read_depth() < np.inf)
    assert 0.05 < sky.mean() < 0.95
    r.lighting_pass(gb, 1.0)
    two_passes = gb.read_color()
    gb.culled = True
    r.lighting_pass(gb, 1.0)
    assert np.array_equal(gb.read_color(), two_passes)
    assert len(np.unique(two_passes[sky].reshape(-1, 3), axis=0)) > 1      # the sky's gradient, not one colour
