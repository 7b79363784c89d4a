"""Scenes: meshes with materials and animations, one shadow-casting sun, point lights, and how to load them.

`load_scene(spec)` takes `builtin:courtyard`, `monastery` (pybullet_data's samurai monastery, with the `scenes`
extra), a scene file (.json / .toml) or any mesh file trimesh reads (.glb, .gltf, .obj, ...).

A scene file lists models with transforms and animations, the sun, point lights, ambient and sky colours:

    {"models": [{"path": "statue.glb", "position": [0, 0, -3], "rotation_deg": [0, 90, 0], "scale": 1.0,
                 "animation": {"type": "rotate", "axis": [0, 1, 0], "speed_deg_s": 30}},
                {"primitive": "box", "extents": [1, 1, 1], "color": [0.8, 0.2, 0.2]}],
     "sun": {"direction": [-0.4, -1, -0.3], "color": [1, 0.95, 0.9], "intensity": 3.0, "shadow_extent": 20},
     "point_lights": [{"position": [0, 3, 0], "color": [1, 0.8, 0.6], "intensity": 5, "radius": 8}],
     "ambient": [0.15, 0.16, 0.18], "sky": [0.55, 0.7, 0.9],
     "spawn": {"position": [0, 1.6, 4], "yaw_deg": 0}}

Animations: `rotate` (axis, speed_deg_s, optional center), `translate` (direction, amplitude, period_s: a
sinusoidal back-and-forth) and `orbit` (center, radius, period_s, axis, optional phase_deg). Every error names
the offending field, e.g. ``models[0].animation.type``.

Every scene has a *spawn point* (:class:`Spawn`: an eye position and a heading) where `--anchor spawn` puts a
recorded head trace (:func:`place_trace`): the built-ins declare theirs, a scene file may (``spawn``), and any other
scene gets :func:`default_spawn` -- in front of a lone object, or in the middle of a large one.
"""
from __future__ import annotations

import importlib
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from quadcast.render.traces import SPAWN, Anchor, Trace, TraceError, parse_anchor, resolve_trace


class SceneError(ValueError):
    """A scene could not be built or loaded; the message names the field or file."""


@dataclass
class Material:
    """Surface appearance. `texture` is sRGB uint8 (H, W, 3|4), sampled with mesh UVs or triplanar in object space."""

    base_color: np.ndarray = field(default_factory=lambda: np.ones(4, np.float32))
    texture: np.ndarray | None = None
    uv_mode: str = "mesh"  # "mesh" or "triplanar"
    uv_scale: float = 1.0
    specular: float = 0.2
    shininess: float = 32.0
    emissive: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))


KEPT_AREA = 0.75
"""`Mesh.simplified` keeps at least this fraction of the mesh's area."""


@dataclass
class Mesh:
    """Triangles in object space: positions/normals (N, 3) float32, uvs (N, 2) or None, indices (M, 3) uint32."""

    name: str
    positions: np.ndarray
    normals: np.ndarray
    indices: np.ndarray
    material: Material
    uvs: np.ndarray | None = None
    _simplified: dict = field(default_factory=dict, init=False, repr=False, compare=False)   # simplified()'s

    def __post_init__(self):
        self.positions = np.ascontiguousarray(self.positions, np.float32).reshape(-1, 3)
        self.normals = np.ascontiguousarray(self.normals, np.float32).reshape(-1, 3)
        self.indices = np.ascontiguousarray(self.indices, np.uint32).reshape(-1, 3)
        if len(self.normals) != len(self.positions):
            raise SceneError(f"mesh {self.name!r}: {len(self.normals)} normals for {len(self.positions)} positions")
        if self.uvs is not None:
            self.uvs = np.ascontiguousarray(self.uvs, np.float32).reshape(-1, 2)
            if len(self.uvs) != len(self.positions):
                raise SceneError(f"mesh {self.name!r}: {len(self.uvs)} uvs for {len(self.positions)} positions")
        if len(self.indices) and self.indices.max() >= len(self.positions):
            raise SceneError(f"mesh {self.name!r}: index {self.indices.max()} out of range")
        bad = ~np.isfinite(self.positions).all(axis=1)
        if bad.any():
            raise SceneError(f"mesh {self.name!r}: {int(bad.sum())} of {len(bad)} vertex positions are not finite "
                             f"(the first is vertex {int(np.argmax(bad))})")
        self._repair_normals()

    def _repair_normals(self) -> None:
        """Normals that are not finite or have no length (files have them; so do vertices whose faces' normals
        cancel) become the vertex normals of the mesh's faces. One still without a direction stays zero: the
        geometry pass then turns the surface towards the eye (render/material.glsl)."""
        n = self.normals
        bad = ~(np.isfinite(n).all(axis=1) & (np.einsum("ij,ij->i", n, n) > 1e-12))
        if not bad.any():
            return
        import trimesh   # only for a mesh that needs it
        faces = trimesh.Trimesh(self.positions, self.indices, process=False).vertex_normals
        n = n.copy()
        n[bad] = np.nan_to_num(faces[bad], nan=0.0, posinf=0.0, neginf=0.0)
        self.normals = np.ascontiguousarray(n, np.float32)

    def simplified(self, triangles: int) -> "Mesh":
        """This mesh decimated to about `triangles` triangles (quadric edge collapses, fast_simplification), with
        the same material; each vertex keeps the normal and UV of one of the original vertices collapsed into it,
        and at least `KEPT_AREA` of the surface is kept (with more triangles where needed). The mesh itself where
        it has no more than `triangles`; made once per count (the scene's renderers share it)."""
        if triangles < 1:
            raise ValueError(f"mesh {self.name!r}: cannot simplify to {triangles} triangles")
        if len(self.indices) <= triangles:
            return self
        if triangles not in self._simplified:
            # A decimation that loses much of the surface (small separate parts collapsed away), or every
            # triangle, is done again with twice the triangles, until the mesh itself is all that is left.
            mesh, area, target = self, self.area(), triangles
            while target < len(self.indices):
                mesh = self._decimated(target)
                if len(mesh.indices) and mesh.area() >= KEPT_AREA * area:
                    break
                mesh, target = self, 2 * target
            self._simplified[triangles] = mesh
        return self._simplified[triangles]

    def _decimated(self, triangles: int) -> "Mesh":
        import fast_simplification
        # Vertices at one position are welded first: a mesh stored as separate triangles shares no edge to
        # collapse, and the decimation would remove its triangles one by one.
        welded, first, inverse = np.unique(self.positions, axis=0, return_index=True, return_inverse=True)
        faces = inverse.reshape(-1)[self.indices].astype(np.int32)
        _, _, collapses = fast_simplification.simplify(welded, faces, target_count=int(triangles),
                                                       return_collapses=True)
        positions, faces, mapping = fast_simplification.replay_simplification(welded, faces, collapses)
        source = np.empty(len(positions), np.intp)
        source[mapping[::-1]] = np.arange(len(mapping))[::-1]     # the first welded vertex of each new one
        source = first[source]                                    # ... and its first original vertex
        return Mesh(self.name, positions, self.normals[source], faces, self.material,
                    None if self.uvs is None else self.uvs[source])

    def area(self) -> float:
        """The total area of the triangles (object space; trimesh's)."""
        import trimesh
        return float(trimesh.Trimesh(self.positions, self.indices, process=False).area)

    @classmethod
    def from_trimesh(cls, tm, material: Material, name: str | None = None) -> "Mesh":
        uvs = None
        visual = getattr(tm, "visual", None)
        if visual is not None and getattr(visual, "uv", None) is not None and len(visual.uv) == len(tm.vertices):
            uvs = np.asarray(visual.uv, np.float32).copy()
            uvs[:, 1] = 1.0 - uvs[:, 1]  # glTF/OBJ v points up; our textures are stored top row first
        return cls(name or tm.metadata.get("name", "mesh"), tm.vertices, tm.vertex_normals, tm.faces, material, uvs)


@dataclass
class Animation:
    """A rigid motion over time, applied before the object's static transform's translation part."""

    kind: str
    axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 1.0, 0.0]))
    speed_deg_s: float = 30.0
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))
    direction: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]))
    amplitude: float = 1.0
    radius: float = 1.0
    period_s: float = 4.0
    phase_deg: float = 0.0

    def matrix(self, t: float) -> np.ndarray:
        """The 4x4 world-space motion at time t (seconds), to be left-multiplied onto the object transform."""
        m = np.eye(4)
        if self.kind == "rotate":
            r = Rotation.from_rotvec(_unit(self.axis) * math.radians(self.speed_deg_s * t)).as_matrix()
            m[:3, :3] = r
            m[:3, 3] = self.center - r @ self.center
        elif self.kind == "translate":
            m[:3, 3] = _unit(self.direction) * self.amplitude * math.sin(2 * math.pi * t / self.period_s)
        elif self.kind == "orbit":
            angle = 2 * math.pi * t / self.period_s + math.radians(self.phase_deg)
            axis = _unit(self.axis)
            ref = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
            u = _unit(np.cross(axis, ref))
            v = np.cross(axis, u)
            m[:3, 3] = self.center + self.radius * (math.cos(angle) * u + math.sin(angle) * v)
        return m


@dataclass
class SceneObject:
    mesh: Mesh
    transform: np.ndarray = field(default_factory=lambda: np.eye(4))
    animation: Animation | None = None
    cast_shadow: bool = True
    object_id: int = 0

    def model_matrix(self, t: float) -> np.ndarray:
        if self.animation is None:
            return self.transform
        return self.animation.matrix(t) @ self.transform


@dataclass
class DirectionalLight:
    direction: np.ndarray  # the direction light travels (points from the sun into the scene)
    color: np.ndarray = field(default_factory=lambda: np.ones(3))
    intensity: float = 3.0
    shadow_extent: float = 20.0  # half-size of the orthographic shadow box (metres)
    shadow_center: np.ndarray = field(default_factory=lambda: np.zeros(3))


@dataclass
class PointLight:
    position: np.ndarray
    color: np.ndarray = field(default_factory=lambda: np.ones(3))
    intensity: float = 5.0
    radius: float = 8.0


@dataclass(frozen=True)
class Spawn:
    """Where a visitor starts in a scene: eye ``position`` (metres) and compass heading ``yaw_deg`` (degrees, as
    trace yaw: 0 looks down -Z, positive turns left)."""

    position: tuple[float, float, float]
    yaw_deg: float = 0.0

    def anchor(self) -> Anchor:
        return Anchor(self.position, self.yaw_deg)


SPAWN_EYE_HEIGHT = 1.6
"""Eye height (m) above a scene's floor of :func:`default_spawn`."""
LARGE_SCENE_M = 20.0
"""A scene whose ground-plane diagonal is at least this (m) is walked in (spawn in its middle); a smaller one is an
object looked at from outside."""


def default_spawn(bounds: np.ndarray, floor_at=None, fovy_deg: float = 60.0) -> Spawn:
    """The spawn point of a scene that declares none, from its (2, 3) bounds: in a large scene
    (:data:`LARGE_SCENE_M`) its middle at eye height above the floor, facing -Z; in front of a smaller one (its +Z
    side), far enough back for the whole box to fit a ``fovy_deg`` view, at eye height above the floor or the box's
    mid-height, whichever is higher, facing it (-Z). ``floor_at(x, z)`` gives the floor's height there (e.g.
    :meth:`Scene.floor_height`; None or a None result: the bounds' bottom)."""
    lo, hi = np.asarray(bounds, dtype=np.float64)
    mid = (lo + hi) / 2

    def eye(x: float, z: float) -> float:
        floor = floor_at(x, z) if floor_at is not None else None
        return (lo[1] if floor is None else floor) + SPAWN_EYE_HEIGHT
    if np.hypot(hi[0] - lo[0], hi[2] - lo[2]) >= LARGE_SCENE_M:
        return Spawn((float(mid[0]), float(eye(mid[0], mid[2])), float(mid[2])), 0.0)
    radius = float(np.linalg.norm(hi - lo) / 2)
    z = mid[2] + radius / math.sin(math.radians(fovy_deg) / 2)
    return Spawn((float(mid[0]), float(max(eye(mid[0], z), mid[1])), float(z)), 0.0)


@dataclass
class Scene:
    name: str
    objects: list[SceneObject]
    sun: DirectionalLight
    point_lights: list[PointLight] = field(default_factory=list)
    ambient: np.ndarray = field(default_factory=lambda: np.array([0.12, 0.13, 0.15]))
    sky: np.ndarray = field(default_factory=lambda: np.array([0.55, 0.70, 0.90]))
    spawn: Spawn | None = None     # None: default_spawn(bounds)

    MAX_POINT_LIGHTS = 16

    def __post_init__(self):
        if not self.objects:
            raise SceneError(f"scene {self.name!r} has no objects")
        if len(self.point_lights) > self.MAX_POINT_LIGHTS:
            raise SceneError(f"scene {self.name!r}: at most {self.MAX_POINT_LIGHTS} point lights, "
                             f"got {len(self.point_lights)}")
        for i, obj in enumerate(self.objects):
            obj.object_id = i + 1  # 0 means "nothing" in the G-buffer
        if self.spawn is None:
            self.spawn = default_spawn(self.bounds(), self.floor_height)

    @property
    def triangle_count(self) -> int:
        return int(sum(len(o.mesh.indices) for o in self.objects))

    @property
    def is_dynamic(self) -> bool:
        return any(o.animation is not None for o in self.objects)

    def floor_height(self, x: float, z: float) -> float | None:
        """The height of the lowest surface straight below or above (x, z) at t = 0 (the ground under a roof),
        or None when no triangle covers that point."""
        lowest = None
        point = np.array([x, z], dtype=np.float64)
        for o in self.objects:
            p = o.mesh.positions.astype(np.float64) @ o.transform[:3, :3].T + o.transform[:3, 3]
            tri = p[o.mesh.indices]                                   # (M, 3, 3)
            a, e1, e2 = tri[:, 0, [0, 2]], tri[:, 1, [0, 2]] - tri[:, 0, [0, 2]], tri[:, 2, [0, 2]] - tri[:, 0, [0, 2]]
            det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
            ok = np.abs(det) > 1e-12
            d = point - a
            with np.errstate(divide="ignore", invalid="ignore"):
                u = (d[:, 0] * e2[:, 1] - d[:, 1] * e2[:, 0]) / det
                v = (e1[:, 0] * d[:, 1] - e1[:, 1] * d[:, 0]) / det
                inside = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
            if inside.any():
                y = tri[inside, 0, 1] + u[inside] * (tri[inside, 1, 1] - tri[inside, 0, 1]) + v[inside] * (
                    tri[inside, 2, 1] - tri[inside, 0, 1])
                lowest = float(y.min()) if lowest is None else min(lowest, float(y.min()))
        return lowest

    def bounds(self) -> np.ndarray:
        """(2, 3) world-space bounding box at t = 0."""
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        for o in self.objects:
            p = o.mesh.positions @ o.transform[:3, :3].T + o.transform[:3, 3]
            lo, hi = np.minimum(lo, p.min(0)), np.maximum(hi, p.max(0))
        return np.stack([lo, hi])


def _unit(v) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v)
    return v / n if n > 0 else np.array([0.0, 1.0, 0.0])


def place_trace(trace: Trace, anchor: str | Anchor | None, scene: Scene | None = None, start_s: float = 0.0) -> Trace:
    """`trace` re-anchored into a scene (:meth:`Trace.anchored`): its pose `start_s` seconds after its first sample
    goes to `anchor` -- ``"spawn"`` (the scene's :class:`Spawn`; needs `scene`), ``"x,y,z[,yaw_deg]"`` or an
    :class:`Anchor` -- and the rest keeps its motion relative to that pose. ``None`` leaves the trace as it is."""
    if anchor is None:
        return trace
    if isinstance(anchor, str):
        anchor = parse_anchor(anchor)
    if anchor == SPAWN:
        if scene is None:
            raise TraceError("anchor 'spawn' needs a scene to take the spawn point from")
        anchor = scene.spawn.anchor()
    return trace.anchored(anchor.position, anchor.yaw_deg, at_s=start_s)


def scene_trace(trace_spec: str, scene: Scene | None = None, anchor: str | Anchor | None = None,
                start_s: float = 0.0, duration_s: float | None = None) -> Trace:
    """The trace `trace_spec` (``builtin:NAME`` or a QUASAR trace file) as `quadcast eval/render/predict` replay it:
    re-anchored into `scene` at its pose `start_s` seconds in (:func:`place_trace`), then cut to the window from
    `start_s` lasting `duration_s` (default: to its end)."""
    trace = place_trace(resolve_trace(trace_spec), anchor, scene, start_s)
    return trace.window(start_s, duration_s) if start_s or duration_s is not None else trace


def compose_transform(position=(0, 0, 0), rotation_deg=(0, 0, 0), scale=1.0) -> np.ndarray:
    """T * R * S, with R from XYZ Euler angles in degrees and a uniform or per-axis scale."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("XYZ", rotation_deg, degrees=True).as_matrix() @ np.diag(
        np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)))
    m[:3, 3] = position
    return m


# ----------------------------------------------------------------------------------------------- loading

BUILTIN_SCENES: dict[str, str] = {
    "courtyard": "quadcast.render.courtyard:courtyard_scene",
    "courtyard-static": "quadcast.render.courtyard:static_courtyard_scene",
}
"""The `builtin:<name>` scenes, as "module:function" making the scene. Those modules build scenes from this
module's types (they import it), so they are named here and imported when a scene is loaded, not imported here."""


def load_scene(spec: str | Path) -> Scene:
    """A scene from `builtin:courtyard`, `monastery`, a scene file (.json/.toml) or a mesh file."""
    spec = str(spec)
    if spec.startswith("builtin:"):
        name = spec.split(":", 1)[1]
        if name not in BUILTIN_SCENES:
            raise SceneError(f"unknown built-in scene {spec!r}; built-ins are "
                             + ", ".join(f"builtin:{n}" for n in BUILTIN_SCENES))
        module, function = BUILTIN_SCENES[name].split(":")
        return getattr(importlib.import_module(module), function)()
    if spec == "monastery":
        return monastery_scene()
    path = Path(spec)
    if not path.exists():
        raise SceneError(f"scene {spec!r}: no such file (built-ins: builtin:courtyard, monastery)")
    if path.suffix.lower() in (".json", ".toml"):
        return load_scene_file(path)
    return _mesh_file_scene(path)


def load_scene_file(path: str | Path) -> Scene:
    path = Path(path)
    try:
        text = path.read_text()
        data = tomllib.loads(text) if path.suffix.lower() == ".toml" else json.loads(text)
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as exc:
        raise SceneError(f"{path}: not valid {path.suffix[1:].upper()}: {exc}") from exc
    return scene_from_dict(data, base_dir=path.parent, name=path.stem)


_TOP_KEYS = {"models", "sun", "point_lights", "ambient", "sky", "name", "spawn"}
_MODEL_KEYS = {"path", "primitive", "extents", "radius", "size", "color", "position", "rotation_deg", "scale",
               "animation", "cast_shadow", "name"}
_ANIM_KEYS = {"type", "axis", "speed_deg_s", "center", "direction", "amplitude", "radius", "period_s", "phase_deg"}


def _check_keys(d: Any, allowed: set, where: str) -> dict:
    if not isinstance(d, dict):
        raise SceneError(f"{where}: expected a table/object, got {type(d).__name__}")
    unknown = sorted(set(d) - allowed)
    if unknown:
        raise SceneError(f"{where}: unknown field(s) {', '.join(unknown)}; allowed: {', '.join(sorted(allowed))}")
    return d


def _numbers(d: dict, key: str, where: str, n: int, default=None) -> np.ndarray:
    if key not in d:
        if default is None:
            raise SceneError(f"{where}.{key}: required")
        return np.asarray(default, dtype=np.float64)
    v = d[key]
    if (not isinstance(v, (list, tuple)) or len(v) != n
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
        raise SceneError(f"{where}.{key}: expected a list of {n} finite numbers, got {v!r}")
    return np.asarray(v, dtype=np.float64)


def _number(d: dict, key: str, where: str, default: float, lo: float = -math.inf, hi: float = math.inf,
            strict_lo: bool = False) -> float:
    v = d.get(key, default)
    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
        raise SceneError(f"{where}.{key}: expected a number, got {v!r}")
    if v < lo or v > hi or (strict_lo and v == lo):
        raise SceneError(f"{where}.{key}: {v} is out of range ({'>' if strict_lo else '>='} {lo}, <= {hi})")
    return float(v)


def _animation(d: dict, where: str) -> Animation:
    d = _check_keys(d, _ANIM_KEYS, where)
    kind = d.get("type")
    if kind not in ("rotate", "translate", "orbit"):
        raise SceneError(f"{where}.type: expected one of rotate, translate, orbit, got {kind!r}")
    return Animation(
        kind=kind,
        axis=_numbers(d, "axis", where, 3, [0, 1, 0]),
        speed_deg_s=_number(d, "speed_deg_s", where, 30.0),
        center=_numbers(d, "center", where, 3, [0, 0, 0]),
        direction=_numbers(d, "direction", where, 3, [1, 0, 0]),
        amplitude=_number(d, "amplitude", where, 1.0),
        radius=_number(d, "radius", where, 1.0, 0.0),
        period_s=_number(d, "period_s", where, 4.0, 0.0, strict_lo=True),
        phase_deg=_number(d, "phase_deg", where, 0.0),
    )


def scene_from_dict(data: dict, base_dir: Path = Path("."), name: str = "scene") -> Scene:
    """Build a scene from a parsed scene file; every error names the offending field."""
    import trimesh

    data = _check_keys(data, _TOP_KEYS, "scene")
    models = data.get("models")
    if not isinstance(models, list) or not models:
        raise SceneError("scene.models: expected a non-empty list of models")
    objects: list[SceneObject] = []
    for i, m in enumerate(models):
        where = f"models[{i}]"
        m = _check_keys(m, _MODEL_KEYS, where)
        if ("path" in m) == ("primitive" in m):
            raise SceneError(f"{where}: give exactly one of 'path' or 'primitive'")
        scale = m.get("scale", 1.0)
        if isinstance(scale, list):
            scale = _numbers(m, "scale", where, 3)
        else:
            scale = _number(m, "scale", where, 1.0, 0.0, strict_lo=True)
        transform = compose_transform(_numbers(m, "position", where, 3, [0, 0, 0]),
                                      _numbers(m, "rotation_deg", where, 3, [0, 0, 0]), scale)
        animation = _animation(m["animation"], f"{where}.animation") if "animation" in m else None
        cast = m.get("cast_shadow", True)
        if not isinstance(cast, bool):
            raise SceneError(f"{where}.cast_shadow: expected true or false, got {cast!r}")
        if "primitive" in m:
            color = _numbers(m, "color", where, 3, [0.8, 0.8, 0.8])
            material = Material(base_color=np.r_[color, 1.0].astype(np.float32))
            kind = m["primitive"]
            if kind == "box":
                tm = flat_shaded(trimesh.creation.box(extents=_numbers(m, "extents", where, 3, [1, 1, 1])))
            elif kind == "sphere":
                tm = trimesh.creation.icosphere(subdivisions=3,
                                                radius=_number(m, "radius", where, 0.5, 0, strict_lo=True))
            elif kind == "plane":
                s = _numbers(m, "size", where, 2, [10, 10])
                tm = _plane(s[0], s[1])
            else:
                raise SceneError(f"{where}.primitive: expected one of box, sphere, plane, got {kind!r}")
            meshes = [Mesh(m.get("name", kind), tm.vertices, tm.vertex_normals, tm.faces, material)]
        else:
            path = Path(m["path"])
            path = path if path.is_absolute() else base_dir / path
            if not path.exists():
                raise SceneError(f"{where}.path: no such file {str(path)!r}")
            meshes = load_meshes(path)
        for mesh in meshes:
            objects.append(SceneObject(mesh, transform, animation, cast))
    sun_d = _check_keys(data.get("sun", {}), {"direction", "color", "intensity", "shadow_extent", "center"}, "sun")
    sun = DirectionalLight(
        direction=_unit(_numbers(sun_d, "direction", "sun", 3, [-0.4, -1.0, -0.3])),
        color=_numbers(sun_d, "color", "sun", 3, [1.0, 0.96, 0.9]),
        intensity=_number(sun_d, "intensity", "sun", 3.0, 0.0),
        shadow_extent=_number(sun_d, "shadow_extent", "sun", 20.0, 0.0, strict_lo=True),
        shadow_center=_numbers(sun_d, "center", "sun", 3, [0, 0, 0]),
    )
    lights_d = data.get("point_lights", [])
    if not isinstance(lights_d, list):
        raise SceneError("scene.point_lights: expected a list")
    lights = []
    for i, ld in enumerate(lights_d):
        where = f"point_lights[{i}]"
        ld = _check_keys(ld, {"position", "color", "intensity", "radius"}, where)
        lights.append(PointLight(_numbers(ld, "position", where, 3), _numbers(ld, "color", where, 3, [1, 1, 1]),
                                 _number(ld, "intensity", where, 5.0, 0.0),
                                 _number(ld, "radius", where, 8.0, 0.0, strict_lo=True)))
    spawn = None
    if "spawn" in data:
        spawn_d = _check_keys(data["spawn"], {"position", "yaw_deg"}, "spawn")
        spawn = Spawn(tuple(_numbers(spawn_d, "position", "spawn", 3)), _number(spawn_d, "yaw_deg", "spawn", 0.0))
    return Scene(str(data.get("name", name)), objects, sun, lights,
                 _numbers(data, "ambient", "scene", 3, [0.12, 0.13, 0.15]),
                 _numbers(data, "sky", "scene", 3, [0.55, 0.70, 0.90]), spawn)


def flat_shaded(tm):
    """A copy of the trimesh with no vertex shared between faces, so each face's normal is its own (boxes, steps):
    trimesh's boxes share their corners, whose averaged normals would shade a box like a rounded blob."""
    tm = tm.copy()
    tm.unmerge_vertices()
    return tm


def _plane(w: float, d: float):
    """A horizontal w x d plane at y = 0 facing +Y, as a trimesh."""
    import trimesh
    v = np.array([[-w / 2, 0, -d / 2], [w / 2, 0, -d / 2], [w / 2, 0, d / 2], [-w / 2, 0, d / 2]])
    return trimesh.Trimesh(v, [[0, 2, 1], [0, 3, 2]], process=False)


def _image_array(img) -> np.ndarray | None:
    if img is None:
        return None
    a = np.asarray(img.convert("RGBA") if hasattr(img, "convert") else img)
    return a if a.ndim == 3 and a.dtype == np.uint8 else None


def _material_from_visual(visual) -> Material:
    """A Material from trimesh's visual (glTF PBR or OBJ/MTL simple material, or vertex/face colours)."""
    mat = Material()
    tm_mat = getattr(visual, "material", None)
    if tm_mat is not None:
        factor = getattr(tm_mat, "baseColorFactor", None)
        if factor is None:
            factor = getattr(tm_mat, "diffuse", None)
        if factor is not None:
            f = np.asarray(factor, dtype=np.float32).reshape(-1)
            if f.max() > 1.0:
                f = f / 255.0
            mat.base_color = np.r_[f[:3], f[3] if len(f) > 3 else 1.0].astype(np.float32)
        tex = getattr(tm_mat, "baseColorTexture", None)
        if tex is None:
            tex = getattr(tm_mat, "image", None)
        mat.texture = _image_array(tex)
    elif hasattr(visual, "main_color"):
        mat.base_color = (np.asarray(visual.main_color, np.float32) / 255.0)
    return mat


def load_meshes(path: str | Path) -> list[Mesh]:
    """All meshes of a glTF/GLB/OBJ/... file, node transforms applied, with their materials."""
    import trimesh
    try:
        loaded = trimesh.load(str(path), force="scene")
    except Exception as exc:  # trimesh raises many types for bad files
        raise SceneError(f"{path}: trimesh could not load it: {exc}") from exc
    meshes = []
    for i, tm in enumerate(loaded.dump(concatenate=False)):
        if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0:
            continue
        meshes.append(Mesh.from_trimesh(tm, _material_from_visual(tm.visual), f"{Path(path).stem}[{i}]"))
    if not meshes:
        raise SceneError(f"{path}: contains no triangle meshes")
    return meshes


def _mesh_file_scene(path: Path) -> Scene:
    """A lone mesh file lit by a default sun and sky."""
    meshes = load_meshes(path)
    scene = Scene(path.stem, [SceneObject(m) for m in meshes], DirectionalLight(_unit([-0.4, -1.0, -0.3])))
    lo, hi = scene.bounds()
    scene.sun.shadow_center = (lo + hi) / 2
    scene.sun.shadow_extent = float(np.linalg.norm(hi - lo) / 2) + 1.0
    return scene


MONASTERY_SPAWN_XZ = (-3.7, 1.5)
"""The middle of the monastery's main courtyard (x, z): open flagstones, > 5 m from any wall."""
MONASTERY_EYE_HEIGHT = 2.0


def monastery_scene() -> Scene:
    """pybullet_data's samurai monastery (125k triangles) with a sun and a few lamps; needs the `scenes` extra.
    Spawn: the middle of its main courtyard, 2 m eye height, facing +X (the courtyard's long open side)."""
    try:
        import pybullet_data
    except ImportError:
        raise SceneError("scene 'monastery' needs pybullet's data files: pip install 'quadcast[scenes]'") from None
    path = Path(pybullet_data.getDataPath()) / "samurai_monastry.obj"
    if not path.exists():
        raise SceneError(f"scene 'monastery': {path} is missing from pybullet_data")
    meshes = load_meshes(path)
    # The OBJ is already Y-up (floor at y = 0, roofs up to 30 m).
    x, z = MONASTERY_SPAWN_XZ
    floor = min(float(m.positions[:, 1].min()) for m in meshes)
    scene = Scene("monastery", [SceneObject(m, np.eye(4)) for m in meshes],
                  DirectionalLight(_unit([-0.5, -1.0, -0.35]), intensity=3.0),
                  [PointLight(np.array([lx, 2.5, lz]), np.array([1.0, 0.75, 0.45]), 4.0, 7.0)
                   for lx, lz in ((-4, -4), (4, -4), (-4, 4), (4, 4))],
                  spawn=Spawn((x, floor + MONASTERY_EYE_HEIGHT, z), -90.0))
    lo, hi = scene.bounds()
    scene.sun.shadow_center = (lo + hi) / 2
    scene.sun.shadow_extent = float(np.linalg.norm(hi - lo) / 2)
    return scene
