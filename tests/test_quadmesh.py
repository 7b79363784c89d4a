"""The layered quad mesh: a cache layer edited in place after residual updates draws what a fresh build draws;
rows of quads on one surface are drawn as one rectangle each, the same image."""
from __future__ import annotations

import moderngl
import numpy as np
import pytest

from quadcast.protocol.quads import OFFSETS_PER_QUAD, QuadSet
from quadcast.render.camera import Camera, Pose
from quadcast.render.quadcache import QuadCache
from quadcast.render.quadmesh import RUN_PARALLAX_M, MeshLayer, MeshView, QuadMesh


def camera_facing_quads(rng, n, width, height, max_size_log2):
    """Random quads of a width x height layer whose planes face the camera (drawable from nearby poses)."""
    flat = rng.random(n) < 0.7
    normal = np.column_stack([rng.normal(scale=0.3, size=(n, 2)), np.ones(n)])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return QuadSet(x=rng.integers(0, width, n), y=rng.integers(0, height, n),
                   size_log2=rng.integers(0, max_size_log2 + 1, n), flattened=flat, alpha=np.zeros(n, bool),
                   normal=normal, depth=rng.uniform(1.0, 8.0, n),
                   offsets=rng.normal(scale=0.05, size=(int((~flat).sum()), OFFSETS_PER_QUAD)))


def plane_quads(camera: Camera, blocks: list[tuple[int, int, int]], normal, offset: float) -> QuadSet:
    """Flattened quads (x, y, size_log2) on the plane dot(normal, X) = offset of `camera`'s view space."""
    x, y, s = (np.array(c) for c in zip(*blocks))
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    ray = camera.image_rays(x + 0.5 * (1 << s), y + 0.5 * (1 << s))
    depth = -ray[:, 2] * offset / (ray @ n)      # view depth where the centre ray meets the plane
    return QuadSet(x=x, y=y, size_log2=s, flattened=np.ones(len(x), bool), alpha=np.zeros(len(x), bool),
                   normal=np.tile(n, (len(x), 1)), depth=depth, offsets=np.zeros((0, OFFSETS_PER_QUAD)))


def planar_quads(rng, n, width, height, max_size_log2):
    """n random aligned 4x4 blocks, each tiled by quads of one size (1, 2 or 4 pixels, at most 2**max_size_log2),
    on one of two planes facing the camera (mostly by side of the image): rows of them form runs."""
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), width, height)
    planes = {True: [], False: []}
    for _ in range(n):
        bx, by = int(rng.integers(0, width // 4)) * 4, int(rng.integers(0, height // 4)) * 4
        k = int(rng.integers(0, min(max_size_log2, 2) + 1))
        first = (bx < width // 2) != (rng.random() < 0.1)
        planes[first] += [(bx + i, by + j, k) for j in range(0, 4, 1 << k) for i in range(0, 4, 1 << k)]
    sets = [plane_quads(camera, planes[first], normal, offset)
            for first, normal, offset in ((True, (0.2, 0.1, 1.0), -4.0), (False, (-0.3, 0.0, 1.0), -3.0))
            if planes[first]]
    return QuadSet.concatenate(sets)


def live_triangles(mesh: QuadMesh) -> list[np.ndarray]:
    """Per layer, the (T, 3, 5) vertex data (position, uv) of the triangles drawn, in draw order (empty ones
    dropped)."""
    out = []
    for _, buf in mesh.layers:
        idx = np.frombuffer(buf.index_buf.read(size=4 * buf.indices), np.uint32).reshape(-1, 3)
        idx = idx[~((idx[:, 0] == idx[:, 1]) & (idx[:, 1] == idx[:, 2]))]
        vertices = np.frombuffer(buf.vertex_buf.read(size=20 * (int(idx.max()) + 1)), np.float32).reshape(-1, 5)
        out.append(vertices[idx])
    return out


@pytest.mark.parametrize("runs", [False, True], ids=["quad by quad", "runs"])
def test_cache_mesh_edited_after_updates_equals_a_fresh_build(ctx, runs):
    """Residual updates append quads and free others; the edited mesh (new vertices at the end, freed quads'
    triangles emptied, rebuilt once dead vertices outnumber live ones) holds the same triangles in the same order
    as a mesh built from scratch, and draws the same image. With runs (quads on two planes, every layer merged),
    an edit redoes only the rows it touched, and the runs are those of a fresh build all the same."""
    rng = np.random.default_rng(7)
    make_quads = planar_quads if runs else camera_facing_quads
    min_run_quads = 0 if runs else None
    w, h = 64, 36
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), w, h)
    eye = Camera.perspective(Pose.look_at([0.3, 0.1, 0.2], [0.0, 0.0, -4.0]), w, h)
    rect = (0, 0, w, h)
    atlas = ctx.texture((w, h), 4, rng.integers(0, 256, (h, w, 4), dtype=np.uint8).tobytes())
    view = MeshView(ctx, w, h)
    cache = QuadCache(w, h)
    cache.reset(make_quads(rng, 900, w, h, 2))
    edited = QuadMesh(ctx)
    edited.min_run_quads = min_run_quads
    builds = {"fresh": 0, "edit": 0}
    for name in builds:
        method = getattr(edited, "_generate" if name == "fresh" else "_edit")

        def counted(*args, method=method, name=name):
            out = method(*args)
            builds[name] += out is not False
            return out
        setattr(edited, "_generate" if name == "fresh" else "_edit", counted)
    edited.build([MeshLayer(cache.quads, camera, rect, edit=cache.edit)], (w, h))
    freed = 0
    for step in range(24):
        freed += cache.update(make_quads(rng, int(rng.integers(1, 40)), w, h, 3))
        edited.build([MeshLayer(cache.quads, camera, rect, edit=cache.edit)], (w, h))
        (_, buf), = edited.layers
        assert 2 * buf.dead <= buf.end, "dead vertices outnumber live ones"
        fresh = QuadMesh(ctx)
        fresh.min_run_quads = min_run_quads
        fresh.build([MeshLayer(cache.quads, camera, rect)], (w, h))
        for a, b in zip(live_triangles(edited), live_triangles(fresh), strict=True):
            np.testing.assert_array_equal(a, b)
            merged_away = int(buf.count.sum()) // 2 - len(a)   # a quad's triangles: half its vertices
            assert merged_away > 100 if runs else merged_away == 0
        view.render(edited, eye, atlas)
        image_edited = view.read_color()
        view.render(fresh, eye, atlas)
        np.testing.assert_array_equal(image_edited, view.read_color())
    assert freed > 0 and builds["edit"] > 0


@pytest.mark.parametrize("min_run_quads", [None, 0], ids=["quad by quad", "runs"])
def test_first_residual_frame_after_a_reference_is_an_edit(ctx, monkeypatch, min_run_quads):
    """The buffers a reference frame's build makes leave room for the next frames' quads: a residual frame's few
    new quads, the first after it, are appended in place, not a rebuild of the layer."""
    w, h = 64, 36
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), w, h)
    cache = QuadCache(w, h)
    cache.reset(plane_quads(camera, [(x, y, 0) for y in range(h) for x in range(w)], (0.0, 0.0, 1.0), -4.0))
    mesh = QuadMesh(ctx)
    mesh.min_run_quads = min_run_quads
    mesh.build([MeshLayer(cache.quads, camera, (0, 0, w, h), edit=cache.edit)], (w, h))
    generated = []
    generate = mesh._generate
    monkeypatch.setattr(mesh, "_generate", lambda *args: generated.append(1) or generate(*args))
    assert cache.update(plane_quads(camera, [(8, 8, 1), (20, 4, 1)], (0.1, 0.0, 1.0), -3.0)) == 8
    mesh.build([MeshLayer(cache.quads, camera, (0, 0, w, h), edit=cache.edit)], (w, h))
    assert not generated
    (_, buf), = mesh.layers
    assert buf.dead == 8 * 4       # the 8 quads the two new ones cover
    fresh = QuadMesh(ctx)
    fresh.min_run_quads = min_run_quads
    fresh.build([MeshLayer(cache.quads, camera, (0, 0, w, h))], (w, h))
    (edited,), (built,) = live_triangles(mesh), live_triangles(fresh)
    np.testing.assert_array_equal(edited, built)
    assert len(edited) == 2 * (w * h - 6) if min_run_quads is None else len(edited) < 100   # runs: rectangles


def test_a_layer_kept_from_the_last_build_is_not_rebuilt_wherever_it_stands(ctx, monkeypatch):
    """A client's far field stays from its reference frame while the fill-in layers before it in the list come and
    go: a layer whose quads the last build already holds keeps its buffers, wherever it stood, and the mesh draws
    what a fresh build of the same layers draws."""
    w, h = 32, 18
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), w, h)
    rng = np.random.default_rng(7)
    near, far = (camera_facing_quads(rng, n, w, h, 2) for n in (40, 60))
    kept = MeshLayer(far, camera, (w, 0, w, h), 2.0)
    mesh = QuadMesh(ctx)
    mesh.build([MeshLayer(near, camera, (0, 0, w, h)), kept], (2 * w, h))
    (_, far_buffers), = [(l, b) for l, b in mesh.layers if l is kept]
    generated = []
    generate = mesh._generate
    monkeypatch.setattr(mesh, "_generate", lambda layer, *args: generated.append(layer) or generate(layer, *args))
    fill_ins = [MeshLayer(camera_facing_quads(rng, 30, w, h, 1), camera, (0, 0, w, h)) for _ in range(2)]
    for layers in ([*fill_ins, kept], [kept], [fill_ins[0], kept]):
        generated.clear()
        mesh.build(layers, (2 * w, h))
        assert kept not in generated and [b for l, b in mesh.layers if l is kept] == [far_buffers]
        assert [l for l, _ in mesh.layers] == layers
        fresh = QuadMesh(ctx)
        fresh.build(layers, (2 * w, h))
        drawn, built = live_triangles(mesh), live_triangles(fresh)
        assert len(drawn) == len(built) == len(layers)
        for a, b in zip(drawn, built):
            np.testing.assert_array_equal(a, b)


def test_quads_on_one_surface_draw_as_rectangles(ctx):
    """With the strict test (planes and normals, no parallax bound), 1-pixel quads on two planes (x < 40 and
    x >= 40) in a 64 x 8 layer are drawn as five rectangles: rows end where the surface changes and at every 16th
    pixel, the 8 rows of each stack into one. The view from a nearby pose has the same depths and colours as the
    quads drawn one by one (the merged layer drawn from its packed indices)."""
    rng = np.random.default_rng(5)
    w, h = 64, 8
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), w, h)
    eye = Camera.perspective(Pose.look_at([0.25, 0.1, 0.3], [0.0, 0.0, -4.0]), 4 * w, 4 * h)
    planes = (((0, 40), (0.2, 0.1, 1.0), -4.0), ((40, 64), (-0.3, 0.0, 1.0), -3.0))
    quads = QuadSet.concatenate([plane_quads(camera, [(x, y, 0) for y in range(h) for x in range(*xs)], n, d)
                                 for xs, n, d in planes])
    atlas = ctx.texture((w, h), 4, rng.integers(0, 256, (h, w, 4), dtype=np.uint8).tobytes())
    view = MeshView(ctx, 4 * w, 4 * h)
    images = {}
    for min_run_quads in (None, 0):
        mesh = QuadMesh(ctx)
        mesh.min_run_quads, mesh.run_parallax_px = min_run_quads, 0.0
        mesh.build([MeshLayer(quads, camera, (0, 0, w, h))], (w, h))
        view.render(mesh, eye, atlas)
        images[min_run_quads] = live_triangles(mesh)[0], (view.read_color(), view.read_depth())
        (_, buf), = mesh.layers   # built from scratch, with runs: drawn from the live triangles' indices, packed
        assert buf.packed_indices == (None if min_run_quads is None else 3 * len(images[min_run_quads][0]))
    (by_quad, (colour, depth)), (runs, (run_colour, run_depth)) = images[None], images[0]
    assert len(by_quad) == 2 * w * h and len(runs) == 2 * 5
    assert np.isfinite(depth).mean() > 0.7
    np.testing.assert_allclose(run_depth, depth, rtol=1e-4)
    assert (run_colour == colour).all(axis=-1).mean() > 0.995


def rippled_quads(rng, camera: Camera, amplitude: float, frequency: float) -> QuadSet:
    """A flattened 1-pixel quad per pixel of `camera` on the wall z = -4 + amplitude * sin(frequency * x) (view
    space, x in metres), each through the wall's point on its centre ray, its normal the wall's turned by about
    5 degrees at random (as a detailed scene's are, pixel to pixel); where x > 0.8 the wall steps 0.5 m nearer."""
    w, h = camera.width, camera.height
    y, x = (c.ravel() for c in np.mgrid[0:h, 0:w])
    ray = camera.image_rays(x + 0.5, y + 0.5)
    z = np.full(len(x), -4.0)
    for _ in range(30):   # where the centre ray meets the wall: fixed-point iteration on z
        wx = ray[:, 0] / -ray[:, 2] * -z
        z = -4.0 + amplitude * np.sin(frequency * wx) + np.where(wx > 0.8, 0.5, 0.0)
    slope = amplitude * frequency * np.cos(frequency * wx)       # dz/dx of the wall
    normal = np.column_stack([-slope, np.zeros(len(x)), np.ones(len(x))])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    normal += rng.normal(scale=np.radians(5.0) / np.sqrt(3), size=normal.shape)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return QuadSet(x=x, y=y, size_log2=np.zeros(len(x), int), flattened=np.ones(len(x), bool),
                   alpha=np.zeros(len(x), bool), normal=normal, depth=-z, offsets=np.zeros((0, OFFSETS_PER_QUAD)))


@pytest.mark.parametrize("amplitude, frequency", [(0.002, 4.0), (0.1, 8.0)],
                         ids=["bumps below the bound", "curves beyond it"])
def test_runs_within_the_parallax_bound(ctx, amplitude, frequency):
    """With the parallax bound (the default), 1-pixel quads on a wall whose normals turn from pixel to pixel (which
    the strict test seldom merges) are drawn as far fewer triangles, yet every pixel's depth at the layer's own
    pose lies so close to the quads' own that, seen from RUN_PARALLAX_M beside it, it moves at most about
    run_parallax_px pixels: a rectangle that would break that bound (on the curving wall) is drawn as rows or
    quads, and the 0.5 m step is never bridged."""
    w, h = 160, 90
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), w, h)
    quads = rippled_quads(np.random.default_rng(11), camera, amplitude, frequency)
    view = MeshView(ctx, w, h, depth_only=True)
    drawn = {}
    for bound in (None, 0.0, 0.5):
        mesh = QuadMesh(ctx)
        mesh.min_run_quads, mesh.run_parallax_px = (None, 0.0) if bound is None else (0, bound)
        mesh.build([MeshLayer(quads, camera, (0, 0, w, h))], (w, h))
        view.render(mesh, camera)
        drawn[bound] = len(live_triangles(mesh)[0]), view.read_depth()
    (_, truth), (strict, _), (bounded, depth) = drawn[None], drawn[0.0], drawn[0.5]
    assert np.isfinite(truth).all() and np.isfinite(depth).all()
    moved = min(camera.focal_px) * RUN_PARALLAX_M * np.abs(depth - truth) / truth ** 2
    assert moved.max() <= 0.5 * 1.01
    assert bounded < strict / (10 if amplitude < 0.01 else 1.5)
    assert (np.abs(depth - truth) < 0.25).all()     # the step (0.5 m) stays a step


def test_depth_only_view_gives_the_colour_views_depths(ctx):
    """The server's depth-only MeshView (no atlas, no colour) writes exactly the view depth a colour view writes,
    and each kind of view refuses the other's call."""
    rng = np.random.default_rng(3)
    w, h = 64, 36
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), w, h)
    eye = Camera.perspective(Pose.look_at([-0.2, 0.1, 0.1], [0.0, 0.0, -4.0]), w, h)
    cache = QuadCache(w, h)
    cache.reset(camera_facing_quads(rng, 900, w, h, 2))
    mesh = QuadMesh(ctx)
    mesh.build([MeshLayer(cache.quads, camera, (0, 0, w, h))], (w, h))
    atlas = ctx.texture((w, h), 4, rng.integers(0, 256, (h, w, 4), dtype=np.uint8).tobytes())
    # the colour view without its crack fill, which the depth-only view has not
    colour, depth_only = MeshView(ctx, w, h, crack_fill=False), MeshView(ctx, w, h, depth_only=True)
    colour.render(mesh, eye, atlas)
    depth_only.render(mesh, eye)
    expected = colour.read_depth()
    assert np.isfinite(expected).mean() > 0.5
    np.testing.assert_array_equal(depth_only.read_depth(), expected)
    with pytest.raises(ValueError, match="depth-only"):
        depth_only.render(mesh, eye, atlas)
    with pytest.raises(ValueError, match="needs one"):
        colour.render(mesh, eye)
    with pytest.raises(ValueError, match="no colour"):
        depth_only.read_color()


def test_a_layer_samples_only_its_own_atlas_rect(ctx):
    """A quad at the edge of its layer's rect, magnified: bilinear filtering never reaches the atlas pixels around
    the rect (another layer's), only the rect's own."""
    quad = QuadSet(x=[0], y=[0], size_log2=[4], flattened=[True], alpha=[False], normal=[[0.0, 0.0, 1.0]],
                   depth=[2.0], offsets=np.zeros((0, 16)))
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), 16, 16)
    atlas_img = np.zeros((32, 32, 4), np.uint8)
    atlas_img[..., 1] = 255                                   # green around the rect
    atlas_img[4:20, 8:24] = (255, 0, 0, 255)                  # the layer's rect: x 8, y 4, 16 x 16, red
    atlas = ctx.texture((32, 32), 4, atlas_img.tobytes())
    atlas.filter = (moderngl.LINEAR, moderngl.LINEAR)
    mesh = QuadMesh(ctx)
    mesh.build([MeshLayer(quad, camera, (8, 4, 16, 16))], (32, 32))
    view = MeshView(ctx, 128, 128)                            # the same view, 8x magnified
    view.render(mesh, Camera.perspective(Pose([0.0, 0.0, 0.0]), 128, 128), atlas)
    image, drawn = view.read_color(), view.read_drawn()
    assert drawn.mean() > 0.95
    assert image[drawn][:, 1].max() == 0, "green from outside the rect was filtered in"
    assert image[drawn][:, 0].min() == 255


CURRENT_WEIGHT = 0.3   # the current view's share in a cached layer's colour (render/quad_mesh_refresh_fragment.glsl)


def test_cached_layer_takes_the_current_views_colour_where_that_view_saw_the_surface(ctx):
    """A cached layer (a grey wall 4 m in front of the reference view) seen after a residual frame whose own view
    (elsewhere) saw the wall in nearly the same colours, a gradient of its pixel coordinates, and a revealed green
    quad 2 m in front of it hiding the wall's left part. Where the current view saw the wall the pixel mixes in
    CURRENT_WEIGHT of its colour, sampled where the wall lies in the current view; where the occluder hid it (the
    colours disagree), and with no current view, the cached colour alone."""
    w, h = 64, 36
    reference = Camera.perspective(Pose([0.0, 0.0, 0.0]), w, h)
    current = Camera.perspective(Pose.look_at([0.3, 0.1, 0.0], [0.0, 0.0, -4.0]), w, h)
    eye = Camera.perspective(Pose.look_at([-0.2, 0.0, -3.0], [0.0, 0.0, -4.0]), w, h)   # beyond the occluder
    blocks = [(x, y, 2) for y in range(0, h, 4) for x in range(0, w, 4)]
    wall = plane_quads(reference, blocks, (0.0, 0.0, 1.0), -4.0)
    occluder = plane_quads(current, [b for b in blocks if b[0] < w // 2], (0.0, 0.0, 1.0), -2.0)
    atlas_img = np.full((h, 2 * w, 4), 255, np.uint8)
    atlas_img[:, :w, :3] = 120
    col, row = np.meshgrid(np.arange(w), np.arange(h))
    atlas_img[:, w:, 0], atlas_img[:, w:, 1], atlas_img[:, w:, 2] = 120 + col - 32, 120 + 1.5 * (row - 18), 140
    atlas_img[:, w:w + w // 2, :3] = (0, 255, 0)        # the occluder
    atlas = ctx.texture((2 * w, h), 4, atlas_img.tobytes())
    atlas.filter = (moderngl.LINEAR, moderngl.LINEAR)
    mesh = QuadMesh(ctx)
    mesh.build([MeshLayer(wall, reference, (0, 0, w, h), cached=True),
                MeshLayer(occluder, current, (w, 0, w, h))], (2 * w, h))
    view = MeshView(ctx, w, h)

    # where each eye pixel's ray meets the wall (z = -4), and where that point lies in the current view
    ex, ey = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = eye.image_rays(ex, ey) @ eye.pose.camera_to_world()[:3, :3].T
    points = eye.pose.position + rays * ((-4.0 - eye.pose.position[2]) / rays[..., 2:3])
    u, v = current.project(points.reshape(-1, 3)).T.reshape(2, h, w)
    hidden = u < w / 2 - 1.5                         # behind the occluder, seen from the current view
    seen = u > w / 2 + 1.5
    inside = np.zeros((h, w), bool)
    inside[2:-2, 2:-2] = True

    mesh.set_current_view(current, (w, 0, w, h))
    view.render(mesh, eye, atlas)
    image, drawn = view.read_color(), view.read_drawn()
    image = image.astype(float)
    assert drawn.all()
    assert (hidden & inside).sum() > 100 and (seen & inside).sum() > 100
    np.testing.assert_array_equal(image[hidden & inside], [[120, 120, 120]] * int((hidden & inside).sum()))
    sel = seen & inside
    np.testing.assert_allclose(image[sel][:, 0], 120 + CURRENT_WEIGHT * (u[sel] - 0.5 - 32), atol=1.0)
    np.testing.assert_allclose(image[sel][:, 1], 120 + CURRENT_WEIGHT * 1.5 * (v[sel] - 0.5 - 18), atol=1.5)
    np.testing.assert_allclose(image[sel][:, 2], 120 + CURRENT_WEIGHT * 20, atol=1.0)

    mesh.set_current_view(None)
    view.render(mesh, eye, atlas)
    assert (view.read_color()[inside] == 120).all()


SHARP_PROBE = """#version 430
layout(local_size_x = 64) in;
#include "sharp_texture.glsl"
uniform sampler2D u_tex;
uniform int u_count;
layout(std430, binding = 0) readonly buffer Where { vec2 where[]; };
layout(std430, binding = 1) writeonly buffer Got { vec2 got[]; };   // (sharp, bilinear)
void main() {
    uint i = gl_GlobalInvocationID.x;
    if (i >= uint(u_count)) return;
    got[i] = vec2(sharp_texture(u_tex, where[i]).r, texture(u_tex, where[i]).r);
}
"""


def test_sharp_texture_keeps_texels_and_ramps_over_the_middle_of_each_interval(ctx, tmp_path):
    """Every client samples colour through render/sharp_texture.glsl: at a texel's centre it returns the texel;
    between two texels the weight of the second rises linearly over the middle 1/1.5 of the interval (bilinear
    filtering rises over all of it), so a quarter of the way across it gives 1/8 of the step, not 1/4."""
    from quadcast.render.gl import compute

    (tmp_path / "probe.comp").write_text(SHARP_PROBE)
    probe = compute(ctx, tmp_path / "probe.comp")
    texels = np.array([[0.0, 1.0, 0.25, 0.25]], np.float32)           # one row of four R32F texels
    tex = ctx.texture((4, 1), 1, texels.tobytes(), dtype="f4")
    tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
    tex.repeat_x = tex.repeat_y = False
    centre = np.array([0.0, 0.125, 0.25, 0.375, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5])  # texel-centre coordinates
    where = np.stack([(centre + 0.5) / 4, np.full_like(centre, 0.5)], axis=1).astype(np.float32)
    src, out = ctx.buffer(where.tobytes()), ctx.buffer(reserve=where.nbytes)
    src.bind_to_storage_buffer(0)
    out.bind_to_storage_buffer(1)
    tex.use(0)
    probe["u_tex"], probe["u_count"] = 0, len(where)
    probe.run(1)
    sharp, bilinear = np.frombuffer(out.read(), np.float32).reshape(-1, 2).T
    row = texels[0].astype(np.float64)
    i = np.floor(centre).astype(int)
    frac = centre - i
    a, b = row[i], row[np.minimum(i + 1, 3)]
    np.testing.assert_allclose(bilinear, a + (b - a) * frac, atol=1e-2)   # the GPU's 8-bit filter weights
    ramp = np.clip((frac - 0.5) * 1.5 + 0.5, 0.0, 1.0)
    np.testing.assert_allclose(sharp, a + (b - a) * ramp, atol=1e-2)
    assert sharp[1] < 0.1 and bilinear[1] > 0.1                         # 1/8 of the way: sharper than bilinear
    np.testing.assert_array_equal(sharp[[0, 8]], row[[0, 2]])           # texel centres: the texels themselves
    for b in (src, out, tex):
        b.release()


def test_crack_fill_closes_the_first_layers_one_pixel_cracks(ctx):
    """A pixel the first layer (a wall 2 m away, one quad per pixel) missed between two of its pixels that agree in
    depth takes their mean colour and depth, and hides the layer behind it (a far wall) as the surface does; a gap
    two pixels wide, a gap the first layer itself shows a farther surface through, and the border stay as drawn."""
    w, h = 16, 12
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), w, h)
    missing = np.zeros((h, w), bool)                  # top row first, as the quads' y
    missing[2:6, 4] = True                            # a vertical seam
    missing[8, 2:6] = True                            # a horizontal one
    missing[1, 9] = True                              # a single dot
    missing[:, 11:13] = True                          # a gap two pixels wide
    missing[0, 0] = True                              # a corner: no pair of neighbours
    deep = np.zeros((h, w), bool)
    deep[9:11, 7] = True                              # the first layer's own surface 20 m away: a real gap
    near = [(x, y, 0) for y in range(h) for x in range(w) if not missing[y, x] and not deep[y, x]]
    layers = [plane_quads(camera, near, [0, 0, 1], -2.0),
              plane_quads(camera, [(x, y, 0) for y, x in zip(*np.nonzero(deep))], [0, 0, 1], -20.0)]
    first = QuadSet.concatenate(layers)
    far = plane_quads(camera, [(x, y, 0) for y in range(h) for x in range(w)], [0, 0, 1], -50.0)
    atlas_img = np.zeros((h, 2 * w, 4), np.uint8)
    atlas_img[:, :w, 0] = np.arange(w)[None, :] * 10  # the first layer: red rises along x, green along y
    atlas_img[:, :w, 1] = np.arange(h)[:, None] * 10
    atlas_img[:, w:, 2] = 255                         # the far layer: blue
    atlas_img[..., 3] = 255
    atlas = ctx.texture((2 * w, h), 4, atlas_img.tobytes())
    mesh = QuadMesh(ctx)
    mesh.build([MeshLayer(first, camera, (0, 0, w, h)), MeshLayer(far, camera, (w, 0, w, h))], (2 * w, h))
    images = {}
    for fill in (True, False):
        view = MeshView(ctx, w, h, crack_fill=fill)
        view.render(mesh, camera, atlas)
        images[fill] = view.read_color().astype(int), view.read_depth()
        view.release()
    (got, depth), (plain, plain_depth) = images[True], images[False]
    cracks = np.zeros((h, w), bool)
    cracks[2:6, 4] = cracks[8, 2:6] = cracks[1, 9] = True
    assert np.allclose(plain_depth[cracks], 50.0, rtol=1e-3) and (plain[cracks][:, 2] == 255).all()
    assert np.allclose(depth[cracks], 2.0, rtol=1e-3)
    expected = atlas_img[:, :w, :3].astype(int)       # the mean of neighbours 20 apart in one channel
    assert np.abs(got[cracks] - expected[cracks]).max() <= 2
    keep = ~cracks
    assert np.array_equal(got[keep], plain[keep]) and np.array_equal(depth[keep], plain_depth[keep])
    assert np.allclose(depth[deep], 20.0, rtol=1e-3) and np.allclose(depth[:, 11:13], 50.0, rtol=1e-3)


def test_crack_fill_keeps_to_its_list_when_there_are_more_cracks(ctx):
    """A first layer with every other column missing (a crack in every other pixel) fills as many as its list holds
    and draws no point past it."""
    from quadcast.render.quadmesh import CRACK_SHARE
    w, h = 64, 48
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), w, h)
    first = plane_quads(camera, [(x, y, 0) for y in range(h) for x in range(0, w, 2)], [0, 0, 1], -2.0)
    far = plane_quads(camera, [(x, y, 0) for y in range(h) for x in range(w)], [0, 0, 1], -50.0)
    atlas = ctx.texture((2 * w, h), 4, np.full((h, 2 * w, 4), 255, np.uint8).tobytes())
    mesh = QuadMesh(ctx)
    mesh.build([MeshLayer(first, camera, (0, 0, w, h)), MeshLayer(far, camera, (w, 0, w, h))], (2 * w, h))
    view = MeshView(ctx, w, h)
    view.render(mesh, camera, atlas)
    depth = view.read_depth()
    filled = np.isclose(depth[:, 1:-1:2], 2.0, rtol=1e-3).sum()   # the missing columns with a drawn pair beside
    assert filled == w * h // CRACK_SHARE < (w // 2 - 1) * h
    assert np.allclose(depth[:, 0::2], 2.0, rtol=1e-3)
    assert np.isfinite(depth).all()
    drawn_points = int(np.frombuffer(view._cracks.buffer.read(4), np.uint32)[0])   # the indirect draw's count
    assert drawn_points == view._cracks.capacity == w * h // CRACK_SHARE
    view.release()
