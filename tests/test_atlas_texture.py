"""The decoded atlas on the GPU: 4:2:0 planes converted to RGBA in a shader (render/atlas_texture.py)."""

from __future__ import annotations

import numpy as np
import pytest

from quadcast.codec.decoder import AtlasDecoder
from quadcast.codec.encoder import AtlasEncoder, VideoSettings
from quadcast.render.atlas_texture import AtlasTexture

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


def _read(atlas: AtlasTexture) -> np.ndarray:
    """The texture's rows in the order GL stores them (row 0 first)."""
    w, h = atlas.size
    return np.frombuffer(atlas.texture.read(), np.uint8).reshape(h, w, 4)


def test_gpu_conversion_matches_the_cpu_one(ctx):
    picture = _picture()
    atlas = AtlasTexture(ctx)
    atlas.write(picture)
    gpu = _read(atlas)
    cpu = picture.to_rgb()
    assert gpu.shape == (H, W, 4) and (gpu[..., 3] == 255).all()
    diff = np.abs(gpu[..., :3].astype(int) - cpu)
    assert diff.mean() < 1.0 and diff.max() <= 6, (diff.mean(), diff.max())
    # and both are close to what was encoded (CRF 0: the conversions are the error)
    assert np.abs(gpu[..., :3].astype(int) - _source()).mean() < 1.5
    atlas.release()


def test_bottom_first_stores_the_rows_flipped(ctx):
    picture = _picture()
    top, bottom = AtlasTexture(ctx), AtlasTexture(ctx, bottom_first=True)
    top.write(picture)
    bottom.write(picture)
    assert np.array_equal(_read(top)[::-1], _read(bottom))
    top.release()
    bottom.release()


def test_a_new_size_replaces_the_texture(ctx):
    atlas = AtlasTexture(ctx)
    small = _picture(_source()[:10, :16])
    atlas.write(small)
    assert atlas.size == (16, 10)
    np.testing.assert_allclose(_read(atlas)[..., :3], small.to_rgb(), atol=6)
    atlas.write(_picture())
    assert atlas.size == (W, H)
    atlas.release()


@pytest.mark.parametrize("bad", [np.zeros((4, 6, 3), np.uint8), "picture"])
def test_bad_input_is_a_clear_error(ctx, bad):
    with pytest.raises(ValueError, match="AtlasTexture.write: need a YuvPicture, got"):
        AtlasTexture(ctx).write(bad)
