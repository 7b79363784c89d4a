"""The client half of a streaming method: `FramePayload`s in, frames for the user's current pose out.

Every method client also says how its last render covered the display (:meth:`MethodClient.coverage`): per pixel,
whether it shows content reprojected from a received frame (:attr:`PixelCoverage.DRAWN`), only a fallback fill
that repeats the frame's edge pixels (:attr:`PixelCoverage.SMEARED`: ATW's clamp-to-edge outside the frame), or
nothing at all (:attr:`PixelCoverage.EMPTY`: the clear colour shows). Pixels that are not DRAWN are *holes*: what
the evaluation counts (``holes`` in frames.csv and summary.json). Holes that do not reach the display's border
(``holes_interior``: cracks and disocclusions inside the view) are told apart from those that do (mostly what
lies beyond the frame the server rendered, and sky).
"""
from __future__ import annotations

import enum
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from quadcast.protocol.frame import FramePayload
from quadcast.render.camera import Pose

__all__ = ["Coverage", "MethodClient", "PixelCoverage"]


class PixelCoverage(enum.IntEnum):
    """What one displayed pixel shows."""

    EMPTY = 0      # nothing drawn: the clear colour (black)
    SMEARED = 1    # only a fallback fill repeating edge pixels of the frame, not content for this direction
    DRAWN = 2      # content reprojected from a received frame (mesh, quads, or an in-frame warp)


@dataclass(frozen=True, eq=False)
class Coverage:
    """How one render covered the display: a :class:`PixelCoverage` per pixel, (H, W) uint8, top row first."""

    pixels: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.pixels)
        if p.ndim != 2 or p.dtype != np.uint8 or p.size == 0:
            raise ValueError(f"Coverage.pixels must be a non-empty (H, W) uint8 array, got {p.dtype} {p.shape}")
        if p.max() > PixelCoverage.DRAWN:
            raise ValueError(f"Coverage.pixels holds {int(p.max())}, not a PixelCoverage value")

    @classmethod
    def empty(cls, width: int, height: int) -> "Coverage":
        """Nothing drawn (a client before its first payload)."""
        return cls(np.zeros((height, width), np.uint8))

    @classmethod
    def from_masks(cls, drawn: np.ndarray, smeared: np.ndarray | None = None) -> "Coverage":
        """From boolean (H, W) masks: `drawn` wins over `smeared`; the rest is EMPTY."""
        drawn = np.asarray(drawn, bool)
        pixels = np.zeros(drawn.shape, np.uint8)
        if smeared is not None:
            pixels[np.asarray(smeared, bool)] = PixelCoverage.SMEARED
        pixels[drawn] = PixelCoverage.DRAWN
        return cls(pixels)

    @property
    def size(self) -> int:
        return int(self.pixels.size)

    @property
    def hole_pixels(self) -> int:
        """Pixels that show no content of their own (EMPTY or SMEARED)."""
        return int(np.count_nonzero(self.pixels != PixelCoverage.DRAWN))

    @property
    def holes(self) -> float:
        """Fraction of the display that is a hole (EMPTY or SMEARED), 0..1."""
        return self.hole_pixels / self.size

    @property
    def empty_fraction(self) -> float:
        """Fraction of the display where nothing was drawn at all."""
        return int(np.count_nonzero(self.pixels == PixelCoverage.EMPTY)) / self.size

    @property
    def smeared_fraction(self) -> float:
        """Fraction of the display filled only by repeating edge pixels."""
        return int(np.count_nonzero(self.pixels == PixelCoverage.SMEARED)) / self.size

    @property
    def interior_fraction(self) -> float:
        """Fraction of the display in holes that do not touch its border (8-connected regions of hole pixels)."""
        mask = self.hole_mask
        labels, count = ndimage.label(mask, structure=np.ones((3, 3), bool))
        if count == 0:
            return 0.0
        border = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        return int(np.count_nonzero(mask & ~np.isin(labels, border))) / self.size

    @property
    def hole_mask(self) -> np.ndarray:
        """(H, W) bool, True where the display shows no content of its own."""
        return self.pixels != PixelCoverage.DRAWN

    def figures(self) -> dict[str, float]:
        """The per-frame figures of the evaluation: ``holes``, ``holes_empty``, ``holes_smeared`` and
        ``holes_interior`` (fractions of the display)."""
        return {"holes": self.holes, "holes_empty": self.empty_fraction, "holes_smeared": self.smeared_fraction,
                "holes_interior": self.interior_fraction}


class MethodClient(ABC):
    """Keeps the last good state; a bad payload raises (ProtocolError / VideoError) and changes nothing."""

    name: str

    @abstractmethod
    def receive(self, payload: FramePayload) -> None:
        """Decode a payload and make it the current state."""

    @abstractmethod
    def render(self, pose: Pose) -> np.ndarray:
        """The displayed image (H, W, 3) uint8 for the user's current pose (black before the first payload)."""

    @abstractmethod
    def coverage(self) -> Coverage:
        """How the last :meth:`render` covered the display, read from what it drew (all EMPTY before any render
        and before the first payload)."""

    @property
    def needs_reference(self) -> bool:
        """True when the client cannot use residual frames until a reference frame arrives."""
        return False

    def warm_up(self, stereo: bool = False) -> None:
        """Before the first payload: run the method's receive and draw once on something made up and drop it, so
        that llvmpipe compiles the shaders before a real frame waits for them (the live client calls it before it
        connects); `stereo`: also what its stereo frames run. The state a payload would set is left as it was.
        The default does nothing."""

    def close(self) -> None:
        pass
