"""The server quad pipeline (QUASAR §3.2–3.5): fitting, merging, residual frames, the encode command."""
import json
from dataclasses import replace

import av
import numpy as np
import pytest

from quadcast.protocol.frame import FrameType, decode_frame_payload
from quadcast.protocol.quads import LayerKind, decode_quad_frame
from quadcast.render.camera import Camera, Pose
from quadcast.render.quadmesh import MeshLayer, MeshView, QuadMesh
from quadcast.render.renderer import DeferredRenderer, GBuffer, read_texture
from quadcast.render.scene import scene_from_dict
from quadcast.server.quads import QUAD_FLOATS, QuadGenerator, QuadParams, gathered_to_quadset, tile_levels
from quadcast.server.quasar import QuasarServer, QuasarSettings


def test_plane_seen_head_on_merges_to_a_handful_of_quads(ctx):
    scene = scene_from_dict({"models": [{"primitive": "plane", "size": [60, 60], "rotation_deg": [90, 0, 0],
                                         "position": [0, 0, -5]}]})
    cam = Camera.perspective(Pose([0, 0, 0]), 256, 128)
    gb = DeferredRenderer(scene, ctx).gbuffer(cam)
    quads, _ = QuadGenerator(ctx, 256, 128).generate(gb.position, gb.normal, cam, QuadParams())
    assert len(quads) <= 4
    assert quads.flattened.all()
    covered = sum(int(1 << s) ** 2 for s in quads.size_log2)
    assert covered == 256 * 128  # every pixel exactly once
    assert np.allclose(quads.depth, 5.0, rtol=1e-4)
    assert np.allclose(np.abs(quads.normal[:, 2]), 1.0, atol=1e-3)


def test_quads_reconstruct_the_view_they_came_from(ctx, courtyard_renderer):
    """Rendering the quad mesh from the server pose gives back the G-buffer's depth almost everywhere."""
    cam = Camera.perspective(Pose.look_at([0, 1.6, 6], [0, 1.5, 0]), 192, 108)
    gb = courtyard_renderer.gbuffer(cam, 0.0)
    quads, _ = QuadGenerator(ctx, 192, 108).generate(gb.position, gb.normal, cam, QuadParams())
    assert 0 < len(quads) < 192 * 108 / 2  # merging really happened
    assert quads.size_log2.max() >= 3
    mesh = QuadMesh(ctx)
    mesh.build([MeshLayer(quads, cam, (0, 0, 192, 108))], (192, 108))
    view = MeshView(ctx, 192, 108)
    view.render(mesh, cam, gb.color)
    truth, got = gb.read_depth(), view.read_depth()
    geometry = np.isfinite(truth)
    close = np.abs(got[geometry] - truth[geometry]) <= 0.02 * truth[geometry]
    assert close.mean() > 0.97


def test_peeling_starts_from_the_nearest_visible_sample_of_each_block(ctx, courtyard_renderer):
    """The hidden layers peel behind the visible layer's positions reduced to their size: per block of the
    full-size layer, the nearest sample (not a second render at the small size)."""
    from quadcast.server.layers import LayerRenderer
    cam = Camera.perspective(Pose.look_at([0, 1.6, 6], [0, 2.5, 0]), 64, 36)
    layers = LayerRenderer(courtyard_renderer, 64, 36, 2, (32, 18))
    visible, hidden = layers.render(cam, 0.0, 0.5)
    full = read_texture(visible.position, 4, "f4")                 # top row first
    small = read_texture(layers.visible_small, 4, "f4")
    depth = np.where(full[..., 3] > 0, -full[..., 2], np.inf).reshape(18, 2, 32, 2).transpose(0, 2, 1, 3)
    nearest = depth.reshape(18, 32, 4).min(axis=2)
    got = np.where(small[..., 3] > 0, -small[..., 2], np.inf)
    assert np.isinf(nearest).any() and np.isfinite(nearest).any()    # sky and geometry in view
    np.testing.assert_array_equal(got, nearest)
    assert np.isfinite(hidden.read_depth()).any()                   # something was peeled


def test_peel_passes_skip_pixels_where_the_previous_layer_is_empty_without_changing_them(ctx, courtyard_renderer,
                                                                                       monkeypatch):
    """Each peel pass first sets depth 0 where the previous layer holds nothing (the peel shader would discard
    every fragment there): the layers are those of passes without that step."""
    from quadcast.server.layers import LayerRenderer
    cam = Camera.perspective(Pose.look_at([0, 1.6, 6], [0, 2.5, 0]), 96, 54)
    def layers(renderer):
        return [(gb.read_depth(), gb.read_color(), gb.read_depth_buffer()) for gb in renderer.render(cam, 0.0, 0.5)]
    culled = LayerRenderer(courtyard_renderer, 96, 54, 4, (48, 27))
    plain = LayerRenderer(courtyard_renderer, 96, 54, 4, (48, 27))
    culled.one_pass = plain.one_pass = False
    culled = layers(culled)
    monkeypatch.setattr(plain, "_depth_step", lambda *args, **kwargs: None)
    full = layers(plain)
    for a, b in zip(culled, full):                 # depth, lit colour (black where empty) and the depth buffer
        assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert np.isinf(full[2][0]).mean() > 0.3 and np.isfinite(full[2][0]).any()   # a sparse layer: much is culled


def test_mesh_orientation_tells_closed_meshes_and_their_winding(ctx):
    """Closed (watertight, consistently wound) meshes are +1 wound outward and -1 inward; open ones 0, and so are
    meshes whose closed parts are wound different ways."""
    from quadcast.render.scene import Mesh, SceneObject
    box = scene_from_dict({"models": [{"primitive": "box"}]}).objects[0].mesh
    inside_out = Mesh("inside out", box.positions, -box.normals, box.indices[:, ::-1], box.material)
    plane = scene_from_dict({"models": [{"primitive": "plane", "size": [2, 2]}]}).objects[0].mesh
    open_box = Mesh("open box", box.positions, box.normals, box.indices[2:], box.material)
    scene = scene_from_dict({"models": [{"primitive": "box"}]})
    # two boxes apart in one mesh: both wound outward (+1), or the second inside out (0: no one cull direction)
    moved = box.positions + np.array([3.0, 0.0, 0.0], np.float32)
    pair = Mesh("pair", np.concatenate([box.positions, moved]), np.concatenate([box.normals, box.normals]),
                np.concatenate([box.indices, box.indices + len(box.positions)]), box.material)
    mixed = Mesh("mixed", pair.positions, pair.normals,
                 np.concatenate([box.indices, box.indices[:, ::-1] + len(box.positions)]), box.material)
    meshes = (box, inside_out, plane, open_box, pair, mixed)
    scene.objects[:] = [SceneObject(m, object_id=i + 1) for i, m in enumerate(meshes)]
    renderer = DeferredRenderer(scene, ctx)
    assert [gm.orientation for gm in renderer.meshes] == [1, -1, 0, 0, 1, 0]


def test_peel_passes_leave_out_closed_meshes_back_faces(ctx):
    """A closed box in front of a wall: behind the box's front face the first hidden layer holds the wall, which
    an eye moving in the view cell can see past the box's edges, not the box's own back faces (its sides, seen from
    in front, and its back), which no eye outside it sees; peeling every face (skip_closed_back_faces False) puts
    them there."""
    from quadcast.server.layers import LayerRenderer
    scene = scene_from_dict({"models": [
        {"primitive": "box", "extents": [1, 1, 1], "position": [0, 0, -3]},
        {"primitive": "plane", "size": [40, 40], "rotation_deg": [90, 0, 0], "position": [0, 0, -6]}]})
    renderer = DeferredRenderer(scene, ctx)
    cam = Camera.perspective(Pose([0, 0, 0]), 96, 54)
    depths = {}
    for skip in (True, False):
        layers = LayerRenderer(renderer, 96, 54, 2)
        layers.skip_closed_back_faces = skip
        visible, hidden = layers.render(cam, 0.0, 0.5)
        depths[skip] = visible.read_depth(), hidden.read_depth()
    visible_depth = depths[True][0]
    box = np.abs(visible_depth - 2.5) < 0.01                    # the box's front face, 2.5 m away
    assert box.sum() > 50 and np.array_equal(visible_depth, depths[False][0])
    skipped, peeled = depths[True][1][box], depths[False][1][box]
    assert np.isfinite(skipped).sum() > 10 and np.allclose(skipped[np.isfinite(skipped)], 6.0, rtol=1e-3)
    assert ((peeled > 2.5) & (peeled <= 3.5 + 1e-3)).sum() > 10   # the box's own (back-facing) sides and back


def test_peel_early_reject_keeps_the_layers_of_the_full_search(ctx, courtyard_renderer):
    """The peel shader's early reject (the visible layer's farthest depth over the square its search covers, from
    LayerRenderer.visible_max) drops only fragments the full search would drop: the layers are the same."""
    from quadcast.server.layers import LayerRenderer
    cam = Camera.perspective(Pose.look_at([1.5, 1.6, 5], [-1, 1.5, 0]), 192, 108)
    fast, full = (LayerRenderer(courtyard_renderer, 192, 108, 4, (96, 54)) for _ in range(2))
    full.early_reject = False
    got, want = ([(gb.read_depth(), gb.read_color(), gb.read_normal(), gb.read_depth_buffer())
                  for gb in layers.render(cam, 0.0, 0.5)] for layers in (fast, full))
    for a, b in zip(got, want):
        assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert np.isfinite(want[1][0]).mean() > 0.02 and np.isfinite(want[2][0]).any()   # two layers hold surfaces
    # Each level holds the largest visible depth over its blocks, counted from the image's bottom-left corner as
    # GL counts pixels (the sky is SKY_DEPTH, 1e30); a level rounds its size up.
    small = fast.read_visible_max(0)
    assert small.shape == (54, 96) and (small == np.float32(1e30)).any() and (small < 1e3).any()
    assert fast.visible_max_levels >= 4                   # a search of up to 5 pixels here: blocks up to 16
    for level in range(1, fast.visible_max_levels):
        block = 1 << level
        h, w = -(-54 // block), -(-96 // block)
        padded = np.zeros((h * block, w * block), np.float32)
        padded[:54, :96] = small[::-1]                     # bottom row first
        want_level = padded.reshape(h, block, w, block).max(axis=(1, 3))[::-1]
        np.testing.assert_array_equal(fast.read_visible_max(level), want_level)


def _layer_images(layers, cam, visible_drawn=False):
    return [(gb.read_depth(), gb.read_color(), gb.read_normal(), gb.read_depth_buffer(), gb.read_object_id())
            for gb in layers.render(cam, 0.0, 0.5, visible_drawn=visible_drawn)]


def test_one_pass_peel_gives_the_layers_of_a_pass_a_layer(ctx, courtyard_renderer, monkeypatch):
    """The hidden layers taken from one draw's per-pixel lists of potentially visible fragments are those the
    layer-by-layer peel passes give, texel for texel (depth, lit colour, normal, depth buffer, object id); also when
    the lists first lack room (they grow and the draw runs again) and when they may not grow enough (the passes a
    layer take over)."""
    import quadcast.server.layers as layers_module
    from quadcast.server.layers import LayerRenderer
    cam = Camera.perspective(Pose.look_at([1.5, 1.6, 5], [-1, 1.5, 0]), 192, 108)
    per_layer = LayerRenderer(courtyard_renderer, 192, 108, 4, (96, 54))
    per_layer.one_pass = False
    want = _layer_images(per_layer, cam)
    assert np.isfinite(want[1][0]).mean() > 0.02 and np.isfinite(want[3][0]).any()   # three layers hold surfaces

    def check(layers):
        got = _layer_images(layers, cam)
        for a, b in zip(got, want):
            assert all(np.array_equal(x, y) for x, y in zip(a, b))

    one = LayerRenderer(courtyard_renderer, 192, 108, 4, (96, 54))
    check(one)
    stored = one.last_list_fragments
    assert stored >= np.isfinite(want[1][0]).sum() and one.list_capacity >= stored
    monkeypatch.setattr(layers_module, "INITIAL_LIST_FRAGMENTS_PER_PIXEL", stored / (96 * 54) / 8)
    grown = LayerRenderer(courtyard_renderer, 192, 108, 4, (96, 54))
    check(grown)
    assert grown.last_list_fragments == stored and stored <= grown.list_capacity < 2 * stored
    monkeypatch.setattr(layers_module, "MAX_LIST_FRAGMENTS_PER_PIXEL", stored / (96 * 54) / 2)
    limited = LayerRenderer(courtyard_renderer, 192, 108, 4, (96, 54))
    check(limited)
    assert limited.list_capacity < stored <= limited.last_list_fragments


def test_one_pass_list_drawn_behind_the_visible_layer_keeps_the_same_layers(ctx, courtyard_renderer):
    """The one-pass peel's list is drawn against a depth just in front of the one behind which its shader keeps
    fragments (peel_cull.frag.glsl's BEHIND step: the window depth of z0 (1 + connectivity), less a margin; 1 where
    the visible layer is empty), so the depth test drops the visible surface's own fragments before the shader
    runs. The same fragments are stored and the same layers made as with the cull step alone."""
    from quadcast.server.layers import LayerRenderer
    cam = Camera.perspective(Pose.look_at([1.5, 1.6, 5], [-1, 1.5, 0]), 192, 108)
    plain = LayerRenderer(courtyard_renderer, 192, 108, 4, (96, 54))
    plain.list_cull_visible = False
    want = _layer_images(plain, cam)
    behind = LayerRenderer(courtyard_renderer, 192, 108, 4, (96, 54))
    got = _layer_images(behind, cam)
    for a, b in zip(got, want):
        assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert behind.last_list_fragments == plain.last_list_fragments > 0
    # the step's depths: 1 where nothing is visible, else just in front of the kept fragments' depths
    position = read_texture(behind.visible_small, 4, "f4")
    stepped = read_texture(behind._list_depth, 1, "f4").astype(np.float64)
    empty = ~(position[..., 3] > 0)
    assert empty.any() and (~empty).mean() > 0.5 and np.all(stepped[empty] == 1.0)
    z = np.minimum(-position[..., 2].astype(np.float64) * 1.001, cam.frustum.far)[~empty]
    clip = cam.frustum.projection_matrix() @ np.stack([np.zeros_like(z), np.zeros_like(z), -z, np.ones_like(z)])
    window = 0.5 * clip[2] / clip[3] + 0.5            # the renderer's projection, depth range [0, 1]
    assert np.all(stepped[~empty] < window) and np.all(stepped[~empty] > window - 2e-6)


def test_layers_lit_after_other_views_are_drawn_are_the_same(ctx, courtyard_renderer):
    """QuasarServer.encode draws the visible layer's geometry (`draw_visible`), then other views' geometry, then
    `render(..., visible_drawn=True)`: the layers are those `render` alone makes, texel for texel."""
    from quadcast.server.layers import LayerRenderer
    cam = Camera.perspective(Pose.look_at([1.5, 1.6, 5], [-1, 1.5, 0]), 192, 108)
    want = _layer_images(LayerRenderer(courtyard_renderer, 192, 108, 4, (96, 54)), cam)
    layers = LayerRenderer(courtyard_renderer, 192, 108, 4, (96, 54))
    layers.draw_visible(cam, 0.0)
    other = GBuffer(ctx, 120, 68)
    courtyard_renderer.geometry_pass(Camera.perspective(Pose.look_at([0, 1.6, -6], [0, 1.5, 0]), 120, 68), 0.0,
                                     target=other)
    got = _layer_images(layers, cam, visible_drawn=True)
    assert len(got) == len(want) == 4
    for a, b in zip(got, want):
        assert all(np.array_equal(x, y) for x, y in zip(a, b))


def test_atlas_copies_layers_of_its_rects_size_as_the_drawing_pass_draws_them(ctx, courtyard_renderer):
    """AtlasComposer copies a layer whose colour has its rect's size (glCopyImageSubData) and draws the others
    scaled: the atlas is the one the drawing pass makes for every layer."""
    from quadcast.server.layers import AtlasComposer, AtlasLayout
    layout = AtlasLayout.for_view(96, 54, 2, (60, 34))
    views = [Camera.perspective(Pose.look_at([0, 1.6, 6], [x, 1.5, 0]), w, h)
             for x, (w, h) in zip((0, 1, 2, 3), ((96, 54), (96, 54), (48, 27), (64, 36)))]
    colors = [courtyard_renderer.gbuffer(cam, 0.0, target=GBuffer(ctx, cam.width, cam.height)).color for cam in views]
    rects = [layout.reference, layout.current, layout.hidden[0], layout.hidden[1]]   # the last one scaled down
    atlases = []
    for copy in (True, False):
        atlas = AtlasComposer(ctx, layout)
        atlas._copy = copy
        atlas.clear()
        for color, rect in zip(colors, rects):
            atlas.draw(color, rect)
        atlases.append(atlas.read())
    assert np.array_equal(atlases[0], atlases[1])
    x, y, w, h = layout.current
    assert np.array_equal(atlases[0][y:y + h, x:x + w, :3], read_texture(colors[1], 4, "u1")[..., :3])
    assert atlases[0][..., :3].std() > 10                  # pictures, not a cleared atlas


def test_grow_mask_is_a_one_pixel_binary_dilation():
    from scipy.ndimage import binary_dilation
    from quadcast.server.quads import grow_mask
    rng = np.random.default_rng(5)
    for shape, p in (((37, 53), 0.05), ((1, 9), 0.3), ((8, 1), 0.3), ((20, 20), 0.0), ((6, 7), 1.0)):
        mask = rng.random(shape) < p
        before = mask.copy()
        assert np.array_equal(grow_mask(mask), binary_dilation(mask, iterations=1))
        assert np.array_equal(mask, before)                          # the input is left as it was


def _same_quads(a, b) -> bool:
    return (len(a) == len(b) and all(np.array_equal(getattr(a, f), getattr(b, f))
                                     for f in ("x", "y", "size_log2", "flattened", "normal", "depth", "offsets")))


def test_tile_ring_is_the_tiles_around_a_list_clipped_to_the_grid():
    from quadcast.server.quads import tile_ring
    code = lambda ty, tx: (ty << 16) | tx
    ring = tile_ring(np.array([code(0, 0), code(2, 5)], np.uint32), (6, 4))
    expected = {code(0, 1), code(1, 0), code(1, 1)} | {code(y, x) for y in (1, 2, 3) for x in (4, 5)} - {code(2, 5)}
    assert set(ring.tolist()) == expected


def test_tile_lists_give_the_quads_of_the_whole_grid(ctx, courtyard_renderer, monkeypatch):
    """The quad passes visit only 8x8 tiles holding a masked pixel, or (wide view) not wholly inside the main
    view and holding geometry: the quads are those a pass over every tile gives, and no Quad Map entry left
    from an earlier frame leaks into a masked one."""
    from quadcast.server import quads as quads_module
    from quadcast.server.layers import wide_camera
    cam = Camera.perspective(Pose.look_at([0, 1.6, 6], [0, 1.5, 0]), 192, 108)
    gb = courtyard_renderer.gbuffer(cam, 0.0)
    rng = np.random.default_rng(3)
    mask = np.zeros((108, 192), bool)
    mask[rng.integers(0, 108, 40), rng.integers(0, 192, 40)] = True
    mask[30:70, 50:120] = True
    params = QuadParams()

    used = QuadGenerator(ctx, 192, 108)
    # A frame at other settings first (fewer merges): it leaves valid quads in every Quad Map, which these
    # settings would merge if the masked pass read them.
    used.generate(gb.position, gb.normal, cam, replace(params, delta_sim=1e-4, coarse_passes=0))
    masked, _ = used.generate(gb.position, gb.normal, cam, params, mask=mask)
    tiles = used.active_tiles(cam, mask)[0]
    assert 0 < len(tiles) < 24 * 14                               # the mask's tiles, not the whole grid
    wide = wide_camera(cam)
    wide_gb = courtyard_renderer.gbuffer(wide, 0.0)
    wide_gen = QuadGenerator(ctx, wide.width, wide.height)
    outer, _ = wide_gen.generate(wide_gb.position, wide_gb.normal, wide, params.relaxed(), inner=cam)
    inside = wide_gen._inside_tiles(wide, cam)
    assert 0 < inside.sum() < inside.size
    occupied = wide_gen.occupied_tiles(wide_gb.position)
    assert 0 < occupied.sum() < occupied.size                     # the sky holds no geometry

    # The same passes over every tile of a fresh generator.
    def every_tile(self, camera, mask=None, inner=None, occupied=None):
        tw, th = self.tile_grids[0]
        ty, tx = np.mgrid[:th, :tw].reshape(2, -1)
        return [np.unique((ty >> l).astype(np.uint32) << 16 | (tx >> l).astype(np.uint32))
                for l in range(self.levels)]
    monkeypatch.setattr(quads_module.QuadGenerator, "active_tiles", every_tile)
    masked_all, _ = QuadGenerator(ctx, 192, 108).generate(gb.position, gb.normal, cam, params, mask=mask)
    outer_all, _ = QuadGenerator(ctx, wide.width, wide.height).generate(wide_gb.position, wide_gb.normal, wide,
                                                                        params.relaxed(), inner=cam)
    assert len(masked) > 0 and len(outer) > 0
    assert _same_quads(masked, masked_all)
    assert _same_quads(outer, outer_all)


def test_sparse_mask_runs_on_its_pixels_with_the_quads_of_its_tiles(ctx, courtyard_renderer):
    """Under a sparse mask the plane and create passes run on the masked pixels (QuadGenerator.listed_pixels), not
    on their whole tiles: the same quads, also after an unmasked frame left planes everywhere; a dense mask keeps
    the tiles."""
    cam = Camera.perspective(Pose.look_at([1.5, 1.6, 5], [-1, 1.5, 0]), 192, 108)
    gb = courtyard_renderer.gbuffer(cam, 0.0)
    rng = np.random.default_rng(11)
    mask = np.zeros((108, 192), bool)
    mask[rng.integers(0, 108, 300), rng.integers(0, 192, 300)] = True
    mask[40:42, 20:170] = True                                     # a thin sliver, as revealed pixels are
    mask[60:90, 100:104] = True
    params = QuadParams()
    listed, tiled = QuadGenerator(ctx, 192, 108), QuadGenerator(ctx, 192, 108)
    tiled.use_pixel_list = False
    listed.generate(gb.position, gb.normal, cam, params)           # planes and Quad Maps of a whole frame first
    pixels = listed.listed_pixels(mask, listed.active_tiles(cam, mask)[0])
    assert pixels is not None and len(pixels) == mask.sum()
    got, _ = listed.generate(gb.position, gb.normal, cam, params, mask=mask)
    want, _ = tiled.generate(gb.position, gb.normal, cam, params, mask=mask)
    assert len(want) > 100 and _same_quads(got, want)
    dense = np.zeros((108, 192), bool)
    dense[8:64, 16:80] = True
    assert listed.listed_pixels(dense, listed.active_tiles(cam, dense)[0]) is None


def test_sparse_geometry_runs_on_its_pixels_with_the_quads_of_its_tiles(ctx, courtyard_renderer):
    """A layer without sky quads (a hidden layer) whose geometry is sparse: occupied_pixels finds the pixels
    holding geometry nearer than max_depth, a bit each, and the passes run on those (listed_pixels) with the quads
    of the occupied tiles."""
    from quadcast.server.layers import LayerRenderer
    cam = Camera.perspective(Pose.look_at([1.5, 1.6, 5], [-1, 1.5, 0]), 192, 108)
    layers = LayerRenderer(courtyard_renderer, 192, 108, 2)
    hidden = layers.render(cam, 0.0, 0.5)[1]
    position = read_texture(hidden.position, 4, "f4")
    params = QuadParams(sky=False, max_depth=12.0)
    geometry = (position[..., 3] > 0) & (-position[..., 2] <= params.max_depth)
    assert 0.01 < geometry.mean() < 0.2 and (position[..., 3] > 0).sum() > geometry.sum()   # sparse; some too far
    listed, tiled = QuadGenerator(ctx, 192, 108), QuadGenerator(ctx, 192, 108)
    tiled.use_pixel_list = False
    visible = courtyard_renderer.gbuffer(cam, 0.0)
    listed.generate(visible.position, visible.normal, cam, QuadParams())   # a whole view first: stale maps
    occupied = listed.occupied_tiles(hidden.position, params.max_depth)
    np.testing.assert_array_equal(listed.occupied_pixels(), geometry)
    assert listed.listed_pixels(geometry, listed.active_tiles(cam, None, None, occupied)[0]) is not None
    got, _ = listed.generate(hidden.position, hidden.normal, cam, params)
    want, _ = tiled.generate(hidden.position, hidden.normal, cam, params)
    assert len(want) > 50 and _same_quads(got, want)


@pytest.fixture(scope="module")
def moving_box_scene():
    return scene_from_dict({"models": [
        {"primitive": "plane", "size": [40, 40], "rotation_deg": [90, 0, 0], "position": [0, 0, -8],
         "color": [0.7, 0.7, 0.6]},
        {"primitive": "plane", "size": [40, 40], "position": [0, -1.5, 0], "color": [0.5, 0.6, 0.5]},
        {"primitive": "box", "extents": [0.8, 0.8, 0.8], "position": [0, 0, -4], "color": [0.9, 0.2, 0.2],
         "animation": {"type": "translate", "direction": [1, 0, 0], "amplitude": 1.0, "period_s": 4.0}}]})


def test_residual_frame_covers_only_the_moving_object_and_what_it_reveals(ctx, moving_box_scene):
    renderer = DeferredRenderer(moving_box_scene, ctx)
    server = QuasarServer(renderer, QuasarSettings(width=160, height=96, layers=2, reference_every=10))
    pose = Pose([0, 0, 0])
    reference = server.encode(pose, 0.0)
    residual = server.encode(pose, 0.25)  # the box moved ~0.38 m to the right
    assert reference.frame_type == 0 and residual.frame_type == 1
    frame = decode_quad_frame(residual.geometry)
    updated = next(l for l in frame.layers if l.kind == LayerKind.UPDATED).quads
    revealed = next(l for l in frame.layers if l.kind == LayerKind.REVEALED).quads
    assert len(updated) > 0
    # The box's pixels before and after, grown by the 1-pixel expansion and 2 pixels of quad slack.
    cam = server.camera_for(pose)
    box_id = moving_box_scene.objects[2].object_id
    before = renderer.render(cam, 0.0).object_id == box_id
    after = renderer.render(cam, 0.25).object_id == box_id
    from scipy.ndimage import binary_dilation
    allowed = binary_dilation(before | after, iterations=3)
    covered = np.zeros_like(allowed)
    for x, y, s in zip(updated.x, updated.y, updated.size_log2):
        covered[y:y + (1 << s), x:x + (1 << s)] = True
    assert covered.any() and (covered & ~allowed).sum() <= 0.02 * covered.sum()
    assert covered[after & ~before].mean() > 0.9   # where the box arrived
    assert covered[before & ~after].mean() > 0.9   # the background it revealed
    # The camera did not move: nothing new is revealed at the new pose beyond the moving box's region.
    rev = np.zeros_like(allowed)
    for x, y, s in zip(revealed.x, revealed.y, revealed.size_log2):
        rev[y:y + (1 << s), x:x + (1 << s)] = True
    assert (rev & ~allowed).sum() <= 0.02 * allowed.size
    assert residual.size_bytes < reference.size_bytes


def test_boundary_expansion_grows_the_revealed_region_by_its_pixels(ctx, courtyard_renderer):
    """reveal_expansion_px (QUASAR's boundary expansion, off by default): with one pixel the revealed quads cover
    what they cover without it and a ring around it."""
    covers = []
    for px in (0, 1):
        server = QuasarServer(courtyard_renderer, QuasarSettings(width=160, height=96, layers=2,
                                                                 reveal_expansion_px=px))
        server.encode(Pose.look_at([0, 1.6, 6], [0, 1.5, 0]), 0.0)
        residual = server.encode(Pose.look_at([0.25, 1.6, 5.9], [0, 1.5, 0]), 0.0)
        revealed = next(l for l in decode_quad_frame(residual.geometry).layers if l.kind == LayerKind.REVEALED).quads
        cover = np.zeros((96, 160), bool)
        for x, y, s in zip(revealed.x, revealed.y, revealed.size_log2):
            cover[y:y + (1 << s), x:x + (1 << s)] = True
        covers.append(cover)
    without, with_ring = covers
    assert 0 < without.sum() and not (without & ~with_ring).any()
    assert with_ring.sum() > 1.3 * without.sum()
    with pytest.raises(ValueError, match="reveal_expansion_px"):
        QuasarSettings(reveal_expansion_px=-1)


def test_hidden_layers_and_wide_view_are_sent_at_fill_depth_bits(ctx, courtyard_renderer):
    """Depths on the wire: 12 mantissa bits for the visible layer, fill_depth_bits (7) for the hidden layers and
    the wide view."""
    server = QuasarServer(courtyard_renderer, QuasarSettings(width=160, height=96, layers=3))
    frame = decode_quad_frame(server.encode(Pose.look_at([0, 1.6, 6], [0, 1.5, 0]), 0.0).geometry)
    low_bits = {}
    for layer in frame.layers:
        if len(layer.quads):
            bits = layer.quads.depth.astype(np.float32).view(np.uint32) & np.uint32((1 << 23) - 1)
            low_bits.setdefault(layer.kind, []).append(int(np.bitwise_or.reduce(bits)))
    assert {LayerKind.VISIBLE, LayerKind.HIDDEN, LayerKind.WIDE} <= set(low_bits)
    kept = lambda masks: 23 - min((m & -m).bit_length() - 1 for m in masks if m)   # highest dropped bit + 1
    assert kept(low_bits[LayerKind.VISIBLE]) == 12
    assert kept(low_bits[LayerKind.HIDDEN]) <= 7 and kept(low_bits[LayerKind.WIDE]) <= 7


def test_encode_command_writes_decodable_video_and_stats(tmp_path):
    import quadcast.cli as quadcast
    out = tmp_path / "enc"
    assert quadcast.main(["-q", "encode", "--scene", "builtin:courtyard", "--trace", "builtin:walk",
                          "--size", "192x108", "--frames", "6", "--viewcell", "0.5", "--every", "3",
                          "--layers", "3", "--out", str(out)]) == 0
    stats = json.loads((out / "stats.json").read_text())
    assert len(stats["frames"]) == 6
    assert [f["type"] for f in stats["frames"]] == ["reference", "residual", "residual"] * 2
    for f in stats["frames"]:
        assert f["bits_per_quad_raw"] <= 80
        assert set(f["ms"]) >= {"gbuffers", "cache", "quads", "merge", "gather", "zstd", "video"}
        assert f["quads"] == sum(f["quads_per_layer"].values())
    assert 0 < stats["residual_to_reference_bytes"] < 1
    assert stats["mbps_at_30fps"] > 0
    # Every payload parses and every access unit decodes with PyAV.
    from quadcast.codec.decoder import AtlasDecoder
    decoder = AtlasDecoder()
    for i in range(6):
        payload = decode_frame_payload((out / f"frame_{i:05d}.bin").read_bytes())
        decode_quad_frame(payload.geometry)
        image = decoder.decode(payload.video)
        assert image is not None and image.shape[2] == 3
    # The concatenated stream decodes as a whole, frame by frame.
    with av.open(str(out / "atlas.h264"), format="h264") as container:
        assert sum(1 for _ in container.decode(video=0)) == 6
    assert quadcast.main(["-q", "encode", "--size", "191x108", "--out", str(out)]) == 2


def test_reference_view_rerendered_where_the_scene_moves_equals_a_full_render(ctx):
    """Residual frames re-render the reference view only within the animated objects' and their shadows' screen
    region; what the server keeps is still exactly the full render at the frame's time."""
    from quadcast.render.renderer import DeferredRenderer, GBuffer
    from quadcast.render.scene import load_scene
    from quadcast.render.traces import resolve_trace
    from quadcast.server.quasar import QuasarServer, QuasarSettings
    renderer = DeferredRenderer(load_scene("builtin:courtyard"), ctx)
    server = QuasarServer(renderer, QuasarSettings(width=160, height=96, reference_every=4))
    check = GBuffer(ctx, 160, 96)
    trace = resolve_trace("builtin:walk")
    regions = []
    for k in range(8):
        t = 0.7 * k                                   # scene time runs fast: the objects move a lot
        p, q = trace.pose_at(trace.times[0] + k / 30)
        before = server.reference_camera
        server.encode(Pose(p, q), t)
        if before is not None and server.reference_camera is before:
            regions.append(renderer.moving_region(before, (0.0, t)))
        truth = renderer.gbuffer(server.reference_camera, t, target=check).read_color()
        assert np.array_equal(server.reference_gbuffer.read_color(), truth), f"frame {k}"
    assert any(0 < w * h < 160 * 96 for _, _, w, h in regions), regions     # only part of the view re-rendered
    server.close()


def test_wide_view_widens_when_frames_come_far_apart(courtyard_renderer):
    """Frames 1/30 s apart get a wide view wide_fovy_deg high; 0.1 s apart, the view's FOV plus the turn
    wide_turn_dps makes in that time on each side; 0.5 s apart, wide_fovy_max_deg. The payload's wide layer carries
    that camera at the same size (the atlas does not change), and display times that go back start again."""
    s = QuasarSettings(width=160, height=96, layers=2)
    expected = {1 / 30: s.wide_fovy_deg, 0.1: s.fovy_deg + 2 * s.wide_turn_dps * 0.1, 0.5: s.wide_fovy_max_deg}
    assert s.wide_fovy_deg < expected[0.1] < s.wide_fovy_max_deg
    server = QuasarServer(courtyard_renderer, s)
    pose = Pose.look_at([0, 1.6, 6], [0, 1.5, 0])
    for step, fovy in expected.items():
        for k in range(4):
            frame = decode_quad_frame(server.encode(pose, 10.0 - step * 4 + step * k).geometry)
        wide = next(layer for layer in frame.layers if layer.kind == LayerKind.WIDE)
        camera = Camera.from_array(wide.camera, wide.width, wide.height)
        assert camera.frustum.fovy_deg == pytest.approx(fovy, abs=1e-3), step
        assert (wide.width, wide.height) == (100, 60)
    # once the session core measured how far the head's rotation strayed from the predicted one, that is the
    # margin on each side instead (frames 0.5 s apart here), within the same bounds
    for miss, fovy in ((20.0, s.fovy_deg + 40.0), (2.0, s.wide_fovy_deg), (50.0, s.wide_fovy_max_deg)):
        server.set_rotation_miss(miss)
        frame = decode_quad_frame(server.encode(pose, 20.0 + miss).geometry)
        wide = next(layer for layer in frame.layers if layer.kind == LayerKind.WIDE)
        assert Camera.from_array(wide.camera, wide.width, wide.height).frustum.fovy_deg == pytest.approx(fovy), miss
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="set_rotation_miss"):
            server.set_rotation_miss(bad)
    with pytest.raises(ValueError, match="wide_fovy_max_deg"):
        QuasarSettings(wide_fovy_deg=130.0)
    server.close()


def test_wide_view_is_not_drawn_where_it_makes_no_quads(courtyard_renderer):
    """The wide view is neither drawn nor lit inside the main view, a margin inside the part its quads leave out
    (`inner_rect`): the same geometry bytes as a server that draws all of it, along a walk with head turns and
    with the wide view at its widest; nothing drawn and black inside the rectangle, all of it drawn outside, and the
    objects wholly inside it not drawn at all."""
    from quadcast.render.traces import resolve_trace
    from quadcast.server.quads import inner_rect
    trace = resolve_trace("builtin:walk")
    s = QuasarSettings(width=160, height=96, layers=2)
    skipping, drawing = QuasarServer(courtyard_renderer, s), QuasarServer(courtyard_renderer, s)
    drawing.skip_wide_inner = False
    rects, skipped = [], 0
    for k, t in enumerate((1.0, 1.1, 1.2, 4.0, 4.5, 9.0)):
        pose = Pose(*trace.pose_at(t))
        if k == 4:
            for server in (skipping, drawing):
                server.set_rotation_miss(50.0)      # the widest view: a smaller rectangle
        a, b = skipping.encode(pose, t), drawing.encode(pose, t)
        assert a.geometry == b.geometry, t
        wide_cam = Camera.from_array(next(layer for layer in decode_quad_frame(a.geometry).layers
                                          if layer.kind == LayerKind.WIDE).camera, 100, 60)
        x, y, w, h = rect = inner_rect(wide_cam, skipping.camera_for(pose))
        rects.append(rect)
        assert w > 20 and h > 10, rect
        inside = np.zeros((60, 100), bool)
        inside[y:y + h, x:x + w] = True
        got, full = skipping.wide_gbuffer.read_depth(), drawing.wide_gbuffer.read_depth()
        assert np.isinf(got[inside]).all() and (skipping.wide_gbuffer.read_color()[inside] == 0).all()
        assert np.array_equal(got[~inside], full[~inside]) and np.isfinite(full[inside]).mean() > 0.9
        skipped += int(courtyard_renderer.objects_within(wide_cam, t, rect).sum())
    assert len(set(rects)) > 1                          # the rectangle follows the wide view's FOV
    assert skipped > 0                                  # objects wholly inside it were not drawn at all
    skipping.close()
    drawing.close()


def test_video_coded_beside_the_quads_is_the_video_coded_after_them(courtyard_renderer):
    """The atlas is coded by x264 on a thread of its own while the quad passes run: along a walk the server sends
    the video and geometry bytes of a server that codes it after them. When the quads fail, the frame x264 took is
    never sent, so the next frame is a reference frame (a keyframe), and the thread is gone after `close`."""
    from quadcast.render.traces import resolve_trace
    trace = resolve_trace("builtin:walk")
    s = QuasarSettings(width=160, height=96, layers=2)
    beside, after = QuasarServer(courtyard_renderer, s), QuasarServer(courtyard_renderer, s)
    after.code_video_beside_quads = False
    for t in (1.0, 1.1, 1.2, 1.3, 4.0, 4.1):
        pose = Pose(*trace.pose_at(t))
        a, b = beside.encode(pose, t), after.encode(pose, t)
        assert (a.video, a.geometry, a.frame_type) == (b.video, b.geometry, b.frame_type), t
    assert beside._video_thread is not None and after._video_thread is None

    def fail(*args, **kwargs):
        raise RuntimeError("quads failed")
    beside._quads_and_geometry = fail
    with pytest.raises(RuntimeError, match="quads failed"):
        beside.encode(Pose(*trace.pose_at(4.2)), 4.2)
    del beside._quads_and_geometry
    frame = beside.encode(Pose(*trace.pose_at(4.3)), 4.3)
    assert frame.frame_type == FrameType.REFERENCE and frame.self_contained
    beside.close()
    after.close()
    assert beside._video_thread is None


def test_hidden_layers_sent_again_while_frames_come_far_apart(courtyard_renderer):
    """Frames more than hidden_reuse_after_ms apart render the hidden layers every hidden_every frames and send the
    last ones again in between: the same quads and camera, and their colour in the kept G-buffers unchanged. Frames
    1/30 s apart, or hidden_every 1, render them with every frame. A frame whose quads fail leaves nothing kept, so
    the next frame renders them again."""
    from quadcast.render.traces import resolve_trace
    trace = resolve_trace("builtin:walk")
    s = QuasarSettings(width=160, height=96, layers=3)
    assert s.hidden_every == 2 and s.hidden_reuse_after_ms == 100.0

    def hidden(server, t):
        """(each hidden layer's camera and quads, the pose's own hidden camera, the kept G-buffers' colour)"""
        pose = Pose(*trace.pose_at(t))
        frame = decode_quad_frame(server.encode(pose, t).geometry)
        layers = [(layer.camera.tobytes(), layer.quads) for layer in frame.layers if layer.kind == LayerKind.HIDDEN]
        own = server.layer_renderer.hidden_camera(server.camera_for(pose)).to_array().tobytes()
        colours = [read_texture(gb.color, 4, "u1") for gb in server.layer_renderer.hidden]
        return layers, own, colours

    def same(a, b):
        return len(a) == len(b) and all(ca == cb and _same_quads(qa, qb) for (ca, qa), (cb, qb) in zip(a, b))

    slow = QuasarServer(courtyard_renderer, s)
    frames = [hidden(slow, 1.0 + 0.2 * k) for k in range(5)]
    assert len(frames[0][0]) == 2
    for k, (layers, own, colours) in enumerate(frames):
        fresh = k % 2 == 0                       # the first frame, then every other one
        assert all(camera == own for camera, _ in layers) == fresh, k
        if not fresh:
            previous = frames[k - 1]
            assert same(layers, previous[0]), k
            assert all(np.array_equal(a, b) for a, b in zip(colours, previous[2])), k
    assert not same(frames[2][0], frames[0][0])

    layers, own, _ = hidden(slow, 2.0)           # frame 6 sends frame 5's again
    assert not any(camera == own for camera, _ in layers)

    def fail(*args, **kwargs):
        raise RuntimeError("quads failed")
    slow._quads_and_geometry = fail              # frame 7 renders them again, then fails
    with pytest.raises(RuntimeError, match="quads failed"):
        slow.encode(Pose(*trace.pose_at(2.2)), 2.2)
    del slow._quads_and_geometry
    layers, own, _ = hidden(slow, 2.4)           # would have sent frame 7's again
    assert all(camera == own for camera, _ in layers)
    slow.close()

    for settings, step in ((s, 1 / 30), (replace(s, hidden_every=1), 0.2)):
        server = QuasarServer(courtyard_renderer, settings)
        for k in range(4):
            layers, own, _ = hidden(server, 1.0 + step * k)
            assert all(camera == own for camera, _ in layers), (step, k)
        server.close()
    for bad in (dict(hidden_every=0), dict(hidden_reuse_after_ms=-1.0)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            QuasarSettings(**bad)


def test_gathered_quads_come_out_by_size_then_row_then_column():
    """The GPU appends quads in any order; the server's QuadSet orders them by size, then y, then x, exactly as
    np.lexsort on those columns does (the payload must not depend on the GPU's scheduling)."""
    rng = np.random.default_rng(3)
    n = 5000
    rows = np.zeros((n, QUAD_FLOATS), np.float32)
    head = rows[:, :4].view(np.uint32)
    head[:, 0], head[:, 1] = rng.integers(0, 960, n), rng.integers(0, 540, n)
    head[:, 2], head[:, 3] = rng.integers(0, 6, n), 1
    rows[:, 6], rows[:, 7] = 1.0, np.arange(n)          # unit normals; the depth tells which row went where
    quads = gathered_to_quadset(rows)
    order = np.lexsort((head[:, 0], head[:, 1], head[:, 2]))
    np.testing.assert_array_equal(quads.depth, np.arange(n, dtype=np.float32)[order])
    keys = np.stack([quads.size_log2, quads.y, quads.x], axis=1).astype(np.int64)
    assert (np.diff(keys[:, 0] * 10**8 + keys[:, 1] * 10**4 + keys[:, 2]) >= 0).all()


def test_tile_levels_are_the_level_0_tiles_shifted_and_deduplicated():
    """Each level's tile codes (pooled 2 x 2 from the level below) are the sorted, distinct codes of the active
    level-0 tiles shifted right by the level, odd grid sizes included."""
    rng = np.random.default_rng(11)
    for _ in range(50):
        th, tw = int(rng.integers(1, 70)), int(rng.integers(1, 125))
        active = rng.random((th, tw)) < rng.random()
        ty, tx = np.nonzero(active)
        got = tile_levels(active, 9)
        for level, codes in enumerate(got):
            want = np.unique((ty >> level).astype(np.uint32) << 16 | (tx >> level).astype(np.uint32))
            np.testing.assert_array_equal(codes, want)
            assert codes.dtype == np.uint32
