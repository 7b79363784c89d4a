"""The client half of a streaming method: `FramePayload`s in, frames for the user's current pose out."""
from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from quadcast.protocol.frame import FramePayload
from quadcast.render.camera import Pose


class MethodClient(ABC):
    """Keeps the last good state; a bad payload raises (ProtocolError / VideoError) and changes nothing."""

    name: str

    @abstractmethod
    def receive(self, payload: FramePayload) -> None:
        """Decode a payload and make it the current state."""

    @abstractmethod
    def render(self, pose: Pose) -> np.ndarray:
        """The displayed image (H, W, 3) uint8 for the user's current pose (black before the first payload)."""

    @property
    def needs_reference(self) -> bool:
        """True when the client cannot use residual frames until a reference frame arrives."""
        return False

    def close(self) -> None:
        pass
