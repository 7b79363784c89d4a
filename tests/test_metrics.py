"""Image-quality metrics: FLIP (official flip_evaluator), SSIM and PSNR on sRGB uint8 images."""
import math

import numpy as np
import pytest

from quadcast.sim.metrics import (
    FLIP_DEFAULT_PPD,
    PSNR_CAP_DB,
    ImageScores,
    compare,
    flip,
    ppd_for_fov,
    psnr,
    ssim,
)


def _image(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    """A smooth gradient with some texture, sRGB uint8 (H, W, 3)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w]
    base = np.stack([x * 255 / (w - 1), y * 255 / (h - 1), 128 + 60 * np.sin(x / 5.0)], axis=-1)
    return np.clip(base + rng.normal(0, 10, base.shape), 0, 255).astype(np.uint8)


def _noisy(img: np.ndarray, sigma: float, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.clip(img + rng.normal(0, sigma, img.shape), 0, 255).astype(np.uint8)


def test_identical_images_score_perfectly():
    img = _image()
    mean, error_map = flip(img, img)
    assert mean == 0.0
    assert error_map.shape == img.shape[:2] and error_map.dtype == np.float32
    assert not error_map.any()
    assert ssim(img, img) == pytest.approx(1.0)
    assert psnr(img, img) == PSNR_CAP_DB


def test_flip_grows_with_noise_and_ssim_psnr_fall():
    img = _image()
    scores = [compare(img, _noisy(img, s)) for s in (2.0, 8.0, 32.0)]
    flips = [s.flip for s in scores]
    assert 0.0 < flips[0] < flips[1] < flips[2] < 1.0
    assert 1.0 > scores[0].ssim > scores[1].ssim > scores[2].ssim
    assert scores[0].psnr > scores[1].psnr > scores[2].psnr
    for s in scores:
        assert isinstance(s, ImageScores)
        assert s.flip_map.shape == img.shape[:2]
        assert 0.0 <= s.flip_map.min() and s.flip_map.max() <= 1.0
        assert s.flip == pytest.approx(float(s.flip_map.mean()), rel=1e-4)
        assert set(s.as_dict()) == {"flip", "ssim", "psnr"}


def test_flip_localises_the_error():
    img = _image()
    test = img.copy()
    test[10:20, 30:40] = 255 - test[10:20, 30:40]
    _, error_map = flip(img, test)
    inside = error_map[10:20, 30:40].mean()
    far = error_map[30:, :20].mean()
    assert inside > 0.3 and far < 0.01


def test_flip_depends_on_pixels_per_degree():
    """Fewer pixels per degree make fine-grained errors more visible; ppd_for_fov reproduces FLIP's default."""
    img = _image()
    test = _noisy(img, 12.0)
    default, _ = flip(img, test)
    assert flip(img, test, ppd=FLIP_DEFAULT_PPD)[0] == pytest.approx(default, rel=1e-5)
    assert flip(img, test, ppd=20.0)[0] > default
    # FLIP's default: 3840 px across a 0.7 m display seen from 0.7 m.
    hfov = 2 * math.degrees(math.atan(0.35 / 0.7))
    assert ppd_for_fov(3840, hfov) == pytest.approx(FLIP_DEFAULT_PPD, rel=1e-3)
    assert ppd_for_fov(1920, 90.0) == pytest.approx(960 * math.tan(math.radians(1)))


def test_flip_treats_uint8_as_srgb_not_raw():
    """uint8 levels are scaled to [0, 1] for FLIP: one level apart is a small error, black vs grey a large one.

    (Raw uint8 handed to flip_evaluator is clamped to [0, 1]: level 1 would count as white and levels
    100 vs 101 as identical.)
    """
    def flat(level: int) -> np.ndarray:
        return np.full((24, 32, 3), level, np.uint8)

    black_vs_1, _ = flip(flat(0), flat(1))
    assert 0.0 < black_vs_1 < 0.05
    grey_step, _ = flip(flat(100), flat(101))
    assert 0.0 < grey_step < 0.05
    black_vs_grey, _ = flip(flat(0), flat(128))
    assert black_vs_grey > 0.5
    assert flip(flat(0), flat(64))[0] < black_vs_grey


def test_psnr_of_a_known_mse():
    ref = np.full((16, 16, 3), 100, np.uint8)
    test = ref.copy()
    test[::2] += 10  # half the pixels off by 10 -> MSE 50
    expected = 10 * math.log10(255.0**2 / 50.0)
    assert psnr(ref, test) == pytest.approx(expected, abs=1e-9)
    assert compare(ref, test).psnr == pytest.approx(expected, abs=1e-9)


def test_ssim_is_symmetric_and_bounded():
    a, b = _image(), _noisy(_image(), 20.0)
    assert ssim(a, b) == pytest.approx(ssim(b, a))
    assert -1.0 <= ssim(a, b) < 1.0


@pytest.mark.parametrize(
    "ref, test, match",
    [
        (np.zeros((16, 16, 3), np.uint8), np.zeros((16, 18, 3), np.uint8), "shapes differ"),
        (np.zeros((16, 16, 4), np.uint8), np.zeros((16, 16, 4), np.uint8), r"reference must have shape \(H, W, 3\)"),
        (np.zeros((16, 16), np.uint8), np.zeros((16, 16), np.uint8), r"must have shape \(H, W, 3\)"),
        (np.zeros((16, 16, 3), np.float32), np.zeros((16, 16, 3), np.uint8), "reference must be sRGB uint8"),
        (np.zeros((16, 16, 3), np.uint8), np.zeros((16, 16, 3), np.uint16), "test must be sRGB uint8"),
    ],
)
def test_bad_inputs_raise_value_error(ref, test, match):
    for fn in (flip, ssim, psnr, compare):
        with pytest.raises(ValueError, match=match):
            fn(ref, test)


def test_other_errors():
    img = np.zeros((16, 16, 3), np.uint8)
    with pytest.raises(TypeError, match="test must be a numpy array"):
        flip(img, img.tolist())
    tiny = np.zeros((4, 16, 3), np.uint8)
    with pytest.raises(ValueError, match="at least 7x7"):
        ssim(tiny, tiny)
    assert psnr(tiny, tiny) == PSNR_CAP_DB  # PSNR and FLIP work on small images
    for bad in (0.0, -3.0, float("nan")):
        with pytest.raises(ValueError, match="ppd must be finite and > 0"):
            flip(img, img, ppd=bad)
    with pytest.raises(ValueError, match="hfov_deg"):
        ppd_for_fov(100, 180.0)
    with pytest.raises(ValueError, match="width_px"):
        ppd_for_fov(0, 90.0)


def test_non_contiguous_views_are_accepted():
    img = _image(48, 128)
    view = img[:, ::2]
    assert not view.flags.c_contiguous
    mean, error_map = flip(view, view.copy())
    assert mean == 0.0 and error_map.shape == (48, 64)
    noisy = _noisy(np.ascontiguousarray(view), 8.0)
    assert flip(view, noisy)[0] == pytest.approx(flip(np.ascontiguousarray(view), noisy)[0])
