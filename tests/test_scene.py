import json

import numpy as np
import pytest
import trimesh

from quadcast.render.scene import SceneError, load_scene, scene_from_dict


def test_builtin_courtyard_has_what_the_card_asks(courtyard):
    assert courtyard.triangle_count > 5000
    animated = [o for o in courtyard.objects if o.animation is not None]
    assert {o.animation.kind for o in animated} == {"rotate", "translate", "orbit"}
    assert len(courtyard.point_lights) >= 4
    assert sum(o.mesh.material.texture is not None for o in courtyard.objects) >= 4
    # Animated objects really move.
    for o in animated:
        assert not np.allclose(o.model_matrix(0.0), o.model_matrix(1.0))


def test_scene_file_json_and_toml(tmp_path):
    obj = tmp_path / "box.obj"
    trimesh.creation.box(extents=[1, 2, 1]).export(obj)
    spec = {"models": [{"path": "box.obj", "position": [0, 1, -3],
                        "animation": {"type": "orbit", "radius": 2, "period_s": 3}},
                       {"primitive": "plane", "size": [10, 10], "color": [0.5, 0.5, 0.5]}],
            "point_lights": [{"position": [0, 3, 0]}], "sun": {"intensity": 2.0}}
    (tmp_path / "s.json").write_text(json.dumps(spec))
    scene = load_scene(tmp_path / "s.json")
    assert len(scene.objects) == 2 and scene.objects[0].animation.kind == "orbit"
    (tmp_path / "s.toml").write_text('[[models]]\nprimitive = "sphere"\nradius = 0.5\n'
                                     '[sun]\ndirection = [0, -1, 0]\n')
    assert load_scene(tmp_path / "s.toml").objects[0].mesh.name == "sphere"


@pytest.mark.parametrize("spec, message", [
    ({}, "scene.models"),
    ({"models": [{"primitive": "cone"}]}, r"models\[0\].primitive"),
    ({"models": [{"primitive": "box", "position": [0, 1]}]}, r"models\[0\].position"),
    ({"models": [{"primitive": "box", "animation": {"type": "spin"}}]}, r"models\[0\].animation.type"),
    ({"models": [{"primitive": "box", "animation": {"type": "orbit", "period_s": 0}}]}, "period_s"),
    ({"models": [{"primitive": "box", "colour": [1, 0, 0]}]}, "unknown field.*colour"),
    ({"models": [{"path": "missing.glb"}]}, r"models\[0\].path"),
    ({"models": [{"primitive": "box"}], "point_lights": [{"color": [1, 1, 1]}]}, r"point_lights\[0\].position"),
    ({"models": [{"primitive": "box"}], "sun": {"intensity": "bright"}}, "sun.intensity"),
])
def test_scene_file_errors_name_the_field(tmp_path, spec, message):
    with pytest.raises(SceneError, match=message):
        scene_from_dict(spec, base_dir=tmp_path)


def test_builtin_scenes_load_without_an_import_cycle():
    """scene.py names the built-in scene makers without importing them; courtyard.py imports scene.py only."""
    import subprocess
    import sys
    code = ("import sys; import quadcast.render.scene as s; assert 'quadcast.render.courtyard' not in sys.modules; "
            "import quadcast.render.courtyard as c; assert not hasattr(c, 'BUILTIN_SCENES'); "
            "scene = s.load_scene('builtin:courtyard-static'); "
            "assert scene.name == 'courtyard-static' and all(o.animation is None for o in scene.objects)")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_bad_scene_specs(tmp_path):
    with pytest.raises(SceneError, match="builtin:courtyard"):
        load_scene("builtin:nowhere")
    with pytest.raises(SceneError, match="no such file"):
        load_scene(tmp_path / "nope.glb")
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(SceneError, match="not valid JSON"):
        load_scene(tmp_path / "bad.json")


def test_gltf_textured_mesh_round_trip(tmp_path):
    """A textured GLB written by trimesh loads with its UVs and base-colour texture."""
    from PIL import Image
    box = trimesh.creation.box()
    uv = np.c_[(box.vertices[:, 0] + 0.5), (box.vertices[:, 1] + 0.5)]
    img = Image.fromarray(np.full((8, 8, 3), (200, 30, 30), np.uint8))
    box.visual = trimesh.visual.TextureVisuals(uv=uv, image=img)
    box.export(tmp_path / "box.glb")
    scene = load_scene(tmp_path / "box.glb")
    mesh = scene.objects[0].mesh
    assert mesh.uvs is not None and mesh.material.texture is not None
    assert mesh.material.texture[..., 0].mean() > 150


def test_mesh_normals_without_a_direction_are_repaired_and_bad_positions_refused():
    """Zero or NaN normals (files have them) become the faces' normals; the others are kept as given; a vertex
    position that is not finite is an error naming the mesh."""
    from quadcast.render.scene import Material, Mesh
    box = trimesh.creation.box()
    normals = np.array(box.vertex_normals, np.float32) * 2.0     # not unit: kept as given
    normals[0] = 0.0
    normals[1] = np.nan
    mesh = Mesh("box", box.vertices, normals, box.faces, Material())
    assert np.allclose(mesh.normals[:2], box.vertex_normals[:2], atol=1e-6)
    assert np.array_equal(mesh.normals[2:], normals[2:])
    positions = np.array(box.vertices)
    positions[5, 1] = np.inf
    with pytest.raises(SceneError, match=r"'box': 1 of 8 vertex positions are not finite \(the first is vertex 5\)"):
        Mesh("box", positions, box.vertex_normals, box.faces, Material())


def test_box_primitive_faces_are_flat(courtyard):
    """A scene file's box is shaded as a box: each corner's normal is its own face's, not the average of the three
    faces that meet there (which shaded it like a rounded blob and tilted the quads made from it); the built-in
    courtyard's boxes are made the same way."""
    planter = next(o.mesh for o in courtyard.objects if o.mesh.name == "planter0")
    box = scene_from_dict({"models": [{"primitive": "box", "extents": [1, 2, 3]}]}).objects[0].mesh
    for mesh in (box, planter):
        tri = mesh.positions[mesh.indices]
        face_normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        face_normals /= np.linalg.norm(face_normals, axis=1, keepdims=True)
        assert np.allclose(mesh.normals[mesh.indices], face_normals[:, None, :], atol=1e-5), mesh.name


def test_simplified_meshes_keep_their_surface_and_their_vertices_attributes():
    """`Mesh.simplified`: about the triangles asked for, at least KEPT_AREA of the area, each vertex with the normal
    and UV of an original vertex; a mesh stored as separate triangles (no shared vertex) is welded first, so it
    keeps its surface; a mesh already small enough is itself; each count is made once."""
    from quadcast.render.scene import KEPT_AREA, Material, Mesh
    ico = trimesh.creation.icosphere(4)                      # 5120 triangles on the unit sphere
    mesh = Mesh("ico", ico.vertices, ico.vertex_normals, ico.faces, Material(), uvs=ico.vertices[:, :2] + 1.0)
    coarse = mesh.simplified(500)
    assert 400 <= len(coarse.indices) <= 600 and coarse.area() >= KEPT_AREA * mesh.area()
    assert np.abs(np.linalg.norm(coarse.positions, axis=1) - 1.0).max() < 0.05
    originals = {tuple(v) for v in np.c_[mesh.normals, mesh.uvs].round(6)}
    assert {tuple(v) for v in np.c_[coarse.normals, coarse.uvs].round(6)} <= originals
    assert mesh.simplified(500) is coarse and mesh.simplified(6000) is mesh
    soup = ico.vertices[ico.faces].reshape(-1, 3)
    separate = Mesh("soup", soup, np.repeat(ico.face_normals, 3, axis=0), np.arange(len(soup)).reshape(-1, 3),
                    Material())
    welded = separate.simplified(500)
    assert len(welded.indices) <= 600 and welded.area() >= 0.95 * separate.area()
    with pytest.raises(ValueError, match="cannot simplify to 0 triangles"):
        mesh.simplified(0)
    flat = Mesh("flat", np.zeros((100, 3)), np.tile([0.0, 0.0, 1.0], (100, 1)),
                np.random.default_rng(0).integers(0, 100, (600, 3)), Material())
    assert flat.simplified(60) is flat                      # no area to keep: not decimated to nothing


# ------------------------------------------------------------------------------------------ spawn points

def test_spawn_points_and_traces_placed_there(tmp_path, courtyard):
    from quadcast.render.scene import Spawn, default_spawn, place_trace, scene_trace
    from quadcast.render.traces import TraceError, builtin_trace, heading_deg

    # The courtyard's spawn is on open ground at eye height, clear of the fountain in the middle.
    x, y, z = courtyard.spawn.position
    assert y == pytest.approx(1.6) and np.hypot(x, z) > 3.0 and max(abs(x), abs(z)) < 8.0 - 1.0
    walk = builtin_trace("walk")
    placed = place_trace(walk, "spawn", courtyard)
    np.testing.assert_allclose(placed.positions[0], courtyard.spawn.position, atol=1e-9)
    assert heading_deg(placed.rotations[0]) == pytest.approx(courtyard.spawn.yaw_deg, abs=1e-3)
    assert place_trace(walk, None, courtyard) is walk
    moved = place_trace(walk, "1,2,3", start_s=1.0)
    np.testing.assert_allclose(moved.pose_at(walk.times[0] + 1.0)[0], [1, 2, 3], atol=1e-9)
    with pytest.raises(TraceError, match="needs a scene"):
        place_trace(walk, "spawn")
    # scene_trace: the window from --start, anchored at its first pose.
    cut = scene_trace("builtin:walk", courtyard, "spawn", start_s=2.0, duration_s=1.0)
    assert cut.duration == pytest.approx(1.0)
    np.testing.assert_allclose(cut.positions[0], courtyard.spawn.position, atol=1e-9)

    # A scene file declares one; a lone object gets one in front of it that sees all of it; a large one its middle.
    (tmp_path / "s.json").write_text(json.dumps({"models": [{"primitive": "box"}],
                                                 "spawn": {"position": [1, 2, 3], "yaw_deg": 45}}))
    assert load_scene(tmp_path / "s.json").spawn == Spawn((1.0, 2.0, 3.0), 45.0)
    (tmp_path / "bad.json").write_text(json.dumps({"models": [{"primitive": "box"}], "spawn": {"position": [1, 2]}}))
    with pytest.raises(SceneError, match="spawn.position"):
        load_scene(tmp_path / "bad.json")
    box = default_spawn(np.array([[-1.0, 0.0, -1.0], [1.0, 2.0, 1.0]]))
    assert box.position[0] == 0.0 and box.position[1] == pytest.approx(1.6) and box.yaw_deg == 0.0
    radius = np.sqrt(3.0)
    assert box.position[2] - 0.0 >= radius / np.sin(np.radians(30)) - 1e-9     # the whole box fits 60°
    hall = default_spawn(np.array([[-30.0, -1.0, -20.0], [30.0, 10.0, 20.0]]))
    assert hall.position == pytest.approx((0.0, 0.6, 0.0))
    # An open space whose pillars reach below the ground: eye height above the ground, not above the bounds.
    (tmp_path / "open.json").write_text(json.dumps({"models": [
        {"primitive": "plane", "size": [60, 60]}, {"primitive": "box", "extents": [1, 6, 1], "position": [10, 1, 0]},
        {"primitive": "box", "extents": [4, 0.5, 4], "position": [0, 8, 0]}]}))       # and a roof above the middle
    scene = load_scene(tmp_path / "open.json")
    assert scene.bounds()[0][1] == pytest.approx(-2.0) and scene.floor_height(0.0, 0.0) == pytest.approx(0.0)
    assert scene.spawn.position == pytest.approx((0.0, 1.6, 0.0)) and scene.floor_height(100.0, 0.0) is None


def test_monastery_spawn_is_its_main_courtyard():
    pytest.importorskip("pybullet_data")
    from quadcast.render.scene import monastery_scene
    scene = monastery_scene()
    x, y, z = scene.spawn.position
    assert (x, z) == (-3.7, 1.5) and y == pytest.approx(scene.bounds()[0][1] + 2.0)


@pytest.mark.parametrize("name", ["checker", "duck_ground", "open_space"])
def test_the_scene_files_in_docs_load(name):
    """docs/scenes' files (the README's untuned scenes) point into the checkout's .venv, where `make` installs
    pybullet_data."""
    from pathlib import Path
    pybullet_data = pytest.importorskip("pybullet_data")
    root = Path(__file__).resolve().parents[1]
    if not (root / ".venv").exists() or root / ".venv" not in Path(pybullet_data.getDataPath()).resolve().parents:
        pytest.skip("pybullet_data is not in this checkout's .venv")
    scene = load_scene(root / "docs" / "scenes" / f"{name}.json")
    assert scene.name == name and len(scene.objects) >= 3 and scene.spawn is not None
