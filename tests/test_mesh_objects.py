"""Mesh objects: convex parts voxelise exactly, a mesh file becomes convex pieces (its hull,
or a CoACD decomposition) in the object frame, cached; URDFs give their collision mesh; a scene class
from a mesh stands on the PyBullet shelf, is seen with its own class and is mapped."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from msmem_core.config import load_config
from msmem_core.errors import UserError
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.runner import build_episode, run_episode
from msmem_core.testing.builders import convex_copy
from msmem_core.world.geometry import pose_matrix
from msmem_core.world.grid import GridSpec
from msmem_core.world.meshparts import load_mesh, mesh_pieces
from msmem_core.world.scene import ObjectSpec, Part, SceneSpec
from msmem_core.world.voxelize import _part_voxels
from tests.support.defaults import ANALYTIC

GRID = GridSpec(origin_m=(-0.2, -0.2, -0.05), voxel_m=0.01, shape=(40, 40, 35))
POSE = pose_matrix((0.013, -0.021, 0.07), (0.2, -0.3, 0.1, 0.9))
SMALL = {**ANALYTIC, "camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}}


@pytest.mark.parametrize("part", [
    Part(kind="box", size_m=(0.08, 0.05, 0.12), position_m=(0.01, 0.0, 0.06), quat_xyzw=(0.0, 0.0, 0.2, 0.98)),
    Part(kind="cylinder", size_m=(0.04, 0.1), position_m=(0.0, 0.02, 0.05)),
])
def test_a_convex_part_voxelises_exactly_as_the_primitive_it_spans(part: Part) -> None:
    want = _part_voxels(part, POSE, GRID)
    got = _part_voxels(convex_copy(part), POSE, GRID)
    assert len(want) > 100
    np.testing.assert_array_equal(np.sort(got), np.sort(want))


def test_convex_part_volume_centroid_and_validation() -> None:
    box = Part(kind="box", size_m=(0.1, 0.2, 0.3), position_m=(0.01, 0.02, 0.15), quat_xyzw=(0, 0, 0.38, 0.92))
    vol, c = convex_copy(box).volume_and_centroid()
    assert vol == pytest.approx(0.006, rel=1e-9)
    np.testing.assert_allclose(c, box.position_m, atol=1e-12)
    with pytest.raises(ValueError, match="at least 4 vertices_m that are not coplanar"):
        Part(kind="convex", vertices_m=((0, 0, 0), (1, 0, 0), (0, 1, 0), (1, 1, 0)))
    with pytest.raises(ValueError, match="a box part needs size_m of 3 positive values"):
        Part(kind="box", size_m=(0.1, 0.2))
    with pytest.raises(ValueError, match="a convex part takes vertices_m, not size_m"):
        Part(kind="convex", size_m=(0.1,), vertices_m=((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1)))


def _write_box(path: Path, extents: tuple[float, float, float], offset: tuple[float, float, float]) -> Path:
    trimesh.creation.box(extents=extents).apply_translation(offset).export(path)
    return path


def _write_l(path: Path) -> Path:
    """An L-shaped prism (not convex), 2 units high, in mesh units (e.g. cm)."""
    xy = np.array([[0, 0], [6, 0], [6, 2], [2, 2], [2, 8], [0, 8]], dtype=float)
    tris = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]])
    trimesh.creation.extrude_triangulation(xy, tris, height=2.0).export(path)
    return path


def test_a_convex_mesh_is_one_piece_in_the_object_frame_and_cached(tmp_path: Path) -> None:
    f = _write_box(tmp_path / "box.obj", (4.0, 6.0, 10.0), (5.0, 5.0, 5.0))  # cm, off-centre
    mesh = load_mesh(f, 0.01)
    lo, hi = mesh.bounds
    np.testing.assert_allclose([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]], 0.0, atol=1e-12)
    np.testing.assert_allclose(hi - lo, [0.04, 0.06, 0.10], atol=1e-12)
    pieces, report = mesh_pieces(f, 0.01)
    assert (report.pieces, report.decomposed) == (1, False)
    assert report.pieces_volume_m3 == pytest.approx(0.04 * 0.06 * 0.10, rel=1e-6)
    assert report.cache.parent == tmp_path
    record = json.loads(report.cache.read_text())
    assert record["pieces"] == [p.tolist() for p in pieces]
    record["pieces"][0] = [[x * 2 for x in v] for v in record["pieces"][0]]  # the cache is what is read back
    report.cache.write_text(json.dumps(record))
    again, _ = mesh_pieces(f, 0.01)
    np.testing.assert_allclose(again[0], 2 * pieces[0])
    _, other = mesh_pieces(f, 0.02)  # another scale: another key
    assert other.cache != report.cache


def test_a_concave_mesh_is_decomposed_into_pieces_that_cover_it(tmp_path: Path) -> None:
    f = _write_l(tmp_path / "l.obj")
    pieces, report = mesh_pieces(f, 0.01, max_hulls=8)
    assert report.decomposed
    assert 2 <= report.pieces <= 8
    assert report.mesh_volume_m3 == pytest.approx(24 * 2 * 1e-6, rel=1e-6)
    assert report.pieces_volume_m3 == pytest.approx(report.mesh_volume_m3, rel=0.15)
    mesh = load_mesh(f, 0.01)
    rng = np.random.default_rng(0)
    cm = rng.uniform([0, 0, 0], [6, 8, 2], (8000, 3))
    cm = cm[(cm[:, 1] <= 2) | (cm[:, 0] <= 2)]  # inside the L
    inside = cm * 0.01 + mesh.bounds[0]
    from scipy.spatial import Delaunay

    covered = np.zeros(len(inside), dtype=bool)
    for v in pieces:
        covered |= Delaunay(v).find_simplex(inside) >= 0
    assert covered.mean() > 0.97
    # the corner that makes the L concave is not filled in
    corner = np.array([[0.04, 0.05, 0.01]]) + mesh.bounds[0] * [1, 1, 0]
    assert not any(Delaunay(v).find_simplex(corner)[0] >= 0 for v in pieces)


def test_a_urdf_gives_its_collision_mesh_with_its_scale(tmp_path: Path) -> None:
    _write_box(tmp_path / "b.obj", (4.0, 6.0, 10.0), (0.0, 0.0, 0.0))
    (tmp_path / "b.urdf").write_text(
        '<robot name="b"><link name="l"><collision><geometry><mesh filename="b.obj" scale="0.01 0.01 0.01"/>'
        "</geometry></collision></link></robot>")
    a, _ = mesh_pieces(tmp_path / "b.urdf")
    b, _ = mesh_pieces(tmp_path / "b.obj", 0.01)
    np.testing.assert_allclose(np.sort(a[0], axis=0), np.sort(b[0], axis=0))


@pytest.mark.parametrize(("name", "text", "message"), [
    ("missing.obj", None, "does not exist"),
    ("bad.xyz", "hello", "unknown format '.xyz'"),
    ("empty.urdf", "<robot name='x'><link name='l'/></robot>", "has no <collision> or <visual> mesh"),
    ("broken.urdf", "<robot", "not a readable URDF"),
])
def test_bad_mesh_files_are_refused_naming_the_file(tmp_path: Path, name: str, text: str | None, message: str) -> None:
    f = tmp_path / name
    if text is not None:
        f.write_text(text)
    with pytest.raises(UserError, match="mesh file") as e:
        mesh_pieces(f)
    assert message in str(e.value)
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"classes": [{"name": "thing", "mesh": {"file": name}}]}))
    with pytest.raises(UserError, match=r"classes\.0\.mesh: mesh file"):
        SceneSpec.from_json(scene)


def _l_scene(folder: Path) -> SceneSpec:
    _write_l(folder / "l.obj")
    (folder / "scene.json").write_text(json.dumps({
        "name": "mesh", "classes": [{"name": "l_block", "mesh": {"file": "l.obj", "scale": [0.02, 0.02, 0.05],
                                                                 "max_hulls": 8}, "mass_kg": 0.3}],
        "objects": [{"id": 0, "class_name": "l_block", "position_m": [-0.1, 0.15, 0.0]},
                    {"id": 1, "class_name": "sugar_box", "position_m": [0.15, 0.2, 0.0]}]}))
    return SceneSpec.from_json(folder / "scene.json")  # the mesh path is relative to the scene file


def test_a_scene_class_from_a_mesh_gets_its_pieces_and_a_scene_json_reads_back(tmp_path: Path) -> None:
    scene = _l_scene(tmp_path)
    cls = scene.objects[0].object_class
    assert cls.name == "l_block"
    assert all(p.kind == "convex" for p in cls.parts)
    assert len(cls.parts) >= 2
    back = SceneSpec.model_validate_json(scene.model_dump_json())
    assert back.objects[0].object_class.parts == cls.parts
    assert ObjectSpec(id=5, class_name="mug", position_m=(0, 0, 0)).object_class.parts[0].kind == "cylinder"


def test_a_mesh_object_stands_on_the_pybullet_shelf_is_labelled_and_mapped(tmp_path: Path) -> None:
    scene = _l_scene(tmp_path)
    cfg = load_config("view-only", None, {**SMALL, "steps": 3})
    ep = build_episode(cfg, get_plugin_manager(), scene=scene)
    ep.sim.reset(ep.scene)
    pose = ep.sim.object_poses()[0]
    np.testing.assert_allclose(pose[:3, 3], scene.objects[0].position_m, atol=0.005)  # settled where placed
    assert pose[2, 2] > 0.999  # upright
    obs = ep.sim.observe(ep.viewpoints[ep.start_view])
    assert obs.object_ids is not None
    assert set(np.unique(obs.labels[obs.object_ids == 0]).tolist()) <= {15, scene.object_class("l_block").confusable_id}
    final = run_episode(ep, tmp_path / "run")
    with np.load(tmp_path / "run" / "gt_final.npz") as f:
        assert (f["classes"] == 15).sum() > 50
    assert final["observable_iou"] > 0.1
