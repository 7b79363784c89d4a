"""Image-quality metrics for comparing a displayed frame with the ground truth.

All metrics take two sRGB images as ``uint8`` arrays of shape ``(H, W, 3)``
(``reference`` = the ground-truth render at the true pose, ``test`` = what the
client displayed) and are CPU-only (no GL):

* :func:`flip` -- NVIDIA's FLIP (LDR-FLIP, via the official ``flip_evaluator``
  package), lower is better, 0 for identical images.  FLIP's Python API wants
  float images in ``[0, 1]``; with ``"LDR"`` it treats them as sRGB-encoded
  (``inputsRGB=True``) and linearises them itself, so the ``uint8`` values are
  only divided by 255 -- *not* converted to linear first.  (Passing ``uint8``
  straight in gives wrong scores, so this module never does.)
* :func:`ssim` -- scikit-image's SSIM over the three channels
  (``channel_axis=-1``, ``data_range=255``, skimage's default 7x7 uniform
  window), higher is better, 1 for identical images.
* :func:`psnr` -- scikit-image's PSNR with ``data_range=255``, in dB, higher is
  better.  Identical images have infinite PSNR; it is capped at
  :data:`PSNR_CAP_DB` (100 dB) so averages and JSON stay finite.

**Pixels per degree.**  FLIP models a viewer; by default (``ppd=None``) it uses
its own default of ~67 pixels per degree: a 0.7 m wide 3840-pixel monitor seen
from 0.7 m.  To score as seen in a headset instead, pass
``ppd=ppd_for_fov(width_px, hfov_deg)`` (pixels per degree at the image centre
of a pinhole camera).

Example::

    >>> ref = np.zeros((32, 32, 3), np.uint8)
    >>> s = compare(ref, ref)
    >>> (s.flip, s.ssim, s.psnr)
    (0.0, 1.0, 100.0)
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from quadcast.render.camera import focal_length_px

__all__ = [
    "PSNR_CAP_DB",
    "FLIP_DEFAULT_PPD",
    "ImageScores",
    "ppd_for_fov",
    "flip",
    "ssim",
    "psnr",
    "compare",
]

PSNR_CAP_DB = 100.0
"""PSNR reported for identical images (and the upper bound of every PSNR here), in dB."""

FLIP_DEFAULT_PPD = 67.0206451416
"""FLIP's default pixels per degree: 3840 px over 0.7 m, viewed from 0.7 m (what ``ppd=None`` means)."""

_SSIM_WIN = 7  # skimage's default window side; images must be at least this big


@dataclass(frozen=True)
class ImageScores:
    """The scores of one displayed frame against its ground truth.

    ``flip`` is the mean LDR-FLIP error (0 = identical, lower is better),
    ``ssim`` the mean SSIM (1 = identical), ``psnr`` in dB (capped at
    :data:`PSNR_CAP_DB`), ``flip_map`` the per-pixel FLIP error, float32
    ``(H, W)`` in ``[0, 1]``.
    """

    flip: float
    ssim: float
    psnr: float
    flip_map: np.ndarray

    def as_dict(self) -> dict[str, float]:
        """The scalar scores as ``{"flip", "ssim", "psnr"}`` (no error map), e.g. for a per-frame record."""
        return {"flip": self.flip, "ssim": self.ssim, "psnr": self.psnr}


def ppd_for_fov(width_px: int, hfov_deg: float) -> float:
    """Pixels per degree at the centre of a pinhole image ``width_px`` wide with horizontal field of view ``hfov_deg``.

    The focal length in pixels is ``f = (width_px / 2) / tan(hfov / 2)``
    (:func:`quadcast.render.camera.focal_length_px`); one degree at the centre
    spans ``f * tan(1 deg)`` pixels.
    """
    if not (isinstance(width_px, (int, np.integer)) and width_px > 0):
        raise ValueError(f"width_px must be a positive integer, got {width_px!r}")
    if not (math.isfinite(hfov_deg) and 0.0 < hfov_deg < 180.0):
        raise ValueError(f"hfov_deg must be in (0, 180) degrees, got {hfov_deg!r}")
    return focal_length_px(width_px, hfov_deg) * math.tan(math.radians(1.0))


def _check_pair(reference: np.ndarray, test: np.ndarray, min_side: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Validate two sRGB uint8 (H, W, 3) images of the same shape; return them as C-contiguous arrays."""
    for name, img in (("reference", reference), ("test", test)):
        if not isinstance(img, np.ndarray):
            raise TypeError(f"{name} must be a numpy array, got {type(img).__name__}")
        if img.dtype != np.uint8:
            raise ValueError(f"{name} must be sRGB uint8, got dtype {img.dtype}")
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"{name} must have shape (H, W, 3), got {img.shape}")
        if min(img.shape[:2]) < min_side:
            raise ValueError(f"{name} must be at least {min_side}x{min_side} pixels, got {img.shape[1]}x{img.shape[0]}")
    if reference.shape != test.shape:
        raise ValueError(f"reference and test shapes differ: {reference.shape} vs {test.shape}")
    return np.ascontiguousarray(reference), np.ascontiguousarray(test)


def _flip(reference: np.ndarray, test: np.ndarray, ppd: float | None) -> tuple[float, np.ndarray]:
    import flip_evaluator

    parameters: dict = {}
    if ppd is not None:
        # flip_evaluator calls sys.exit() on a bad ppd, so check it here.
        if not (math.isfinite(ppd) and ppd > 0):
            raise ValueError(f"ppd must be finite and > 0, got {ppd!r}")
        parameters["ppd"] = float(ppd)
    ref = reference.astype(np.float32) / np.float32(255.0)
    tst = test.astype(np.float32) / np.float32(255.0)
    error_map, mean, _ = flip_evaluator.evaluate(
        ref, tst, "LDR", inputsRGB=True, applyMagma=False, computeMeanError=True, parameters=parameters
    )
    error_map = np.asarray(error_map, dtype=np.float32).reshape(reference.shape[:2])
    return float(mean), error_map


def flip(reference: np.ndarray, test: np.ndarray, ppd: float | None = None) -> tuple[float, np.ndarray]:
    """LDR-FLIP of ``test`` against ``reference`` (both sRGB uint8 ``(H, W, 3)``).

    Returns ``(mean, error_map)``: the mean error (0 = identical, at most 1)
    and the per-pixel error as float32 ``(H, W)`` in ``[0, 1]``.  ``ppd`` is
    the assumed pixels per degree (None = FLIP's default, see
    :data:`FLIP_DEFAULT_PPD` and :func:`ppd_for_fov`).
    """
    reference, test = _check_pair(reference, test)
    return _flip(reference, test, ppd)


def ssim(reference: np.ndarray, test: np.ndarray) -> float:
    """Mean SSIM of ``test`` against ``reference`` (sRGB uint8 ``(H, W, 3)``, both sides >= 7 px); 1 = identical."""
    reference, test = _check_pair(reference, test, min_side=_SSIM_WIN)
    return _ssim(reference, test)


def _ssim(reference: np.ndarray, test: np.ndarray) -> float:
    from skimage.metrics import structural_similarity

    return float(structural_similarity(reference, test, channel_axis=-1, data_range=255))


def psnr(reference: np.ndarray, test: np.ndarray) -> float:
    """PSNR of ``test`` against ``reference`` in dB (sRGB uint8 ``(H, W, 3)``), capped at :data:`PSNR_CAP_DB`."""
    reference, test = _check_pair(reference, test)
    return _psnr(reference, test)


def _psnr(reference: np.ndarray, test: np.ndarray) -> float:
    from skimage.metrics import peak_signal_noise_ratio

    if np.array_equal(reference, test):
        return PSNR_CAP_DB  # MSE is 0: skimage would return inf with a divide-by-zero warning
    value = float(peak_signal_noise_ratio(reference, test, data_range=255))
    return min(value, PSNR_CAP_DB)


def compare(reference: np.ndarray, test: np.ndarray, ppd: float | None = None) -> ImageScores:
    """All metrics of ``test`` against ``reference`` (sRGB uint8 ``(H, W, 3)``, both sides >= 7 px) at once."""
    reference, test = _check_pair(reference, test, min_side=_SSIM_WIN)
    mean, error_map = _flip(reference, test, ppd)
    return ImageScores(flip=mean, ssim=_ssim(reference, test), psnr=_psnr(reference, test), flip_map=error_map)
