"""GL-free stand-ins for a method's two halves, for tests of the session core and its drivers."""
from __future__ import annotations

import numpy as np

from quadcast.protocol.errors import ProtocolError
from quadcast.protocol.frame import FramePayload, FrameStats, FrameType, Method
from quadcast.server.method import MethodServer


class StubServer(MethodServer):
    """A method server without GL: every `every`-th frame (and the first, if `first_reference`) self-contained, as
    if each were a reference; its frames are `size` bytes, or as big as its operating point's measured rate at its
    frame rate (times `scale`: another size or scene than the ladder's)."""

    def __init__(self, size: int = 1000, every: int = 3, scale: float = 1.0, first_reference: bool = False):
        self.frame_id, self.force, self.size, self.every, self.scale = 0, first_reference, size, every, scale
        self.rotation_misses: list = []     # what the driver told it before each frame (set_rotation_miss)
        self.gazes: list = []               # ... and each gaze it was given (set_gaze)

    def apply_operating_point(self, point):
        self.size = int(point.mbps * 1e6 / 8 / min(point.fps, 30.0) * self.scale)
        return True

    def set_gaze(self, gaze):
        self.gazes.append(tuple(float(v) for v in gaze))

    def set_rotation_miss(self, degrees):
        self.rotation_misses.append(degrees)

    def request_reference(self):
        self.force = True

    def encode(self, pose, t):
        sc = self.force or self.frame_id % self.every == 0
        self.force = False
        p = FramePayload(Method.QUASAR, self.frame_id, FrameType.REFERENCE if sc else FrameType.RESIDUAL, 0, t,
                         pose.position, pose.quat, b"\0" * self.size, b"", sc, FrameStats())
        self.frame_id += 1
        return p

    def close(self):
        pass


class StubClient:
    """A method client without GL that needs a reference after a lost frame."""

    needs_reference = False

    def __init__(self):
        self.last = -1
        self.stats = {}

    def receive(self, payload):
        if not payload.self_contained and payload.frame_id != self.last + 1:
            self.needs_reference = True
            raise ProtocolError(f"frame {payload.frame_id} follows {self.last}")
        self.needs_reference = False
        self.last = payload.frame_id

    def render(self, pose):
        return np.zeros((2, 2, 3), np.uint8)

    def coverage(self):
        from quadcast.client.method import Coverage
        return Coverage.empty(2, 2)
