"""The server half of a streaming method: poses in, `FramePayload`s out."""
from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from quadcast.protocol.frame import FramePayload
from quadcast.protocol.pose import gaze_direction
from quadcast.protocol.session import EncodeFrame
from quadcast.render.camera import Pose


class MethodServer(ABC):
    """Renders the scene for a (predicted) pose and encodes one frame. One instance per client session."""

    name: str

    @abstractmethod
    def encode(self, pose: Pose, t: float) -> FramePayload:
        """Render and encode the frame for `pose` at scene time `t` (seconds). `payload.stats` holds ms per stage."""

    def apply_operating_point(self, point) -> bool:
        """Make the next frames at ``point`` (a :class:`quadcast.protocol.rate.OperatingPoint`), switching only where
        the stream stays decodable. Returns False when the method has no such knobs (the default: it ignores it)."""
        return False

    def set_gaze(self, gaze) -> None:
        """The viewer's gaze direction (view space) for the next frames (methods without foveation ignore it)."""

    def set_rotation_miss(self, degrees: float | None) -> None:
        """How far the viewer's rotation strayed from the predicted one while recent frames were shown
        (:meth:`quadcast.protocol.session.ServerSession.rotation_miss_deg`; None: unknown). Methods that send
        content beyond the view may size it by this; the others ignore it."""

    def warm_up(self, frames: list[tuple[Pose, float]]) -> None:
        """Encode `frames` ((pose, scene time) pairs) and drop them, so that the shader variants this method's frames
        use are compiled before a session needs them (quadcast.server.app.SessionHost; llvmpipe compiles each on its
        first draw or dispatch). The instance is thrown away after. The default encodes them."""
        for pose, t in frames:
            self.encode(pose, t)

    def request_reference(self) -> None:
        """The client lost its reference state: make the next frame self-contained (default: every frame is)."""

    def encode_decision(self, decision: EncodeFrame) -> FramePayload:
        """The frame a session core's decision asks for (:class:`quadcast.protocol.session.EncodeFrame`): made
        self-contained if it says so, at its operating point, for its rotation miss and gaze (a decision without a
        gaze leaves the gaze where the last one put it: the view centre until one does), for its predicted pose and
        display time. The virtual-time replay and the live server's workers both encode through here."""
        if decision.reference:
            self.request_reference()
        if decision.point is not None:
            self.apply_operating_point(decision.point)
        self.set_rotation_miss(decision.rotation_miss_deg)
        if decision.gaze_deg is not None:
            self.set_gaze(gaze_direction(decision.gaze_deg))
        pose = Pose(np.asarray(decision.position, np.float64), np.asarray(decision.quat, np.float64))
        return self.encode(pose, decision.display_t)

    def close(self) -> None:
        pass
