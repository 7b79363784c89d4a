"""Server halves of the two baselines QUASAR compares against (§4.1.1-4.1.2): ATW and MeshWarp.

`ATWServer` renders the (predicted) pose and streams only its colour as H.264; the client re-orients it (asynchronous
time warp). `MeshWarpServer` streams the colour plus the view's depth map (`quadcast.protocol.depth`, BC4-like inverse depth
+ zstd) as the payload's `geometry`; the client turns the depth into a grid mesh and renders it from its own pose.
QUASAR runs MeshWarp at the display's 60 degrees, and also at 120 degrees rendered at twice the resolution so a
wider margin survives rotation; `MeshWarpServer(fovy=120)` does the latter by default (`render_scale`).

`payload.stats.ms` (not sent): ms per stage -- ``render`` (G-buffer + lighting + read-back), ``video`` (H.264
encode) and, for MeshWarp, ``depth`` (depth codec). A frame is self-contained when its access unit is an IDR.
"""
from __future__ import annotations

import time

from quadcast.protocol.depth import encode_depth
from quadcast.protocol.frame import FramePayload, FrameStats, FrameType, Method
from quadcast.protocol.methods import meshwarp_render_size
from quadcast.render.camera import Camera, Pose
from quadcast.render.renderer import DeferredRenderer
from quadcast.server.method import MethodServer
from quadcast.codec.encoder import AtlasEncoder, VideoSettings

__all__ = ["ATWServer", "MeshWarpServer", "DEFAULT_KEYFRAME_INTERVAL"]

DEFAULT_KEYFRAME_INTERVAL = 60  # frames between forced IDRs (one per second at 60 Hz)


def _ms_since(start: float) -> float:
    return (time.perf_counter() - start) * 1000.0


class _VideoBaselineServer(MethodServer):
    """Shared part: one camera, one H.264 stream, IDRs every `keyframe_interval` frames or on request."""

    method: Method

    def __init__(self, renderer: DeferredRenderer, width: int, height: int, fovy: float,
                 video: VideoSettings | None, keyframe_interval: int | None, near: float, far: float):
        if not isinstance(renderer, DeferredRenderer):
            raise TypeError(f"{type(self).__name__}: renderer must be a DeferredRenderer, "
                            f"got {type(renderer).__name__}")
        if int(width) <= 0 or int(height) <= 0 or int(width) % 2 or int(height) % 2:
            raise ValueError(f"{type(self).__name__}: frame size must be positive and even (H.264 4:2:0), "
                             f"got {width}x{height}")
        if keyframe_interval is not None and int(keyframe_interval) < 1:
            raise ValueError(f"{type(self).__name__}: keyframe_interval must be >= 1 or None, got {keyframe_interval}")
        self.renderer = renderer
        self.width, self.height, self.fovy = int(width), int(height), float(fovy)
        self.near, self.far = float(near), float(far)
        # Validates fovy / near / far.
        Camera.perspective(Pose([0.0, 0.0, 0.0]), self.width, self.height, self.fovy, self.near, self.far)
        self.keyframe_interval = None if keyframe_interval is None else int(keyframe_interval)
        self.encoder = AtlasEncoder(self.width, self.height, video or VideoSettings())
        self.frame_id = 0
        self._force_keyframe = True

    def camera(self, pose: Pose) -> Camera:
        """The server's render camera for `pose`."""
        return Camera.perspective(pose, self.width, self.height, self.fovy, self.near, self.far)

    def request_reference(self) -> None:
        """The client lost the video stream: make the next access unit an IDR."""
        self._force_keyframe = True

    def _keyframe_due(self) -> bool:
        due = self._force_keyframe or (self.keyframe_interval is not None
                                       and self.frame_id % self.keyframe_interval == 0)
        self._force_keyframe = False
        return due

    def _geometry(self, frame, ms: dict) -> bytes:
        return b""

    def encode(self, pose: Pose, t: float) -> FramePayload:
        """Render `pose` at scene time `t`, encode the colour (and the method's geometry)."""
        start = time.perf_counter()
        frame = self.renderer.render(self.camera(pose), t)
        ms = {"render": _ms_since(start)}
        start = time.perf_counter()
        encoded = self.encoder.encode(frame.color, keyframe=self._keyframe_due())
        ms["video"] = _ms_since(start)
        geometry = self._geometry(frame, ms)
        payload = FramePayload(self.method, self.frame_id, FrameType.REFERENCE, self.frame_id, float(t),
                               pose.position.copy(), pose.quat.copy(), encoded.data, geometry,
                               self_contained=encoded.keyframe, stats=FrameStats(ms=ms))
        self.frame_id += 1
        return payload

    def close(self) -> None:
        self.encoder.close()


class ATWServer(_VideoBaselineServer):
    """Asynchronous time warp baseline: the rendered colour of the predicted pose, as H.264, nothing else."""

    name = "atw"
    method = Method.ATW

    def __init__(self, renderer: DeferredRenderer, width: int, height: int, fovy: float = 60.0,
                 video: VideoSettings | None = None, keyframe_interval: int | None = DEFAULT_KEYFRAME_INTERVAL,
                 near: float = 0.1, far: float = 100.0):
        super().__init__(renderer, width, height, fovy, video, keyframe_interval, near, far)


class MeshWarpServer(_VideoBaselineServer):
    """MeshWarp baseline: colour as H.264 plus the linear depth map as a `quadcast.protocol.depth` blob (`geometry`).

    `width` x `height` is the display size the frame is meant for; the server renders at `render_scale` times it
    (default 2 when `fovy` > 90 degrees, as QUASAR's 120-degree MeshWarp, else 1), rounded to even sizes.
    """

    name = "meshwarp"
    method = Method.MESHWARP

    def __init__(self, renderer: DeferredRenderer, width: int, height: int, fovy: float = 60.0,
                 video: VideoSettings | None = None, keyframe_interval: int | None = DEFAULT_KEYFRAME_INTERVAL,
                 render_scale: float | None = None, depth_level: int = 3, near: float = 0.1, far: float = 100.0):
        if render_scale is None:
            render_scale = 2.0 if fovy > 90.0 else 1.0
        if not render_scale > 0:
            raise ValueError(f"MeshWarpServer: render_scale must be > 0, got {render_scale}")
        if not 1 <= int(depth_level) <= 22:
            raise ValueError(f"MeshWarpServer: depth_level (zstd) must be in 1..22, got {depth_level}")
        self.render_scale = float(render_scale)
        self.depth_level = int(depth_level)
        w, h = meshwarp_render_size(width, height, fovy, render_scale)
        super().__init__(renderer, w, h, fovy, video, keyframe_interval, near, far)

    def _geometry(self, frame, ms: dict) -> bytes:
        start = time.perf_counter()
        blob = encode_depth(frame.depth, level=self.depth_level)
        ms["depth"] = _ms_since(start)
        return blob
