"""Single-render stereo (client/stereo.py): YORO reprojection + Patcher, and mode 2 (re-render disocclusions).

The synthetic scene is fronto-parallel: a textured wall at z = -4 and a red box whose front face is at z = -1.7,
seen by a left eye at the origin looking down -Z. The eyes are 0.3 m apart so disparities are several pixels:
f * ipd / z = 5.85 px on the wall and 13.75 px on the box face at 160x90, 60 degrees vertical field of view.
"""
import numpy as np
import pytest
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from quadcast.client.stereo import StereoSynthesizer, benchmark_stereo, deferred_draw_fn
from quadcast.render.camera import Camera, Pose
from quadcast.render.renderer import DeferredRenderer
from quadcast.render.scene import DirectionalLight, Material, Mesh, Scene, SceneObject

W, H = 160, 90
IPD = 0.3
WALL_Z, FACE_Z = -4.0, -1.7
BOX_HALF = (0.5, 0.3)  # half width and half height of the box's front face (metres)
FOCAL = (H / 2) / np.tan(np.radians(30))  # pixels
D_WALL, D_FACE = FOCAL * IPD / -WALL_Z, FOCAL * IPD / -FACE_Z


def _quad(width, height, z, uv=True):
    """A rectangle in the plane z facing +Z."""
    w, h = width / 2, height / 2
    pos = np.array([[-w, -h, z], [w, -h, z], [w, h, z], [-w, h, z]], np.float32)
    uvs = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32) if uv else None
    return pos, np.tile([0, 0, 1], (4, 1)), np.array([[0, 1, 2], [0, 2, 3]]), uvs


def _box(half_x, half_y, half_z, z_center):
    import trimesh
    tm = trimesh.creation.box(extents=[2 * half_x, 2 * half_y, 2 * half_z])
    tm.apply_translation([0, 0, z_center])
    return tm


def _scene(near_object):
    """The textured wall and a red object (a trimesh) in front of it."""
    rng = np.random.default_rng(7)
    blocks = np.stack([rng.integers(10, 110, (32, 32)), rng.integers(90, 230, (32, 32)),
                       rng.integers(90, 230, (32, 32))], -1).astype(np.uint8)
    texture = np.kron(blocks, np.ones((8, 8, 1), np.uint8))  # 256x256, 8-texel blocks of random blue-greens
    pos, nrm, idx, uvs = _quad(12.0, 8.0, WALL_Z)
    wall = Mesh("wall", pos, nrm, idx, Material(texture=texture, specular=0.0), uvs)
    red = Mesh("red", near_object.vertices, near_object.vertex_normals, near_object.faces,
               Material(base_color=np.array([0.9, 0.05, 0.05, 1.0], np.float32), specular=0.0))
    sun = DirectionalLight(np.array([0.3, -0.4, -1.0]) / np.linalg.norm([0.3, -0.4, -1.0]), intensity=2.0)
    return Scene("stereo-test", [SceneObject(wall), SceneObject(red)], sun, ambient=np.array([0.3, 0.3, 0.3]))


def _is_red(img):
    return (img[..., 0].astype(int) - img[..., 1]) > 80


@pytest.fixture(scope="module")
def scene():
    return _scene(_box(BOX_HALF[0], BOX_HALF[1], 0.3, FACE_Z - 0.3))


@pytest.fixture(scope="module")
def renderer(ctx, scene):
    return DeferredRenderer(scene, ctx, shadow_size=512)


@pytest.fixture(scope="module")
def left_camera():
    return Camera.perspective(Pose([0.0, 0.0, 0.0]), W, H, fovy_deg=60)


@pytest.fixture(scope="module")
def synth(ctx):
    return StereoSynthesizer(ctx, W, H, ipd=IPD)


@pytest.fixture(scope="module")
def stereo(renderer, left_camera, synth):
    """Mode 1 on the synthetic scene: (left frame, synthesized, disocclusion mask, re-render mask, truth)."""
    gb = renderer.gbuffer(left_camera)
    left = gb.read()
    result = synth.synthesize_gbuffer(gb)
    out = result.read_color(), result.read_disocclusion(), result.read_rerender_mask()
    truth = renderer.render(result.camera)
    return left, *out, truth


def _psnr(a, b, where=None):
    d = a.astype(np.float64) - b
    d = d[where] if where is not None else d
    return 10 * np.log10(255.0 ** 2 / max(np.mean(d ** 2), 1e-12))


def _shift(a, b, rows, cols):
    """The x shift s (pixels, 0.05 steps) minimising |a(x) - b(x + s)| over rows x cols."""
    xs = np.arange(W, dtype=np.float64)
    best = (np.inf, 0.0)
    for s in np.arange(0.0, 16.0, 0.05):
        err = 0.0
        for y in rows:
            for c in range(3):
                shifted = np.interp(cols + s, xs, b[y, :, c].astype(np.float64))
                err += np.sum((a[y, cols, c].astype(np.float64) - shifted) ** 2)
        best = min(best, (err, s))
    return best[1]


WALL_ROWS = range(2, 24)  # above the box (box face spans rows ~31..59)
BOX_ROWS = slice(36, 54)


def test_wall_moves_by_the_analytic_disparity(stereo):
    left, synth_img, mask, _, truth = stereo
    cols = np.arange(10, 140)
    assert _shift(synth_img, left.color, WALL_ROWS, cols) == pytest.approx(D_WALL, abs=0.2)
    assert _shift(truth.color, left.color, WALL_ROWS, cols) == pytest.approx(D_WALL, abs=0.2)  # the test's own check
    region = np.zeros((H, W), bool)
    region[list(WALL_ROWS)] = True
    region &= ~mask
    assert region.sum() > 0.9 * len(WALL_ROWS) * (W - D_WALL - 1)
    assert _psnr(synth_img, truth.color, region) >= 30.0
    assert _psnr(left.color, truth.color, region) < 20.0  # the unshifted eye would not pass


def test_overlaps_keep_the_nearest_surface(stereo):
    _, synth_img, _, _, truth = stereo
    red = _is_red(synth_img)
    box = truth.object_id == 2
    inner = box & np.roll(box, 1, 1) & np.roll(box, -1, 1) & np.roll(box, 1, 0) & np.roll(box, -1, 0)
    assert inner.sum() > 300
    assert red[inner].mean() > 0.99  # where the wall's pixels also land, the box wins
    outer = ~(box | np.roll(box, 1, 1) | np.roll(box, -1, 1) | np.roll(box, 1, 0) | np.roll(box, -1, 0))
    assert red[outer].sum() == 0
    # the box in the right eye starts where the analytic disparity puts it
    cols = np.nonzero(red[45])[0]
    left_edge = (W / 2) + (-BOX_HALF[0] - IPD) / -FACE_Z * FOCAL
    assert abs(cols[0] - left_edge) <= 1.0


def test_disocclusion_lies_beside_the_box_and_is_as_wide_as_the_disparity_step(stereo, left_camera, synth):
    _, _, mask, _, _ = stereo
    right = synth.other_eye(left_camera)
    x_face = right.project([[BOX_HALF[0], 0.0, FACE_Z]])[0, 0]          # box's right edge in the right eye
    x_wall = right.project([[BOX_HALF[0] * WALL_Z / FACE_Z, 0.0, WALL_Z]])[0, 0]  # first wall point the left saw
    assert x_wall - x_face == pytest.approx(D_FACE - D_WALL, abs=1e-6)
    for y in range(BOX_ROWS.start, BOX_ROWS.stop):
        cols = np.nonzero(mask[y])[0]
        border = cols[cols >= W - np.ceil(D_WALL) - 1]   # the strip the left eye never saw at the frame's edge
        inner = cols[cols < W - np.ceil(D_WALL) - 1]
        assert len(border) == pytest.approx(D_WALL, abs=1.0) and border[-1] == W - 1
        assert len(inner) == pytest.approx(D_FACE - D_WALL, abs=1.0)
        assert np.all(np.diff(inner) == 1)                            # one run ...
        assert abs(inner[0] + 0.5 - x_face) <= 1.0                     # ... starting at the box's edge
    assert not mask[:BOX_ROWS.start - 8, :int(W - np.ceil(D_WALL) - 1)].any()  # no holes on the bare wall


def test_disocclusions_are_filled_from_the_background(stereo):
    _, synth_img, mask, _, truth = stereo
    band = mask.copy()
    band[:, int(W - np.ceil(D_WALL) - 1):] = False
    band[:BOX_ROWS.start] = band[BOX_ROWS.stop:] = False
    assert band.sum() > 100 and (truth.object_id[band] == 1).all()  # truly the wall there
    fill = synth_img[band].astype(np.float64)
    box_color = truth.color[truth.object_id == 2].astype(np.float64).mean(0)
    wall_color = truth.color[truth.object_id == 1].astype(np.float64).mean(0)
    assert ((fill[:, 0] - fill[:, 1]) < 30).all()                           # no red box smeared in
    assert np.linalg.norm(fill - wall_color, axis=1).max() < np.linalg.norm(fill - box_color, axis=1).min()
    # a nearest-wall-pixel fill: close to the truth on average even though the texture there was never seen
    assert np.abs(fill - truth.color[band]).mean() < 40


def test_patcher_skips_foreground_in_neighbouring_rows(ctx, left_camera):
    """Beside a sphere the silhouette is slanted: the kernel's rows above and below reach into the sphere."""
    import trimesh
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.45)
    sphere.apply_translation([0.0, 0.0, -2.0])
    r = DeferredRenderer(_scene(sphere), ctx, shadow_size=512)
    synth = StereoSynthesizer(ctx, W, H, ipd=IPD)
    result = synth.synthesize_gbuffer(r.gbuffer(left_camera))
    img, mask = result.read_color(), result.read_disocclusion()
    truth = r.render(result.camera)
    band = mask & (np.arange(W) < W - np.ceil(D_WALL) - 1) & (truth.object_id == 1)  # wall behind the sphere
    synth.release()
    assert band.sum() > 80
    assert not _is_red(img)[band].any()
    assert ((img[band][:, 0].astype(int) - img[band][:, 1]) < 30).all()


def _gl_rows(a):
    """A top-row-first numpy image as the bytes of a GL texture (bottom row first)."""
    return np.ascontiguousarray(a[::-1]).tobytes()


def test_scan_resolves_overlaps_nearest_first_and_records_disocclusions(ctx):
    """Algorithm 2 on a hand-made row: background (depth 4) shifts 1 px left, source pixels 6..9 are a
    foreground (depth 1) shifting 4 px left, so it overlaps the background on its left and opens a 3 px hole on
    its right; the frame's last pixel is unseen."""
    s = StereoSynthesizer(ctx, 16, 1)
    x = np.arange(16, dtype=np.float32)
    fg = (x >= 6) & (x <= 9)
    targets = np.stack([np.where(fg, x - 4, x - 1), np.where(fg, 1.0, 4.0)], -1).astype("f4")[None]
    s.targets.write(_gl_rows(targets))
    s.scan()
    im = s.read_imbuffer()[0]
    covered = im[:, 2] == 0
    assert covered.tolist() == [True] * 6 + [False] * 3 + [True] * 6 + [False]
    source = (np.arange(16) + im[:, 0] * 16)[covered]  # where each covered target pixel comes from
    assert np.allclose(source, [1, 2, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15])  # 2..5: the foreground won
    assert np.allclose(im[covered, 1], [4, 4, 1, 1, 1, 1, 4, 4, 4, 4, 4, 4])
    assert np.allclose(im[6:9], [[6, 4, 3, 9]] * 3)   # left edge 6, background depth 4, width 3, from pixel 9
    assert np.allclose(im[15], [15, 4, 1, 14])         # the frame edge: only the left side to fill from
    s.release()


def test_scan_bridges_a_stretched_surface(ctx):
    """A surface seen more obliquely by the other eye lands 1.5 px apart per pixel: the pixels between are
    covered by sub-pixel source positions, not holes."""
    s = StereoSynthesizer(ctx, 16, 1)
    x = np.arange(16, dtype=np.float32)
    s.targets.write(_gl_rows(np.stack([1.5 * x, 3.0 + 0.01 * x], -1).astype("f4")[None]))
    s.scan()
    im = s.read_imbuffer()[0]
    assert (im[:, 2] == 0).all()
    assert np.allclose(np.arange(16) + im[:, 0] * 16, np.arange(16) / 1.5, atol=1e-4)
    s.release()


def test_patcher_fills_from_background_and_skips_foreground(ctx):
    """Algorithm 3 on a hand-made ImBuffer: a 3 px hole in the middle row whose background neighbour (right) has
    foreground in the rows above and below; the fill must be pure background."""
    s = StereoSynthesizer(ctx, 16, 3)
    x = np.arange(16)
    fg_cols = np.stack([x <= 9, x <= 4, x <= 9])  # (3, 16): foreground in the source and ImBuffer
    im = np.zeros((3, 16, 4), np.float32)
    im[..., 1] = np.where(fg_cols, 1.0, 4.0)
    im[1, 5:8] = [5, 4, 3, 8]
    s.write_imbuffer(im)
    assert np.array_equal(s.read_imbuffer(), im)              # covered texels and the hole's records, as written
    with pytest.raises(ValueError, match="write_imbuffer"):
        s.write_imbuffer(im[:, :8])
    color = np.where(fg_cols[..., None], [255, 0, 0, 255], [0, 0, 255, 255]).astype(np.uint8)
    color[1, 5:8] = [0, 255, 0, 255]  # never to be used
    depth = np.where(fg_cols, 1.0, 4.0).astype("f4")
    ctex = ctx.texture((16, 3), 4, _gl_rows(color))
    dtex = ctx.texture((16, 3), 1, _gl_rows(depth), dtype="f4")
    result = s.patch(ctex, dtex, Camera.perspective(Pose([0, 0, 0]), 16, 3))
    out = result.read_color()
    assert (out[1, 5:8] == [0, 0, 255]).all()                  # background only
    assert (out[fg_cols] == [255, 0, 0]).all() and (out[~fg_cols & (x[None] >= 8)] == [0, 0, 255]).all()
    assert result.read_disocclusion().sum() == 3 and result.read_disocclusion()[1, 5:8].all()
    ctex.release(), dtex.release(), s.release()


def test_mode2_rerenders_only_the_masked_pixels(renderer, synth, stereo):
    _, synth_img, mask, redo, truth = stereo
    assert (redo >= mask).all() and redo.sum() > mask.sum()  # conservative filter adds the box's edges
    draw = deferred_draw_fn(renderer, 0.0)
    merged = synth.rerender_disoccluded(draw).read_color()
    assert np.array_equal(merged[redo], truth.color[redo])       # re-rendered pixels are the real right eye
    assert np.array_equal(merged[~redo], synth_img[~redo])       # the rest is the reprojection
    shaded = draw.gbuffer.read_object_id() != 0
    assert not shaded[~redo].any()                                # culled: no geometry where not needed
    assert shaded[redo].mean() > 0.99
    assert _psnr(merged, truth.color) > _psnr(synth_img, truth.color)


def test_yoro_without_the_edge_reject_makes_the_same_eye(renderer, left_camera, synth, stereo):
    """edge_mask=False (mode 1) runs the Patcher built without the conservative edge reject: the same colour and
    disocclusions, no re-render mask."""
    _, synth_img, mask, redo, _ = stereo
    assert redo.any()
    result = synth.synthesize_gbuffer(renderer.gbuffer(left_camera), edge_mask=False)
    assert np.array_equal(result.read_color(), synth_img)
    assert np.array_equal(result.read_disocclusion(), mask)
    assert np.array_equal(result.read_rerender_mask(), mask)


def test_linear_depth_input_matches_position_input(ctx, renderer, left_camera, synth, stereo):
    _, synth_img, mask, _, _ = stereo
    gb = renderer.gbuffer(left_camera)
    depth = gb.read_depth()[::-1].copy()  # GL rows, bottom first; inf where nothing was hit
    tex = ctx.texture((W, H), 1, depth.astype("f4").tobytes(), dtype="f4")
    result = synth.synthesize(gb.color, tex, left_camera)
    assert np.abs(result.read_color().astype(int) - synth_img).max() <= 1
    assert np.array_equal(result.read_disocclusion(), mask)
    tex.release()


def test_right_dominant_eye_and_coarse_imbuffer(ctx, renderer, left_camera):
    right_cam = left_camera.with_pose(left_camera.pose.offset_local([IPD, 0, 0]))
    gb = renderer.gbuffer(right_cam)
    for scale, min_psnr in ((1.0, 30.0), (0.5, 27.0)):
        s = StereoSynthesizer(ctx, W, H, ipd=IPD, intermediate_scale=scale, dominant="right")
        assert s.intermediate_width == int(W * scale)
        result = s.synthesize_gbuffer(gb)
        img, mask = result.read_color(), result.read_disocclusion()
        assert np.allclose(result.camera.pose.position, [0, 0, 0])
        truth = renderer.render(left_camera)
        region = np.zeros((H, W), bool)
        region[list(WALL_ROWS)] = True
        assert mask[list(WALL_ROWS), :int(D_WALL) - 1].all()  # now the left edge is unseen
        assert _psnr(img, truth.color, region & ~mask) >= min_psnr
        gb = renderer.gbuffer(right_cam)
        s.release()


def test_courtyard_quality_and_mode2_no_worse(courtyard_renderer):
    from quadcast.render.traces import resolve_trace
    p, q = resolve_trace("builtin:walk").pose_at(10.0)
    bench = benchmark_stereo(courtyard_renderer, Camera.perspective(Pose(p, q), W, H), 10.0, repeats=1)
    ssim1 = structural_similarity(bench.synthesized, bench.truth, channel_axis=-1)
    ssim2 = structural_similarity(bench.rerendered, bench.truth, channel_axis=-1)
    ssim0 = structural_similarity(bench.left, bench.truth, channel_axis=-1)
    assert ssim1 >= 0.8 and ssim1 > ssim0 + 0.1
    assert ssim2 >= ssim1
    assert peak_signal_noise_ratio(bench.truth, bench.rerendered) >= peak_signal_noise_ratio(bench.truth,
                                                                                             bench.synthesized)
    assert 0 < bench.disoccluded_fraction <= bench.rerender_fraction < 0.2
    assert bench.synthesize_ms > 0 and bench.render_ms > 0 and bench.rerender_ms > 0


@pytest.mark.parametrize("width", [W, W - 13])
def test_fused_row_pass_makes_what_the_three_stages_make(ctx, courtyard_renderer, width):
    """A full-resolution ImBuffer runs the fused row pass (Algorithms 1-3 in one row sweep, then the hole pass,
    which finds the disocclusions' runs; the colour interpolation's same-surface test from the row pass's bits):
    colour, masks and ImBuffer (with the disocclusions' records) equal to running `reproject`, `scan` and `patch`
    one after another, with and without the edge reject, on courtyard views with disocclusions and sky; also at a
    width that is not a multiple of the bits' 32-pixel words."""
    from quadcast.render.traces import resolve_trace
    trace = resolve_trace("builtin:walk")
    s = StereoSynthesizer(ctx, width, H, ipd=0.063)
    assert s.row_cs is not None and StereoSynthesizer(ctx, width, H, intermediate_scale=0.5).row_cs is None
    for t in (2.0, 10.0):
        camera = Camera.perspective(Pose(*trace.pose_at(t)), width, H)
        gb = courtyard_renderer.gbuffer(camera, t)
        for edges in (False, True):
            fused = s.synthesize_gbuffer(gb, edge_mask=edges)
            color, masks, imbuffer = fused.read_color().copy(), fused.read_masks(), s.read_imbuffer().copy()
            assert masks[0].any() and (masks[1].sum() > masks[0].sum()) == edges
            s.reproject(gb.position, camera)
            s.scan()
            staged = s.patch(gb.color, gb.position, camera, edges)
            assert np.array_equal(staged.read_color(), color)
            assert all(np.array_equal(a, b) for a, b in zip(staged.read_masks(), masks))
            assert np.array_equal(s.read_imbuffer(), imbuffer)
    s.release()


def test_bad_inputs_are_named(ctx, renderer, left_camera, synth):
    gb = renderer.gbuffer(left_camera)
    with pytest.raises(ValueError, match="intermediate_scale"):
        StereoSynthesizer(ctx, W, H, intermediate_scale=0.0)
    with pytest.raises(ValueError, match="dominant"):
        StereoSynthesizer(ctx, W, H, dominant="middle")
    with pytest.raises(ValueError, match="depth must be"):
        synth.synthesize(gb.color, gb.depth, left_camera)        # the depth buffer, not linear depth
    with pytest.raises(ValueError, match="color must be"):
        synth.synthesize(gb.position, gb.position, left_camera)
    with pytest.raises(ValueError, match="camera is 80x45"):
        synth.synthesize(gb.color, gb.position, Camera.perspective(Pose([0, 0, 0]), 80, 45))
    small = ctx.texture((80, 45), 4, dtype="f4")
    with pytest.raises(ValueError, match="depth texture is 80x45"):
        synth.synthesize(gb.color, small, left_camera)
    with pytest.raises(ValueError, match="expected a depth texture"):
        synth.cull(small)
    small.release()
    fresh = StereoSynthesizer(ctx, W, H)
    with pytest.raises(ValueError, match="synthesize first"):
        fresh.rerender_disoccluded(deferred_draw_fn(renderer))
    fresh.release()
