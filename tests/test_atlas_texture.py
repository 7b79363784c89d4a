"""The decoded atlas on the GPU: 4:2:0 planes, converted to RGB where the draws sample them (render/atlas_texture.py,
render/atlas_colour.glsl)."""

from __future__ import annotations

import moderngl
import numpy as np
import pytest

from quadcast.codec.decoder import AtlasDecoder
from quadcast.codec.encoder import AtlasEncoder, VideoSettings
from quadcast.protocol.quads import QuadSet
from quadcast.render.atlas_texture import AtlasTexture
from quadcast.render.camera import Camera, Pose
from quadcast.render.quadmesh import MeshLayer, MeshView, QuadMesh

W, H = 96, 58   # chroma planes 48x29: the last chroma row covers one luma row


def _source() -> np.ndarray:
    y, x = np.mgrid[0:H, 0:W].astype(np.float64)
    return np.clip(np.stack([120 + 90 * np.sin(x / 11.0), 120 + 80 * np.cos(y / 7.0 + x / 30.0),
                             100 + 60 * np.sin((x - y) / 13.0)], axis=-1), 0, 255).astype(np.uint8)


def _picture(source: np.ndarray | None = None):
    source = _source() if source is None else source
    with AtlasEncoder(source.shape[1], source.shape[0], VideoSettings(crf=0, threads=1)) as encoder:
        unit = encoder.encode(source, keyframe=True).data
    return AtlasDecoder(output="yuv420").decode(unit, 0)


def test_gpu_conversion_matches_the_cpu_one(ctx):
    picture = _picture()
    atlas = AtlasTexture(ctx)
    atlas.write(picture)
    gpu = atlas.read_rgb()
    cpu = picture.to_rgb()
    assert gpu.shape == (H, W, 3)
    diff = np.abs(gpu.astype(int) - cpu)
    # the GPU sharpens the chroma on its own grid, FFmpeg interpolates it bilinearly: on this picture of smooth
    # colour they differ by 1.4 levels on average, at most 7 (a wrong matrix or range would be tens of levels off)
    assert diff.mean() < 1.5 and diff.max() <= 8, (diff.mean(), diff.max())
    # and both are close to what was encoded (CRF 0: the conversions are the error)
    assert np.abs(gpu.astype(int) - _source()).mean() < 1.5
    atlas.release()


def test_a_new_size_replaces_the_planes(ctx):
    atlas = AtlasTexture(ctx)
    assert atlas.size is None
    with pytest.raises(ValueError, match="no picture written yet"):
        atlas.use(0)
    small = _picture(_source()[:10, :16])
    atlas.write(small)
    assert atlas.size == (16, 10)
    np.testing.assert_allclose(atlas.read_rgb(), small.to_rgb(), atol=6)
    atlas.write(_picture())
    assert atlas.size == (W, H)
    atlas.release()


@pytest.mark.parametrize("bad", [np.zeros((4, 6, 3), np.uint8), "picture"])
def test_bad_input_is_a_clear_error(ctx, bad):
    with pytest.raises(ValueError, match="AtlasTexture.write: need a YuvPicture, got"):
        AtlasTexture(ctx).write(bad)


def test_the_mesh_draw_converts_the_planes_as_read_rgb_does(ctx):
    """A quad mesh drawn from its layer's own camera samples the atlas at texel centres: through the planes it
    shows exactly what read_rgb shows, as drawing from that RGBA picture does; from another pose the two differ by
    about a level on average (measured 0.89, at most 6: the RGBA picture was rounded to 8 bits before filtering, and
    the planes' chroma is sharpened on its own grid, the picture's on the luma's)."""
    picture = _picture()
    atlas = AtlasTexture(ctx)
    atlas.write(picture)
    rgb = atlas.read_rgb()
    rgba = np.concatenate([rgb, np.full((H, W, 1), 255, np.uint8)], axis=-1)
    texture = ctx.texture((W, H), 4, rgba.tobytes())   # the quad mesh counts atlas rows from the top
    texture.filter = (moderngl.LINEAR, moderngl.LINEAR)
    quad = QuadSet(x=[0], y=[0], size_log2=[7], flattened=[True], alpha=[False], normal=[[0.0, 0.0, 1.0]],
                   depth=[2.0], offsets=np.zeros((0, 16)))
    camera = Camera.perspective(Pose([0.0, 0.0, 0.0]), W, H)
    mesh = QuadMesh(ctx)
    mesh.build([MeshLayer(quad, camera, (0, 0, W, H))], (W, H))
    view = MeshView(ctx, W, H)
    moved = Camera.perspective(Pose.look_at([0.1, 0.05, 0.0], [0.0, 0.0, -2.0]), W, H)
    for eye, max_difference, mean_difference in ((camera, 0, 0.0), (moved, 6, 1.0)):
        images = []
        for source in (atlas, texture):
            view.render(mesh, eye, source)
            image, drawn = view.read_color(), view.read_drawn()
            images.append(image[drawn].astype(int))
        assert len(images[0]) > 0.6 * W * H
        difference = np.abs(images[0] - images[1])
        assert difference.max() <= max_difference and difference.mean() <= mean_difference
    texture.release()
    atlas.release()
