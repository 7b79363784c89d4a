"""`builtin:courtyard`: an arcaded courtyard made in code (no downloads), the default scene everywhere.
(`builtin:courtyard-static` is the same with its animations stopped; both are listed in
`quadcast.render.scene.BUILTIN_SCENES`.)

Layout (metres, +Y up): an open square |x|, |z| <= 8 paved with flagstones, a fountain at the origin, colonnades
with arches on all four sides (columns every 2.5 m on the lines |x| = 8 and |z| = 8), an upper gallery at 4 m with
thin railings, brick back walls at 11 m, a stair in the north arcade, crates and planters in the corners. Three
objects move: a sculpture spinning above the fountain, a lantern flying back and forth, a drone orbiting the
fountain. One shadow-casting sun and six point lights. Surfaces carry procedural textures so the video codec sees
real texture, and the columns, railings and crates give depth complexity: a 0.5 m step reveals disocclusions.
"""
from __future__ import annotations

import numpy as np
import trimesh
from scipy.ndimage import zoom

from quadcast.render.scene import (Animation, DirectionalLight, Material, Mesh, PointLight, Scene, SceneObject,
                                   Spawn, compose_transform, flat_shaded)

HALF = 8.0          # the open square's half-size
WALL = 11.0         # back walls of the arcades
GALLERY_Y = 4.0     # gallery floor height
SPACING = 2.5       # column spacing
COLUMN_R = 0.25
# Where `--anchor spawn` starts a head trace: the open square's south side at eye height, facing east (+X) along
# it. Its very centre holds the fountain (a 1.6 m eye would be inside its bowl); from here 11 m of open flagstones
# lie ahead and 3.5 m to the left before the fountain's basin, 2.5 m to the right before the arcade.
SPAWN = Spawn((-5.5, 1.6, 5.5), -90.0)


# ------------------------------------------------------------------------------------------ procedural textures

def _noise(size: int, cells: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth value noise in [0, 1], tileable enough for our use (cubic upsampling of a random grid)."""
    grid = rng.random((cells + 3, cells + 3))
    up = zoom(grid, size / cells, order=3, mode="grid-wrap")
    return np.clip(up[:size, :size], 0, 1)


def _fractal(size: int, rng: np.random.Generator, octaves=(4, 8, 16, 32, 64)) -> np.ndarray:
    out = sum(_noise(size, c, rng) / (i + 1) for i, c in enumerate(octaves))
    out -= out.min()
    return out / out.max()


def _to_u8(rgb: np.ndarray) -> np.ndarray:
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


def flagstone_texture(size=512, seed=1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = 4  # tiles per texture
    y, x = np.mgrid[0:size, 0:size] / size * n
    row = np.floor(y)
    x = x + 0.5 * (row % 2)  # running bond
    tile = (np.floor(x) % n) + n * row
    tone = rng.random(n * n + n)[tile.astype(int)]
    fx, fy = x % 1, y % 1
    grout = np.minimum(np.minimum(fx, 1 - fx), np.minimum(fy, 1 - fy)) < 0.03
    f = _fractal(size, rng)
    base = np.array([0.55, 0.50, 0.44]) * (0.75 + 0.35 * tone)[..., None] * (0.8 + 0.3 * f)[..., None]
    base[grout] = np.array([0.25, 0.23, 0.21]) * (0.8 + 0.3 * f[grout])[..., None]
    return _to_u8(base)


def brick_texture(size=512, seed=2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    rows, cols = 16, 8
    y, x = np.mgrid[0:size, 0:size] / size
    r = np.floor(y * rows)
    xx = x * cols + 0.5 * (r % 2)
    brick = (np.floor(xx) % cols) + cols * r
    tone = rng.random(rows * cols + cols)[brick.astype(int)]
    fx, fy = xx % 1, (y * rows) % 1
    mortar = (np.minimum(fx, 1 - fx) < 0.04) | (np.minimum(fy, 1 - fy) < 0.08)
    f = _fractal(size, rng)
    base = np.array([0.62, 0.30, 0.22]) * (0.7 + 0.4 * tone)[..., None] * (0.85 + 0.25 * f)[..., None]
    base[mortar] = np.array([0.72, 0.70, 0.64]) * (0.9 + 0.1 * f[mortar])[..., None]
    return _to_u8(base)


def sandstone_texture(size=512, seed=3) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = _fractal(size, rng)
    y = np.mgrid[0:size, 0:size][0] / size
    veins = 0.5 + 0.5 * np.sin(2 * np.pi * (y * 6 + 3 * f))
    base = np.array([0.82, 0.74, 0.58])[None, None] * (0.75 + 0.2 * f + 0.1 * veins)[..., None]
    return _to_u8(base)


def wood_texture(size=256, seed=4) -> np.ndarray:
    rng = np.random.default_rng(seed)
    f = _fractal(size, rng)
    x = np.mgrid[0:size, 0:size][1] / size
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (x * 12 + 2.5 * f))
    base = np.array([0.45, 0.28, 0.14])[None, None] * (0.7 + 0.35 * rings)[..., None]
    return _to_u8(base)


def tile_texture(size=256, seed=5, colors=((0.8, 0.15, 0.1), (0.95, 0.85, 0.2), (0.1, 0.35, 0.8))) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = 8
    y, x = np.mgrid[0:size, 0:size] / size * n
    idx = (np.floor(x) + np.floor(y) * 3).astype(int) % len(colors)
    base = np.asarray(colors)[idx] * (0.85 + 0.15 * _fractal(size, rng))[..., None]
    return _to_u8(base)


# -------------------------------------------------------------------------------------------------- geometry

def _box(extents, center) -> trimesh.Trimesh:
    return flat_shaded(trimesh.creation.box(extents=extents,
                                            transform=trimesh.transformations.translation_matrix(center)))


def _cylinder(radius, height, center, sections=24) -> trimesh.Trimesh:
    tm = trimesh.creation.cylinder(radius=radius, height=height, sections=sections,
                                   transform=trimesh.transformations.translation_matrix(center)
                                   @ trimesh.transformations.rotation_matrix(-np.pi / 2, [1, 0, 0]))
    return tm.smooth_shaded


def arch_panel(span: float, height: float, radius: float, depth: float, segments: int = 16) -> trimesh.Trimesh:
    """The wall between two columns with a semicircular opening: a `span` x `height` panel whose bottom edge
    carries a half-disc hole of `radius` centred at the origin, extruded `depth` along Z (centred)."""
    theta = np.linspace(np.pi, 0.0, segments + 1)
    inner = np.c_[radius * np.cos(theta), radius * np.sin(theta)]
    # Outer boundary: where the ray from the centre through each inner point meets the panel's rectangle.
    d = inner / radius
    with np.errstate(divide="ignore"):
        t_side = np.where(np.abs(d[:, 0]) > 1e-9, (span / 2) / np.abs(d[:, 0]), np.inf)
        t_top = np.where(d[:, 1] > 1e-9, height / d[:, 1], np.inf)
    outer = d * np.minimum(t_side, t_top)[:, None]
    verts, faces, normals = [], [], []

    def quad(a, b, c, e, n):
        base = len(verts)
        verts.extend([a, b, c, e])
        normals.extend([n] * 4)
        faces.extend([[base, base + 1, base + 2], [base, base + 2, base + 3]])

    z0, z1 = -depth / 2, depth / 2
    for i in range(segments):
        o0, o1, i0, i1 = outer[i], outer[i + 1], inner[i], inner[i + 1]
        quad([*i0, z1], [*i1, z1], [*o1, z1], [*o0, z1], [0, 0, 1])        # front
        quad([*o0, z0], [*o1, z0], [*i1, z0], [*i0, z0], [0, 0, -1])       # back
        n = -(i0 + i1) / np.linalg.norm(i0 + i1)                            # intrados faces the opening
        quad([*i0, z0], [*i1, z0], [*i1, z1], [*i0, z1], [n[0], n[1], 0])
    # Corners of the rectangle the ray-mapping skipped (top-left and top-right triangles).
    for sx in (-1, 1):
        k = np.argmin(np.abs(outer[:, 0] - sx * span / 2) + np.abs(outer[:, 1] - height))
        corner = np.array([sx * span / 2, height])
        for z, n in ((z1, [0, 0, 1]), (z0, [0, 0, -1])):
            base = len(verts)
            verts.extend([[*outer[k], z], [*corner, z], [*inner[k], z]])
            normals.extend([n] * 3)
            faces.append([base, base + 1, base + 2])
    tm = trimesh.Trimesh(np.array(verts), np.array(faces), vertex_normals=np.array(normals), process=False)
    return tm


def _concat(parts: list[trimesh.Trimesh]) -> trimesh.Trimesh:
    normals = np.concatenate([p.vertex_normals for p in parts])
    tm = trimesh.util.concatenate(parts)
    return trimesh.Trimesh(tm.vertices, tm.faces, vertex_normals=normals, process=False)


def _side_transforms() -> list[np.ndarray]:
    """Four rigid transforms taking the south side (z = +HALF, facing -Z into the court) to each side."""
    return [compose_transform(rotation_deg=(0, a, 0)) for a in (0, 90, 180, 270)]


def _colonnade() -> dict[str, list[trimesh.Trimesh]]:
    """One side's columns, arches, gallery slab, railing, back wall and ceiling, built on the south side."""
    parts: dict[str, list[trimesh.Trimesh]] = {"stone": [], "brick": [], "wood": [], "metal": []}
    xs = np.arange(-HALF + SPACING / 2 - SPACING * 0, HALF + 1e-6, SPACING)
    xs = xs[np.abs(xs) <= HALF - SPACING / 2 + 1e-6]
    col_h = 3.0
    for x in xs:
        parts["stone"].append(_cylinder(COLUMN_R, col_h, (x, col_h / 2, HALF)))
        parts["stone"].append(_box((0.7, 0.25, 0.7), (x, 0.125, HALF)))            # plinth
        parts["stone"].append(_box((0.65, 0.2, 0.65), (x, col_h - 0.1, HALF)))    # capital
    for a, b in zip(xs[:-1], xs[1:]):
        arch = arch_panel(SPACING, GALLERY_Y - col_h, SPACING / 2 - 0.3, 0.5)
        arch.apply_transform(trimesh.transformations.translation_matrix(((a + b) / 2, col_h, HALF)))
        parts["stone"].append(arch)
    width = 2 * HALF + 2 * (WALL - HALF)
    parts["stone"].append(_box((width, 0.3, WALL - HALF + 0.5), (0, GALLERY_Y + 0.15, (HALF + WALL) / 2)))
    # Gallery railing: thin posts and a handrail on the court edge.
    for x in np.arange(-HALF + 0.25, HALF, 0.5):
        parts["metal"].append(_box((0.04, 1.0, 0.04), (x, GALLERY_Y + 0.8, HALF - 0.1)))
    parts["wood"].append(_box((2 * HALF, 0.08, 0.12), (0, GALLERY_Y + 1.32, HALF - 0.1)))
    parts["wood"].append(_box((2 * HALF, 0.05, 0.05), (0, GALLERY_Y + 0.6, HALF - 0.1)))
    # Back wall (full height) and the upper wall with windows' worth of depth: pilasters.
    parts["brick"].append(_box((width, 8.0, 0.4), (0, 4.0, WALL + 0.2)))
    for x in np.arange(-HALF + SPACING / 2, HALF, SPACING):
        parts["stone"].append(_box((0.4, 8.0, 0.25), (x, 4.0, WALL - 0.1)))
    # Gallery roof.
    parts["stone"].append(_box((width, 0.25, WALL - HALF + 0.6), (0, 7.6, (HALF + WALL) / 2)))
    return parts


def courtyard_scene() -> Scene:
    stone = Material(texture=sandstone_texture(), uv_mode="triplanar", uv_scale=0.5, specular=0.15)
    brick = Material(texture=brick_texture(), uv_mode="triplanar", uv_scale=0.35, specular=0.05)
    wood = Material(texture=wood_texture(), uv_mode="triplanar", uv_scale=1.0, specular=0.3, shininess=24)
    metal = Material(base_color=np.array([0.12, 0.12, 0.13, 1], np.float32), specular=0.8, shininess=64)
    floor = Material(texture=flagstone_texture(), uv_mode="triplanar", uv_scale=0.25, specular=0.1)
    water = Material(base_color=np.array([0.15, 0.35, 0.5, 1], np.float32), specular=1.0, shininess=96)
    tiles = Material(texture=tile_texture(), uv_mode="triplanar", uv_scale=1.0, specular=0.5, shininess=48)
    materials = {"stone": stone, "brick": brick, "wood": wood, "metal": metal}

    objects: list[SceneObject] = []

    def add(name, tm, material, transform=None, animation=None, cast_shadow=True):
        objects.append(SceneObject(Mesh(name, tm.vertices, tm.vertex_normals, tm.faces, material),
                                   np.eye(4) if transform is None else transform, animation, cast_shadow))

    ground = trimesh.Trimesh([[-WALL, 0, -WALL], [WALL, 0, -WALL], [WALL, 0, WALL], [-WALL, 0, WALL]],
                             [[0, 2, 1], [0, 3, 2]], process=False)
    add("ground", ground, floor)

    side = _colonnade()
    for i, t in enumerate(_side_transforms()):
        for key, parts in side.items():
            add(f"colonnade{i}_{key}", _concat(parts), materials[key], t)

    # Stair in the north arcade, rising along +X to the gallery.
    steps = [_box((0.3, (k + 1) * 0.25, 1.6), (1.5 + 0.3 * k + 0.15, (k + 1) * 0.125, -(WALL - 1.0)))
             for k in range(16)]
    add("stair", _concat(steps), stone)

    # Fountain: basin wall, water, pillar, bowl.
    basin = _concat([_cylinder(1.5, 0.6, (0, 0.3, 0), 40)])
    add("fountain_basin", basin, stone)
    add("fountain_water", _cylinder(1.4, 0.02, (0, 0.5, 0), 40), water, cast_shadow=False)
    add("fountain_pillar", _concat([_cylinder(0.18, 1.6, (0, 0.8, 0)), _cylinder(0.6, 0.15, (0, 1.6, 0), 32)]),
        stone)

    # Crates and planters in the court's corners.
    rng = np.random.default_rng(7)
    for k, (cx, cz) in enumerate(((-7.0, -7.0), (7.0, -6.8), (-6.8, 7.0), (7.2, 7.1))):
        crates = []
        for j in range(3):
            s = 0.5 + 0.3 * rng.random()
            crates.append(_box((s, s, s), (cx + 0.7 * (j % 2) - 0.35, s / 2 + 0.55 * (j == 2), cz + 0.3 * j - 0.3)))
        add(f"crates{k}", _concat(crates), wood)
    for k, (cx, cz) in enumerate(((-3.0, 0.0), (3.0, 0.0))):
        add(f"planter{k}", _box((0.8, 0.7, 0.8), (cx, 0.35, cz)), brick)
        add(f"shrub{k}", trimesh.creation.icosphere(subdivisions=2, radius=0.55).apply_translation((cx, 1.15, cz)),
            Material(base_color=np.array([0.2, 0.45, 0.15, 1], np.float32), specular=0.05))

    # Animated objects.
    sculpture = _concat([_box((1.2, 0.12, 0.12), (0, 0, 0)), _box((0.12, 1.2, 0.12), (0, 0, 0)),
                         _box((0.12, 0.12, 1.2), (0, 0, 0)),
                         trimesh.creation.icosphere(subdivisions=2, radius=0.25)])
    add("sculpture", sculpture, tiles, compose_transform((0, 2.6, 0)),
        Animation("rotate", axis=np.array([0.3, 1.0, 0.2]), speed_deg_s=45.0, center=np.array([0, 2.6, 0])))
    lantern = _concat([_box((0.35, 0.5, 0.35), (0, 0, 0)), _box((0.45, 0.06, 0.45), (0, 0.28, 0))])
    add("lantern", lantern, tiles, compose_transform((0, 3.2, -4.0)),
        Animation("translate", direction=np.array([1.0, 0.15, 0.0]), amplitude=4.0, period_s=6.0))
    drone = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    add("drone", drone, tiles, np.eye(4),
        Animation("orbit", center=np.array([0, 1.9, 0]), radius=2.4, period_s=5.0, axis=np.array([0, 1.0, 0])))

    sun = DirectionalLight(np.array([-0.45, -1.0, -0.35]) / np.linalg.norm([-0.45, -1.0, -0.35]),
                           np.array([1.0, 0.95, 0.85]), 3.2, shadow_extent=15.5)
    warm, cool = np.array([1.0, 0.7, 0.4]), np.array([0.5, 0.7, 1.0])
    lights = [PointLight(np.array([x, 2.7, z]), warm, 3.0, 6.0) for x, z in ((-7, -7), (7, -7), (-7, 7), (7, 7))]
    lights += [PointLight(np.array([0.0, 2.5, 9.5]), cool, 2.5, 6.0), PointLight(np.array([0, 2.5, -9.5]), warm,
                                                                                2.5, 6.0)]
    return Scene("courtyard", objects, sun, lights, ambient=np.array([0.16, 0.17, 0.2]),
                 sky=np.array([0.55, 0.70, 0.92]), spawn=SPAWN)


def static_courtyard_scene() -> Scene:
    """The courtyard with its animations stopped (for tests and static-scene figures)."""
    scene = courtyard_scene()
    for obj in scene.objects:
        obj.animation = None
    scene.name = "courtyard-static"
    return scene
