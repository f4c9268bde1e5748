"""Fault injection on the files a user hands msmem: meshes, URDFs and weights.

- Geometry is finite and plausible: a vertex that is not finite is refused naming the file and the
  vertex; pieces whose volume is far from the mesh's (or its hull's) are refused or warned about,
  naming both volumes.
- Named means required: weights the user names load, or the component is refused when it is built
  (before any episode), naming the file and the reason; every loader refuses tensors that are not
  finite; only ``auto`` with nothing named falls back, and says so once.
- Paths stay inside their roots: a shipped-weights name inside the shipped folder, a URDF's meshes
  inside its folder or a declared package root, refused before the file is read.
- URDF geometry: the collision origin's full rotation is applied; mesh errors name the class and the
  URDF; a long decomposition reports its progress.
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial.transform import Rotation

from msmem_core.errors import UserError
from msmem_core.plugins import ComponentRef, get_plugin_manager
from msmem_core.util.artifacts import load_state, sha256_file
from msmem_core.world import meshparts
from msmem_core.world.grid import GridSpec
from msmem_core.world.meshparts import load_mesh, mesh_pieces
from msmem_core.world.scene import Part, SceneSpec
from msmem_core.world.voxelize import _part_voxels

ROOT = Path(__file__).resolve().parents[1]
CNABU_WEIGHTS = ROOT / "plugins" / "msmem_cnabu" / "weights"
GRID = GridSpec(origin_m=(-0.2, -0.2, -0.05), voxel_m=0.01, shape=(40, 40, 35))


def _cube(path: Path, size: float = 6.0) -> Path:
    trimesh.creation.box((size, size, size)).export(path)
    return path


def _one_line(e: pytest.ExceptionInfo[BaseException]) -> str:
    text = str(e.value)
    assert "\n" not in text, text
    return text


# ================================================================================ finite geometry
def _nan_cube(path: Path, index: int, value: float) -> Path:
    m = trimesh.creation.box((6.0, 6.0, 6.0))
    v = m.vertices.copy()
    v[index, 1] = value
    trimesh.Trimesh(v, m.faces, process=False).export(path)
    return path


@pytest.mark.parametrize(("name", "value"), [("cube.obj", np.nan), ("cube.obj", np.inf), ("cube.ply", np.nan)])
def test_a_mesh_vertex_that_is_not_finite_is_refused_naming_the_file_and_the_vertex(tmp_path, name, value):
    f = _nan_cube(tmp_path / name, 3, value)
    with pytest.raises(UserError) as e:
        mesh_pieces(f, 0.01)
    text = _one_line(e)
    assert str(f) in text
    assert "vertex 3 (counting from 0, of 8) is not finite" in text
    assert not list(tmp_path.glob("*.hulls-*.json"))  # nothing cached
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"classes": [{"name": "crate", "mesh": {"file": name, "scale": 0.01}}]}))
    with pytest.raises(UserError) as e:
        SceneSpec.from_json(scene)
    assert "vertex 3" in _one_line(e)
    assert "'crate'" in str(e.value)


def _tamper(cache: Path, pieces: list[np.ndarray], volume: float) -> None:
    record = json.loads(cache.read_text())
    record["pieces"] = [p.tolist() for p in pieces]
    record["pieces_volume_m3"] = volume
    cache.write_text(json.dumps(record))


SLIVER = np.array([[0, 0, 0], [0.06, 0, 0], [0, 0.06, 0], [0, 0, 0.0197]])  # 1.18e-5 m^3, as the sliver seen


def test_pieces_holding_far_less_than_the_mesh_are_refused_naming_both_volumes(tmp_path):
    f = _cube(tmp_path / "cube.obj")
    _, report = mesh_pieces(f, 0.01)
    assert report.pieces_volume_m3 == pytest.approx(2.16e-4)
    sliver = float(trimesh.convex.convex_hull(SLIVER).volume)
    _tamper(report.cache, [SLIVER], sliver)
    with pytest.raises(UserError) as e:
        mesh_pieces(f, 0.01)
    text = _one_line(e)
    assert "its convex pieces hold 1.18e-05 m^3 where the mesh holds 0.000216 m^3 (ratio 0.05)" in text
    assert str(f) in text


def test_an_open_mesh_is_checked_against_its_hull_and_an_unchecked_cache_record_is_checked_too(tmp_path, caplog):
    """An open mesh's pieces far smaller than its hull are warned about (an open container's thin walls
    hold little; so does the sliver CoACD made of a cube with a dropped vertex: 1.18e-5 m^3 in 170 s)."""
    box = trimesh.creation.box((6.0, 6.0, 6.0))
    up = box.face_normals[:, 2] > 0.9
    f = tmp_path / "open.obj"
    trimesh.Trimesh(box.vertices, box.faces[~up]).export(f)  # no lid: not watertight
    assert load_mesh(f).is_watertight is False
    settings = {"max_hulls": 16, "threshold": 0.05, "convex_ratio": 0.95, "quat_xyzw": [0.0, 0.0, 0.0, 1.0]}
    cache = f.with_name(f"{f.name}.hulls-{meshparts._key(f, 0.01, settings)}.json")
    # a record without a hull volume (unchecked): the mesh is read to check it
    cache.write_text(json.dumps({"source": str(f), "decomposed": True, "mesh_volume_m3": None,
                                 "pieces_volume_m3": 1.18e-5, "pieces": [SLIVER.tolist()]}))
    with caplog.at_level(logging.WARNING, logger="msmem_core.world.meshparts"):
        _, report = mesh_pieces(f, 0.01)
    assert report.cache == cache
    assert report.hull_volume_m3 == pytest.approx(2.16e-4)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1
    assert "its convex pieces hold 1.18e-05 m^3 where its convex hull (the mesh is not watertight) holds " \
           "0.000216 m^3 (ratio 0.05), below 0.1" in said[0]
    assert json.loads(cache.read_text())["hull_volume_m3"] == pytest.approx(2.16e-4)  # checked once, recorded


def test_pieces_holding_far_more_than_the_mesh_are_warned_about_once(tmp_path, caplog):
    f = _cube(tmp_path / "cube.obj")
    _, report = mesh_pieces(f, 0.01)
    big = trimesh.creation.box((0.1, 0.1, 0.1)).vertices
    _tamper(report.cache, [big], 1e-3)
    with caplog.at_level(logging.WARNING, logger="msmem_core.world.meshparts"):
        mesh_pieces(f, 0.01)
        mesh_pieces(f, 0.01)
    warned = [r.getMessage() for r in caplog.records if "convex pieces hold" in r.getMessage()]
    assert len(warned) == 1
    assert "hold 0.001 m^3 where the mesh holds 0.000216 m^3 (ratio 4.63)" in warned[0]


def test_an_inside_out_mesh_holds_its_volume_and_is_one_piece(tmp_path):
    m = trimesh.creation.box((6.0, 6.0, 6.0))
    m.invert()
    m.export(tmp_path / "inv.obj")
    _, report = mesh_pieces(tmp_path / "inv.obj", 0.01)
    assert (report.pieces, report.decomposed) == (1, False)
    assert report.mesh_volume_m3 == pytest.approx(2.16e-4)


# ================================================================================ named weights
def _fe_vmf_weights(path: Path, poison: bool = False) -> Path:
    from msmem_grasp.fevmf import FEVMF
    from msmem_grasp.learn.training import WEIGHTS_FORMAT, default_model_config

    torch.manual_seed(0)
    model = FEVMF(default_model_config())
    state = model.state_dict()
    if poison:
        state = {k: torch.full_like(v, float("nan")) if v.is_floating_point() else v for k, v in state.items()}
    torch.save(state, path)
    path.with_suffix(".json").write_text(json.dumps({"format": WEIGHTS_FORMAT, "sha256": sha256_file(path),
                                                     "model": model.config.model_dump()}))
    return path


class _Payload:
    """A pickle that would create a file when unpickled by a loader that runs code."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):  # type: ignore[no-untyped-def]
        return (Path.touch, (self.marker,))


def _hostile(path: Path, marker: Path) -> Path:
    _fe_vmf_weights(path)
    path.write_bytes(pickle.dumps({"backbone.weight": _Payload(marker)}))
    side = json.loads(path.with_suffix(".json").read_text())
    side["sha256"] = sha256_file(path)  # the sidecar agrees: only the loader stands in the way
    path.with_suffix(".json").write_text(json.dumps(side))
    return path


def _corrupt(path: Path) -> Path:
    _fe_vmf_weights(path)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    return path


def _foreign_format(path: Path) -> Path:
    _fe_vmf_weights(path)
    side = json.loads(path.with_suffix(".json").read_text())
    side["format"] = "msmem-cnabu"
    path.with_suffix(".json").write_text(json.dumps(side))
    return path


NAMED_WEIGHTS = [  # (make the file, what the one line says)
    (lambda p, m: _corrupt(p), "expected sha256"),
    (lambda p, m: _foreign_format(p), "not an FE-vMF weights sidecar (format 'msmem-cnabu')"),
    (lambda p, m: _fe_vmf_weights(p, poison=True), "not finite (NaN or infinite) in tensor"),
    (lambda p, m: _hostile(p, m), "not readable as weights: not a plain state dict"),
    (lambda p, m: p, "does not exist"),
]


@pytest.mark.parametrize(("make", "reason"), NAMED_WEIGHTS, ids=["hash", "format", "nan", "pickle", "missing"])
def test_named_grasp_weights_load_or_refuse_the_skill_when_it_is_built(tmp_path, make, reason):
    marker = tmp_path / "code-ran"
    w = make(tmp_path / "named.pt", marker)
    ref = ComponentRef(name="grasp", params={"weights": str(w)})  # predictor: auto, as skill_params sets it
    with pytest.raises(UserError) as e:
        get_plugin_manager().build("skill", ref, where="skills.1")  # what build_episode does before an episode
    text = _one_line(e)
    assert f"grasp skill: FE-vMF weights {w} (named in its weights parameter) cannot be used, no fallback" in text
    assert reason in text
    assert not marker.exists()


def test_named_grasp_weights_that_load_are_used(tmp_path):
    w = _fe_vmf_weights(tmp_path / "good.pt")
    skill = get_plugin_manager().build("skill", ComponentRef(name="grasp", params={"weights": str(w)}))
    assert skill.predictor == "fe-vmf:good.pt"


def test_auto_with_nothing_named_falls_back_and_says_so_once(tmp_path, monkeypatch, caplog):
    from msmem_grasp.skill import GraspConfig, GraspSkill

    monkeypatch.setattr("msmem_grasp.weights.SHIPPED_WEIGHTS", _corrupt(tmp_path / "shipped.pt"))
    with caplog.at_level(logging.WARNING, logger="msmem.grasp"):
        skills = [GraspSkill(GraspConfig()) for _ in range(3)]
        assert [s.predictor for s in skills] == ["geometric"] * 3
    said = [r.getMessage() for r in caplog.records if "geometric" in r.getMessage()]
    assert len(said) == 1
    assert "no usable FE-vMF weights" in said[0]
    assert "shipped.pt" in said[0]


def _poisoned_copy(src: Path, dst: Path) -> str:
    """A copy of shipped weights with one tensor NaN and a sidecar that agrees with it; the tensor's name."""
    state = torch.load(src, map_location="cpu", weights_only=True)
    name = next(k for k, v in state.items() if v.is_floating_point() and v.numel() > 1)
    state[name] = state[name].clone()
    state[name].view(-1)[0] = float("nan")
    torch.save(state, dst)
    side = json.loads(src.with_suffix(".json").read_text())
    side.update(sha256=sha256_file(dst), bytes=dst.stat().st_size, weights=dst.name)
    dst.with_suffix(".json").write_text(json.dumps(side))
    return name


@pytest.mark.parametrize(("model", "shipped"), [("cnabu-push", "cnabu_push.pt"), ("cnabu-map", "cnabu_map.pt")])
def test_learned_belief_model_weights_with_a_nan_tensor_are_refused_naming_it(tmp_path, model, shipped):
    w = tmp_path / shipped
    name = _poisoned_copy(CNABU_WEIGHTS / shipped, w)
    with pytest.raises(UserError) as e:
        get_plugin_manager().build("belief-model", ComponentRef(name=model, params={"weights": str(w)}))
    text = _one_line(e)
    assert str(w) in text
    assert f"not finite (NaN or infinite) in tensor {name} (1 of " in text


def test_a_training_checkpoint_or_init_with_nan_tensors_is_refused(tmp_path):
    from msmem_core.learn.training import TrainingRun

    net = torch.nn.Linear(3, 2)
    opt = torch.optim.SGD(net.parameters(), lr=0.1)
    out = tmp_path / "w.pt"
    bad = {k: torch.full_like(v, float("inf")) for k, v in net.state_dict().items()}
    torch.save({"model": bad, "optimizer": opt.state_dict(), "history": "[]", "best": "", "epoch": 0,
                "seconds": 0.0}, out.with_suffix(".ckpt"))
    with pytest.raises(UserError) as e:
        TrainingRun(out, net, opt, resume=True, log=lambda _: None)
    assert "the checkpoint's weights are not finite (NaN or infinite) in tensor weight (6 of 6 values)" in _one_line(e)
    torch.save(bad, tmp_path / "init.pt")  # ``msmem train cnabu-map --init``
    with pytest.raises(UserError, match="initial weights with values that are not finite"):
        load_state(tmp_path / "init.pt", UserError, "initial weights")


# ================================================================================ paths stay inside
@pytest.mark.parametrize("name", [
    "msmem_cnabu/weights/../../msmem_grasp/weights/fe_vmf.pt",
    "msmem_cnabu/weights/../weights.py",
    "msmem_cnabu/weights/..",
])
def test_a_shipped_weights_name_leading_out_of_the_shipped_folder_is_refused(tmp_path, monkeypatch, name):
    from msmem_cnabu.weights import WeightsError, resolve_weights

    monkeypatch.chdir(tmp_path)
    with pytest.raises(WeightsError) as e:
        resolve_weights(name)
    assert f"weights {name!r}: a shipped weights name must name a file inside the shipped folder" in _one_line(e)
    with pytest.raises(UserError, match="inside the shipped folder"):
        get_plugin_manager().build("belief-model", ComponentRef(name="cnabu-map", params={"weights": name}))


def test_a_shipped_weights_name_through_a_symlink_out_of_the_folder_is_refused(tmp_path, monkeypatch):
    import msmem_cnabu.weights as cw

    folder = tmp_path / "shipped"
    folder.mkdir()
    (tmp_path / "elsewhere.pt").write_bytes(b"x")
    (folder / "inside.pt").write_bytes(b"x")
    os.symlink(tmp_path / "elsewhere.pt", folder / "link.pt")
    monkeypatch.setattr(cw, "WEIGHTS_DIR", folder)
    monkeypatch.chdir(tmp_path)
    assert cw.resolve_weights("msmem_cnabu/weights/inside.pt") == folder / "inside.pt"
    with pytest.raises(cw.WeightsError, match=r"leads to .*elsewhere\.pt"):
        cw.resolve_weights("msmem_cnabu/weights/link.pt")


_OPENED: list[str] = []
_WATCH: list[str] = []


def _audit(event: str, args: tuple) -> None:  # type: ignore[type-arg]
    if event == "open" and _WATCH and isinstance(args[0], str | bytes | os.PathLike):
        path = os.fsdecode(args[0])
        if any(path.startswith(w) for w in _WATCH):
            _OPENED.append(path)


sys.addaudithook(_audit)


def _urdf(path: Path, filename: str, rpy: str = "0 0 0", scale: str = "0.01 0.01 0.01") -> Path:
    path.write_text(f'<robot name="r"><link name="l"><collision><origin rpy="{rpy}" xyz="0.1 0.2 0.3"/><geometry>'
                    f'<mesh filename="{filename}" scale="{scale}"/></geometry></collision></link></robot>')
    return path


@pytest.fixture
def outside(tmp_path: Path) -> Path:
    """A valid mesh outside the URDF's folder (so reading it would succeed), and the URDF's folder."""
    (tmp_path / "urdf").mkdir()
    (tmp_path / "secret").mkdir()
    return _cube(tmp_path / "secret" / "cube.obj")


ESCAPES = {  # form -> (mesh filename from the outside mesh, what the line says)
    "absolute": (lambda o: str(o), "an absolute path"),
    "file://": (lambda o: f"file://{o}", "an absolute path"),
    "package://..": (lambda o: "package://../secret/cube.obj", "package '..' is not a declared package root"),
    "package://pkg/../..": (lambda o: "package://urdf/../secret/cube.obj", "outside"),
    "../": (lambda o: "../secret/cube.obj", "outside"),
    "symlink": (lambda o: "link.obj", "outside"),
    "http://": (lambda o: "http://example.com/cube.obj", "only relative paths, file:// and package:// are read"),
}


@pytest.mark.parametrize("form", list(ESCAPES))
def test_a_urdf_mesh_outside_its_folder_is_refused_before_it_is_read(outside, form):
    folder = outside.parents[1] / "urdf"
    os.symlink(outside, folder / "link.obj")
    name, says = ESCAPES[form][0](outside), ESCAPES[form][1]
    urdf = _urdf(folder / "thing.urdf", name)
    _WATCH[:] = [str(outside), str(outside.parent)]
    _OPENED.clear()
    try:
        with pytest.raises(UserError) as e:
            mesh_pieces(urdf, package_roots=[str(folder)])
    finally:
        _WATCH.clear()
    text = _one_line(e)
    assert f"URDF {urdf}: mesh filename {name!r}" in text
    assert says in text
    assert _OPENED == []  # refused before the file was opened
    scene = folder / "scene.json"
    scene.write_text(json.dumps({"classes": [{"name": "crate", "mesh": {"file": "thing.urdf"}}]}))
    with pytest.raises(UserError) as e:
        SceneSpec.from_json(scene)
    assert str(urdf) in _one_line(e)
    assert "(class 'crate')" in str(e.value)


def test_urdf_meshes_inside_the_folder_or_a_declared_package_root_load(tmp_path):
    (tmp_path / "robot" / "meshes").mkdir(parents=True)
    (tmp_path / "assets" / "props" / "meshes").mkdir(parents=True)
    _cube(tmp_path / "robot" / "meshes" / "cube.obj")
    _cube(tmp_path / "assets" / "props" / "meshes" / "cube.obj", 4.0)
    os.symlink(tmp_path / "robot" / "meshes" / "cube.obj", tmp_path / "robot" / "same.obj")  # stays inside
    for name in ("meshes/cube.obj", "file://meshes/cube.obj", "same.obj", "./meshes/../meshes/cube.obj"):
        _, r = mesh_pieces(_urdf(tmp_path / "robot" / "a.urdf", name))
        assert r.pieces_volume_m3 == pytest.approx(2.16e-4), name
    urdf = _urdf(tmp_path / "robot" / "p.urdf", "package://props/meshes/cube.obj")
    with pytest.raises(UserError, match="package 'props' is not a declared package root"):
        mesh_pieces(urdf)
    _, r = mesh_pieces(urdf, package_roots=[tmp_path / "assets" / "props"])
    assert r.pieces_volume_m3 == pytest.approx(0.04 ** 3)
    scene = tmp_path / "robot" / "scene.json"  # package roots in a scene file are relative to it
    scene.write_text(json.dumps({"classes": [{"name": "prop", "mesh": {"file": "p.urdf",
                                                                        "package_roots": ["../assets/props"]}}]}))
    cls = SceneSpec.from_json(scene).object_class("prop")
    assert sum(p.volume_and_centroid()[0] for p in cls.parts) == pytest.approx(0.04 ** 3)


# ================================================================================ URDF geometry
def _wedge(path: Path) -> np.ndarray:
    """A right triangular prism (no symmetry a wrong rotation could hide behind), in cm."""
    xy = np.array([[0.0, 0.0], [9.0, 0.0], [0.0, 4.0]])
    m = trimesh.creation.extrude_triangulation(xy, np.array([[0, 1, 2]]), height=6.0)
    m.export(path)
    return np.asarray(m.vertices)


@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.9), (1.2, 0.0, 0.0), (0.0, -0.8, 0.0), (0.4, -0.7, 2.1)],
                         ids=["yaw", "roll", "pitch", "all"])
def test_the_collision_origin_rotation_is_applied_against_voxelised_ground_truth(tmp_path, rpy):
    cm = _wedge(tmp_path / "wedge.obj")
    urdf = _urdf(tmp_path / "wedge.urdf", "wedge.obj", rpy=" ".join(map(str, rpy)))
    pieces, report = mesh_pieces(urdf)
    assert report.pieces == 1
    # ground truth, independently: scipy's extrinsic x-y-z Euler angles are URDF's rpy
    v = cm * 0.01 @ Rotation.from_euler("xyz", rpy).as_matrix().T
    lo, hi = v.min(axis=0), v.max(axis=0)
    v = v - [(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]]
    pose = np.eye(4)
    pose[:3, 3] = (0.013, -0.021, 0.0)
    want = _part_voxels(Part(kind="convex", vertices_m=tuple(map(tuple, v))), pose, GRID)
    got = _part_voxels(Part(kind="convex", vertices_m=tuple(map(tuple, pieces[0]))), pose, GRID)
    assert len(want) > 50
    np.testing.assert_array_equal(np.sort(got), np.sort(want))
    # the same rotation given as the class's own quat_xyzw on the bare mesh gives the same pieces
    same, _ = mesh_pieces(tmp_path / "wedge.obj", 0.01, quat_xyzw=tuple(Rotation.from_euler("xyz", rpy).as_quat()))
    np.testing.assert_allclose(np.sort(same[0], axis=0), np.sort(pieces[0], axis=0), atol=2e-6)


def test_a_rotated_urdf_is_not_served_pieces_cached_without_its_rotation(tmp_path):
    import hashlib

    _wedge(tmp_path / "wedge.obj")
    flat, flat_report = mesh_pieces(tmp_path / "wedge.obj", 0.01)
    urdf = _urdf(tmp_path / "wedge.urdf", "wedge.obj", rpy="1.2 0 0")
    # the key the URDF had when its origin was not applied; pieces cached under it are the unrotated ones
    h = hashlib.sha256(urdf.read_bytes() + (tmp_path / "wedge.obj").read_bytes())
    h.update(json.dumps({"v": meshparts.CACHE_VERSION, "scale": 1.0, "max_hulls": 16, "threshold": 0.05,
                         "convex_ratio": 0.95, "quat_xyzw": [0.0, 0.0, 0.0, 1.0]}, sort_keys=True).encode())
    stale = tmp_path / f"{urdf.name}.hulls-{h.hexdigest()[:16]}.json"
    stale.write_text(flat_report.cache.read_text())
    pieces, report = mesh_pieces(urdf)
    assert report.cache != stale
    ext = np.ptp(pieces[0], axis=0)
    assert not np.allclose(ext, np.ptp(flat[0], axis=0), atol=1e-3)
    np.testing.assert_allclose(ext, load_mesh(urdf).extents, atol=1e-6)


@pytest.mark.parametrize(("mesh", "says"), [
    ("missing.obj", "does not exist"),
    ("wedge.txt", "unknown format '.txt'"),
    ("nan.obj", "vertex 3 (counting from 0, of 8) is not finite"),
    ("../wedge.obj", "outside"),
])
def test_every_mesh_error_names_the_class_and_the_urdf(tmp_path, mesh, says):
    (tmp_path / "pkg").mkdir()
    _wedge(tmp_path / "wedge.obj")
    (tmp_path / "pkg" / "wedge.txt").write_text("v 0 0 0\n")
    _nan_cube(tmp_path / "pkg" / "nan.obj", 3, np.nan)
    urdf = _urdf(tmp_path / "pkg" / "thing.urdf", mesh, scale="2 2 2")
    scene = tmp_path / "scene.json"
    scene.write_text(json.dumps({"classes": [{"name": "crate", "mesh": {"file": "pkg/thing.urdf", "scale": 0.01}}]}))
    with pytest.raises(UserError) as e:
        SceneSpec.from_json(scene)
    text = _one_line(e)
    assert "(class 'crate')" in text
    assert str(urdf) in text
    assert says in text


def test_a_long_decomposition_reports_its_progress_and_a_short_or_cached_one_is_quiet(tmp_path, monkeypatch, capfd):
    xy = np.array([[0, 0], [6, 0], [6, 2], [2, 2], [2, 8], [0, 8]], dtype=float)  # an L: CoACD runs
    tris = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]])
    f = tmp_path / "l.obj"
    trimesh.creation.extrude_triangulation(xy, tris, height=2.0).export(f)
    _, report = mesh_pieces(f, 0.01, max_hulls=8)
    assert report.decomposed
    assert "decompos" not in capfd.readouterr().err  # under a second: nothing to say
    monkeypatch.setattr(meshparts, "PROGRESS_AFTER_S", 0.0)  # as if it took long
    _, report = mesh_pieces(f, 0.02, max_hulls=8)
    err = capfd.readouterr().err.splitlines()
    assert len(err) == 2, err
    assert err[0].startswith(f"msmem: decomposing mesh file {f} (")
    assert "with CoACD" in err[0]
    assert err[1].startswith(f"msmem: decomposed mesh file {f} into ")
    assert f"(cached: {report.cache})" in err[1]
    mesh_pieces(f, 0.02, max_hulls=8)  # cached: no decomposition, nothing said
    assert capfd.readouterr().err == ""


@pytest.mark.slow  # about 10 s (a fresh msmem process): run by CI's `make test-slow`
def test_msmem_run_with_named_grasp_weights_that_do_not_load_is_refused_before_the_episode(tmp_path):
    import subprocess

    w = _corrupt(tmp_path / "named.pt")
    cfg = tmp_path / "run.yaml"
    cfg.write_text(f"skill_params:\n  grasp:\n    weights: {w}\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(str(ROOT / d) for d in ("", "plugins", "simulators"))}
    res = subprocess.run([str(Path(sys.executable).with_name("msmem")), "run", "-m", "ours", "-c", str(cfg),
                          "--steps", "2", "--out", str(tmp_path / "run"), "-q"],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=300, check=False)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith(f"msmem: error: grasp skill: FE-vMF weights {w} (named in its weights parameter)")
    assert "expected sha256" in lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["named.json", "named.pt", "run.yaml"]  # no run folder


def test_a_bench_refuses_named_weights_that_do_not_load_before_any_episode(tmp_path):
    import torch

    from msmem_core.config import load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import check_components

    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a torch file")
    nan = tmp_path / "nan.pt"
    torch.save({"w": torch.full((2,), float("nan"))}, nan)
    pm = get_plugin_manager()
    for f, why in ((bad, "not readable"), (nan, "not finite")):
        cfg = load_config("grasp-only", None, {"skill_params": {"grasp": {"weights": str(f)}}})
        with pytest.raises(UserError, match=f"grasp's weights: {f}.*{why}"):
            check_components(cfg, pm)
    assert check_components(load_config("grasp-only"), pm)  # the shipped ones pass
