"""Candidate views from a poses file: the file's views, its start and front views, checks
that name the file and the entry at fault, paths relative to the config file, benchmark fingerprints
that follow the file's content, and a real PyBullet episode over the views of a file."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msmem_core.config import RunConfig, load_config
from msmem_core.errors import UserError
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import fingerprint
from msmem_core.run.runner import build_episode, run_episode, run_wide
from msmem_core.world.scene import ObjectSpec, SceneSpec, ShelfSpec
from msmem_core.world.viewpoints import (
    ViewpointConfig,
    default_start_view,
    front_views,
    generate_viewpoints,
    read_poses_file,
)

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "viewpoints" / "shared-positions.poses.yaml"
SMALL = {"camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}}


def _look_at_file(path: Path, cfg: ViewpointConfig, **extra: object) -> Path:
    """The parametric views of ``cfg`` written as look-at entries (target: the grid's target)."""
    poses = generate_viewpoints(cfg)
    per = cfg.grid**2
    views = [{"position_m": poses[i, :3, 3].tolist(),
              "target_m": [cfg.targets_x_m[i // per], cfg.target_y_m, cfg.target_z_m]} for i in range(len(poses))]
    path.write_text(json.dumps({"views": views, **extra}))
    return path


def test_a_file_of_look_at_views_gives_the_parametric_poses(tmp_path: Path) -> None:
    cfg = ViewpointConfig(grid=4)
    f = _look_at_file(tmp_path / "views.json", cfg)
    from_file = ViewpointConfig(poses_file=f)
    assert from_file.num_views == 48
    np.testing.assert_allclose(generate_viewpoints(from_file), generate_viewpoints(cfg), atol=1e-12)


def test_a_npy_file_round_trips_camera_to_world_matrices(tmp_path: Path) -> None:
    poses = generate_viewpoints(ViewpointConfig(grid=3))
    np.save(tmp_path / "views.npy", poses)
    cfg = ViewpointConfig(poses_file=tmp_path / "views.npy")
    np.testing.assert_array_equal(generate_viewpoints(cfg), poses)


def test_start_and_front_views_come_from_the_file_when_it_names_them(tmp_path: Path) -> None:
    f = _look_at_file(tmp_path / "v.json", ViewpointConfig(grid=3), start_view=4, front_views=[1, 2])
    cfg = ViewpointConfig(poses_file=f)
    assert default_start_view(cfg) == 4
    assert front_views(cfg) == [1, 2]


def test_without_them_the_start_is_the_most_frontal_central_view_and_the_fronts_one_per_third() -> None:
    cfg = ViewpointConfig(poses_file=EXAMPLE)
    poses = generate_viewpoints(cfg)
    start = default_start_view(cfg)
    forward = poses[:, :3, 2]
    assert abs(poses[start, 0, 3]) < 0.05  # near x = 0
    assert forward[start, 1] > 0.99  # straight in
    fronts = front_views(cfg)
    assert len(fronts) == 3
    targets = [f // 100 for f in fronts]  # view k * 100 + i looks at target k (left, middle, right)
    assert targets == [0, 1, 2]
    for f in fronts:  # the most frontal view among those looking at the same target
        same = np.arange(f // 100 * 100, f // 100 * 100 + 100)
        assert forward[f, 1] == pytest.approx(forward[same, 1].max())


def test_the_example_reuses_100_positions_for_three_targets() -> None:
    poses = generate_viewpoints(ViewpointConfig(poses_file=EXAMPLE))
    assert len(poses) == 300
    assert len(np.unique(poses[:, :3, 3].round(4), axis=0)) == 100


def _write(tmp_path: Path, text: str, name: str = "v.yaml") -> Path:
    (tmp_path / name).write_text(text)
    return tmp_path / name


@pytest.mark.parametrize(("text", "message"), [
    ("views: []\n", "lists no views"),
    ("views:\n  - {position_m: [0, -0.5, 0.1], target_m: [0, -0.5, 0.1]}\n",
     "views.0: position_m and target_m coincide"),
    ("views:\n  - {position_m: [0, -0.5, 0.1], target_m: [0, 0.2, 0.1]}\n  - {position_m: [0, -0.5]}\n",
     "views.1 must have exactly position_m and target_m, or matrix"),
    ("views:\n  - matrix: [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n", "views.0: the rotation"),
    ("views:\n  - matrix: [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]]\n", "views.0.matrix must be 4 x 4"),
    ("views:\n  - {position_m: [0, -0.5, .nan], target_m: [0, 0.2, 0.1]}\n", "must be finite"),
    ("views:\n  - {position_m: [0, -0.5, 0.1], target_m: [0, 0.2, 0.1]}\nstart_view: 1\n",
     "start_view must be a view index from 0 to 0"),
    ("views:\n  - {position_m: [0, -0.5, 0.1], target_m: [0, 0.2, 0.1]}\nfront_view: [0]\n",
     "unknown key(s) front_view"),
    ("cameras: []\n", "must be a mapping with a list 'views'"),
    ("views: [\n", "is not valid YAML"),
])
def test_a_bad_poses_file_is_refused_naming_the_file_and_the_entry(tmp_path: Path, text: str, message: str) -> None:
    f = _write(tmp_path, text)
    with pytest.raises(UserError, match="poses file") as e:
        read_poses_file(f)
    assert message in str(e.value)
    assert str(f.resolve()) in str(e.value)


def test_config_errors_name_the_field(tmp_path: Path) -> None:
    with pytest.raises(UserError, match=r"viewpoints\.poses_file.*cannot read poses file"):
        load_config("view-only", None, {"viewpoints": {"poses_file": str(tmp_path / "missing.yaml")}})
    with pytest.raises(UserError, match="poses_file replaces the parametric grids: leave out grid"):
        load_config("view-only", None, {"viewpoints": {"poses_file": str(EXAMPLE), "grid": 4}})
    with pytest.raises(UserError, match=r"msas\.start_view 300 is not a viewpoint: there are 300"):
        load_config("view-only", None, {"viewpoints": {"poses_file": str(EXAMPLE)}, "msas": {"start_view": 300}})


def test_a_camera_inside_the_shelf_is_refused_naming_the_view(tmp_path: Path) -> None:
    f = _write(tmp_path, "views:\n  - {position_m: [0, -0.5, 0.1], target_m: [0, 0.2, 0.1]}\n"
                         "  - {position_m: [0, 0.1, 0.1], target_m: [0, 0.3, 0.1]}\n")
    with pytest.raises(UserError, match=r"view 1: camera y = 0\.100 m"):
        generate_viewpoints(ViewpointConfig(poses_file=f), ShelfSpec())


def test_a_relative_path_in_a_config_file_is_relative_to_that_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch
                                                                   ) -> None:
    sub = tmp_path / "cfg"
    sub.mkdir()
    _look_at_file(sub / "views.json", ViewpointConfig(grid=2))
    (sub / "run.yaml").write_text("viewpoints: {poses_file: views.json}\n")
    monkeypatch.chdir(tmp_path)  # not the config file's folder
    cfg = load_config("view-only", Path("cfg/run.yaml"))
    assert cfg.viewpoints.num_views == 12
    assert cfg.viewpoints.poses_file is not None
    assert cfg.viewpoints.poses_file.resolve() == (sub / "views.json")
    assert RunConfig.model_validate_json(cfg.model_dump_json()) == cfg  # a run folder's config.json reads back


def test_the_benchmark_fingerprint_follows_the_files_content(tmp_path: Path) -> None:
    f = _look_at_file(tmp_path / "v.json", ViewpointConfig(grid=2))
    cfg = load_config("view-only", None, {"viewpoints": {"poses_file": str(f)}})
    scene = SceneSpec(name="empty", objects=())
    before = fingerprint(cfg, "s", scene, {})
    _look_at_file(f, ViewpointConfig(grid=3))  # same path, other views
    assert fingerprint(cfg, "s", scene, {})["config_sha256"] != before["config_sha256"]


@pytest.mark.slow  # an end-to-end run: the slow suite (CI) runs it
def test_the_grasp_skill_gets_the_runs_viewpoints_for_its_virtual_front_cameras(tmp_path: Path) -> None:
    from msmem_grasp.fpp import virtual_front_views

    f = _look_at_file(tmp_path / "v.json", ViewpointConfig(grid=3), front_views=[7, 20])
    cfg = load_config("grasp-only", None, {"viewpoints": {"poses_file": str(f)}})
    ep = build_episode(cfg, get_plugin_manager())
    grasp = next(s.skill for s in ep.skills if s.name == "grasp")
    assert grasp.config.viewpoints == cfg.viewpoints
    np.testing.assert_array_equal(virtual_front_views(grasp.config.viewpoints), ep.viewpoints[[7, 20]])
    assert run_wide(cfg)["viewpoints"] is cfg.viewpoints


def test_a_pybullet_episode_runs_over_the_views_of_a_file(tmp_path: Path) -> None:
    f = _look_at_file(tmp_path / "v.json", ViewpointConfig(grid=3), start_view=13)
    cfg = load_config("view-only", None, {**SMALL, "steps": 3, "viewpoints": {"poses_file": str(f)}})
    scene = SceneSpec(name="two", objects=(
        ObjectSpec(id=0, class_name="cracker_box", position_m=(-0.15, 0.08, 0.0)),
        ObjectSpec(id=1, class_name="sugar_box", position_m=(0.2, 0.2, 0.0)),
    ))
    ep = build_episode(cfg, get_plugin_manager(), scene=scene)
    assert ep.start_view == 13
    np.testing.assert_array_equal(ep.viewpoints, generate_viewpoints(cfg.viewpoints))
    final = run_episode(ep, tmp_path / "run")
    views = [r["action"]["view"] for r in ep.records]
    assert len(views) == 3
    assert all(0 <= v < 27 and v != 13 for v in views)
    assert final["observable_iou"] > 0.1


def test_the_grasp_skill_tracks_with_the_front_views_of_its_viewpoints(tmp_path: Path, monkeypatch) -> None:
    """FE-UMGF's first update (no view visited, nothing manipulated) uses the run's front views."""
    import msmem_grasp.skill as skill_module

    from tests.test_grasp import TARGET, box_belief, ctx

    f = _look_at_file(tmp_path / "v.json", ViewpointConfig(grid=3), front_views=[7, 20])
    cfg = ViewpointConfig(poses_file=f)
    seen: list[ViewpointConfig | None] = []
    real = skill_module.virtual_front_views
    monkeypatch.setattr(skill_module, "virtual_front_views", lambda v=None: seen.append(v) or real(v))
    grasp = skill_module.GraspSkill(skill_module.GraspConfig(predictor="geometric", viewpoints=cfg))
    grasp.track(ctx(box_belief([TARGET]), step=0, allowed=False))
    assert seen == [cfg]
