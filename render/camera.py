"""Poses, frusta and cameras: the coordinate conventions every stage shares.

World space is right-handed with +Y up. A camera looks down its local -Z with +Y up (OpenGL). A `Pose` is a
position plus a unit quaternion (x, y, z, w order, as scipy.spatial.transform.Rotation uses). Matrices are numpy
float64, row-major, acting on column vectors (``p_view = view @ p_world``); `gl_matrix` converts one for upload.
Clip space is OpenGL's (z in [-1, 1]); depth-buffer values are in [0, 1].
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

DEFAULT_IPD_M = 0.063


def _vec3(v, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected 3 finite numbers, got {v!r}")
    return a


@dataclass(frozen=True)
class Pose:
    """A rigid camera pose: world-space position (metres) and orientation (unit quaternion, xyzw)."""

    position: np.ndarray
    quat: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 0.0, 1.0]))

    def __post_init__(self):
        object.__setattr__(self, "position", _vec3(self.position, "Pose.position"))
        q = np.asarray(self.quat, dtype=np.float64).reshape(-1)
        norm = np.linalg.norm(q) if q.shape == (4,) else 0.0
        if q.shape != (4,) or not np.all(np.isfinite(q)) or not 1e-9 <= norm < np.inf:  # 1e200s overflow it
            raise ValueError(f"Pose.quat: expected a non-zero quaternion (x, y, z, w) of finite norm, got {self.quat!r}")
        object.__setattr__(self, "quat", q / norm)

    @classmethod
    def from_euler(cls, position, pitch_deg: float, yaw_deg: float, roll_deg: float = 0.0) -> "Pose":
        """QUASAR's trace convention: yaw about world Y, then pitch about the camera X, then roll."""
        rot = Rotation.from_euler("YXZ", [yaw_deg, pitch_deg, roll_deg], degrees=True)
        return cls(position, rot.as_quat())

    @classmethod
    def look_at(cls, eye, target, up=(0.0, 1.0, 0.0)) -> "Pose":
        eye, target, up = _vec3(eye, "eye"), _vec3(target, "target"), _vec3(up, "up")
        back = eye - target
        if np.linalg.norm(back) < 1e-12:
            raise ValueError("Pose.look_at: eye and target coincide")
        z = back / np.linalg.norm(back)
        x = np.cross(up, z)
        if np.linalg.norm(x) < 1e-9:  # looking straight along up: pick any perpendicular
            x = np.cross([1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 0.0, 1.0], z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        return cls(eye, Rotation.from_matrix(np.stack([x, y, z], axis=1)).as_quat())

    @property
    def rotation(self) -> Rotation:
        return Rotation.from_quat(self.quat)

    def rotation_matrix(self) -> np.ndarray:
        """The orientation as a 3x3 matrix (camera axes as columns), worked out once per pose: the renderer asks
        for view matrices many times a frame, and scipy's Rotation costs tens of microseconds a call."""
        m = self.__dict__.get("_rotation_matrix")
        if m is None:
            m = self.rotation.as_matrix()
            m.flags.writeable = False
            object.__setattr__(self, "_rotation_matrix", m)
        return m

    @property
    def forward(self) -> np.ndarray:
        return self.rotation.apply([0.0, 0.0, -1.0])

    def camera_to_world(self) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.rotation_matrix()
        m[:3, 3] = self.position
        return m

    def view_matrix(self) -> np.ndarray:
        """World -> view transform."""
        r = self.rotation_matrix()
        m = np.eye(4)
        m[:3, :3] = r.T
        m[:3, 3] = -r.T @ self.position
        return m

    def offset_local(self, offset) -> "Pose":
        """The same orientation, moved by `offset` expressed in the camera's own axes."""
        return Pose(self.position + self.rotation.apply(_vec3(offset, "offset")), self.quat)

    def stereo_eyes(self, ipd: float = DEFAULT_IPD_M) -> tuple["Pose", "Pose"]:
        """(left, right) eye poses, each half the inter-pupillary distance from this (head) pose."""
        if not ipd >= 0:
            raise ValueError(f"ipd must be >= 0 metres, got {ipd}")
        return self.offset_local([-ipd / 2, 0.0, 0.0]), self.offset_local([ipd / 2, 0.0, 0.0])

    def distance_to(self, other: "Pose") -> float:
        return float(np.linalg.norm(self.position - other.position))

    def angle_to_deg(self, other: "Pose") -> float:
        return float(np.degrees((self.rotation.inv() * other.rotation).magnitude()))


@dataclass(frozen=True)
class Frustum:
    """A perspective frustum given by its extents on the near plane (glFrustum's l, r, b, t, n, f)."""

    left: float
    right: float
    bottom: float
    top: float
    near: float = 0.1
    far: float = 100.0

    def __post_init__(self):
        if not (0 < self.near < self.far):
            raise ValueError(f"Frustum: need 0 < near < far, got near={self.near} far={self.far}")
        if not (self.left < self.right and self.bottom < self.top):
            raise ValueError(f"Frustum: empty extents l={self.left} r={self.right} b={self.bottom} t={self.top}")

    @classmethod
    def symmetric(cls, fovy_deg: float, aspect: float, near: float = 0.1, far: float = 100.0) -> "Frustum":
        if not 0 < fovy_deg < 180:
            raise ValueError(f"fovy must be in (0, 180) degrees, got {fovy_deg}")
        if not aspect > 0:
            raise ValueError(f"aspect must be > 0, got {aspect}")
        t = near * np.tan(np.radians(fovy_deg) / 2)
        return cls(-t * aspect, t * aspect, -t, t, near, far)

    @property
    def fovy_deg(self) -> float:
        return float(np.degrees(np.arctan(self.top / self.near) - np.arctan(self.bottom / self.near)))

    @property
    def aspect(self) -> float:
        return (self.right - self.left) / (self.top - self.bottom)

    def projection_matrix(self) -> np.ndarray:
        l, r, b, t, n, f = self.left, self.right, self.bottom, self.top, self.near, self.far
        return np.array([
            [2 * n / (r - l), 0, (r + l) / (r - l), 0],
            [0, 2 * n / (t - b), (t + b) / (t - b), 0],
            [0, 0, -(f + n) / (f - n), -2 * f * n / (f - n)],
            [0, 0, -1, 0],
        ])

    @property
    def unit_extents(self) -> tuple[float, float, float, float]:
        """(left, right, bottom, top) scaled to the plane at distance 1 (the signed tangents of the angles from the
        axis to each side): the `extents` that render/camera.glsl's `view_ray` takes with near = 1."""
        n = self.near
        return self.left / n, self.right / n, self.bottom / n, self.top / n

    def sphere_outside(self, centre, radius: float) -> bool:
        """Whether a sphere (`centre` in view space, -Z forward) lies wholly outside one of the frustum's six
        planes, so that no point inside the frustum is within `radius` of `centre`."""
        x, y, z = (float(c) for c in centre)
        l, r, b, t = self.unit_extents
        # inward normals of the side planes through the eye, (1, 0, l) for the left one and so on, then near, far
        sides = ((x + l * z) / np.hypot(1.0, l), (-x - r * z) / np.hypot(1.0, r),
                 (y + b * z) / np.hypot(1.0, b), (-y - t * z) / np.hypot(1.0, t), -z - self.near, z + self.far)
        return min(sides) < -radius

    def as_array(self) -> np.ndarray:
        return np.array([self.left, self.right, self.bottom, self.top, self.near, self.far])

    def linear_depth(self, depth01: np.ndarray) -> np.ndarray:
        """Depth-buffer values in [0, 1] -> positive view-space distance along -Z (far where d == 1)."""
        n, f = self.near, self.far
        z_ndc = 2.0 * np.asarray(depth01, dtype=np.float64) - 1.0
        return (2.0 * n * f / (f + n - z_ndc * (f - n))).astype(np.float32)


@dataclass(frozen=True)
class Camera:
    """A pose, a frustum and an image size: everything needed to render one view."""

    pose: Pose
    frustum: Frustum
    width: int
    height: int

    def __post_init__(self):
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Camera: image size must be positive, got {self.width}x{self.height}")

    @classmethod
    def perspective(cls, pose: Pose, width: int, height: int, fovy_deg: float = 60.0,
                    near: float = 0.1, far: float = 100.0) -> "Camera":
        return cls(pose, Frustum.symmetric(fovy_deg, width / height, near, far), int(width), int(height))

    def view_matrix(self) -> np.ndarray:
        return self.pose.view_matrix()

    @property
    def focal_px(self) -> tuple[float, float]:
        """(fx, fy): the focal length in pixels along x and along y, i.e. pixels per unit of x/z and of y/z.
        A point at view depth z shifted sideways by d metres moves fx * d / z pixels."""
        f = self.frustum
        return self.width * f.near / (f.right - f.left), self.height * f.near / (f.top - f.bottom)

    def projection_matrix(self) -> np.ndarray:
        return self.frustum.projection_matrix()

    def image_rays(self, px, py) -> np.ndarray:
        """Unit view-space rays through image points (pixels from the top-left corner), as render/quad.glsl's
        ray_dir: (l + (r - l) x / w, t + (b - t) y / h, -near), normalised; shape (..., 3)."""
        f = self.frustum
        px, py = np.asarray(px, np.float64), np.asarray(py, np.float64)
        r = np.stack([f.left + (f.right - f.left) * px / self.width,
                      f.top + (f.bottom - f.top) * py / self.height,
                      np.full(np.broadcast(px, py).shape, -f.near)], axis=-1)
        return r / np.linalg.norm(r, axis=-1, keepdims=True)

    def view_projection(self) -> np.ndarray:
        return self.projection_matrix() @ self.view_matrix()

    def with_pose(self, pose: Pose) -> "Camera":
        return Camera(pose, self.frustum, self.width, self.height)

    def to_array(self) -> np.ndarray:
        """16 float32: position (3), quaternion xyzw (4), frustum l, r, b, t, near, far (6), 3 zeros."""
        return np.r_[self.pose.position, self.pose.quat, self.frustum.as_array(), np.zeros(3)].astype(np.float32)

    @classmethod
    def from_array(cls, values, width: int, height: int) -> "Camera":
        a = np.asarray(values, dtype=np.float64).reshape(-1)
        if a.shape != (16,):
            raise ValueError(f"Camera.from_array: expected 16 numbers, got {a.size}")
        return cls(Pose(a[:3], a[3:7]), Frustum(*a[7:13]), int(width), int(height))

    def eccentricity_deg(self, gaze=(0.0, 0.0, -1.0)) -> np.ndarray:
        """(height, width) float32: the angle in degrees between each pixel centre's view ray and ``gaze`` (a
        view-space direction; default the view axis), top row first."""
        l, r, b, t = self.frustum.unit_extents
        x = l + (r - l) * (np.arange(self.width) + 0.5) / self.width
        y = t - (t - b) * (np.arange(self.height) + 0.5) / self.height
        g = np.asarray(gaze, np.float64)
        g = g / np.linalg.norm(g)
        xx, yy = np.meshgrid(x, y)
        cos = (xx * g[0] + yy * g[1] - g[2]) / np.sqrt(xx * xx + yy * yy + 1.0)
        return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))).astype(np.float32)

    def project(self, points_world: np.ndarray) -> np.ndarray:
        """World points (N, 3) -> pixel coordinates (N, 2), x right and y down from the top-left corner."""
        p = np.asarray(points_world, dtype=np.float64).reshape(-1, 3)
        clip = np.c_[p, np.ones(len(p))] @ self.view_projection().T
        ndc = clip[:, :2] / clip[:, 3:4]
        return np.c_[(ndc[:, 0] + 1) * 0.5 * self.width, (1 - ndc[:, 1]) * 0.5 * self.height]


def focal_length_px(pixels: float, fov_deg: float) -> float:
    """The focal length in pixels of a symmetric pinhole view whose field of view `fov_deg` spans `pixels` (the
    width with the horizontal field of view, or the height with the vertical one). With a camera at hand, use
    `Camera.focal_px`."""
    if not 0 < fov_deg < 180:
        raise ValueError(f"field of view must be in (0, 180) degrees, got {fov_deg}")
    return 0.5 * pixels / math.tan(math.radians(fov_deg) / 2.0)


def gl_matrix(m: np.ndarray) -> bytes:
    """A row-major numpy matrix as the column-major float32 bytes a GLSL mat4 uniform expects."""
    return np.ascontiguousarray(np.asarray(m, dtype=np.float32).T).tobytes()


def parse_size(text: str) -> tuple[int, int]:
    """'WxH' -> (W, H)."""
    try:
        w, h = (int(v) for v in str(text).lower().split("x"))
    except ValueError:
        raise ValueError(f"size must look like 960x540, got {text!r}") from None
    if w <= 0 or h <= 0 or w > 8192 or h > 8192:
        raise ValueError(f"size must be between 1x1 and 8192x8192, got {text!r}")
    return w, h
