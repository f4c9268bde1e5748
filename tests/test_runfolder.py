"""Run-folder files: snapshots and ground truth round-trip, and ``load_run`` reads what the runner wrote
(falling back to the final belief when the last step has no snapshot) and rejects incomplete folders."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msmem_core.config import RunConfig
from msmem_core.errors import UserError
from msmem_core.map.belief import EvidentialMap
from msmem_core.run.runfolder import load_ground_truth, load_run, save_ground_truth, save_snapshot
from msmem_core.world.grid import GridSpec

GRID = GridSpec(origin_m=(0.0, 0.0, 0.0), voxel_m=0.05, shape=(4, 3, 2))


def _belief(seed: int) -> EvidentialMap:
    rng = np.random.default_rng(seed)
    b = EvidentialMap.empty(GRID)
    b.alpha[:] = rng.uniform(1, 50, GRID.shape)
    b.beta[:] = rng.uniform(1, 50, GRID.shape)
    b.eta[:] = rng.uniform(1, 50, b.eta.shape)
    return b


def _truth(seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    occ = rng.random(GRID.shape) < 0.5
    return occ, np.where(occ, rng.integers(1, 15, GRID.shape), 0)


def test_a_snapshot_stores_half_precision_evidence_clipped_to_float16_and_the_ground_truth(tmp_path: Path) -> None:
    belief = _belief(0)
    belief.alpha[0, 0, 0] = 1e6  # beyond float16's largest value
    occ, cls = _truth(1)
    save_snapshot(tmp_path / "s.npz", belief, occ, cls)
    back = EvidentialMap.load(tmp_path / "s.npz")
    assert back.grid == GRID
    assert back.alpha[0, 0, 0] == np.finfo(np.float16).max
    np.testing.assert_allclose(back.beta, belief.beta, rtol=1e-3)
    np.testing.assert_allclose(back.eta, belief.eta, rtol=1e-3)
    with np.load(tmp_path / "s.npz") as f:
        assert f["alpha"].dtype == np.float16
        np.testing.assert_array_equal(f["gt_occ"], occ)
        np.testing.assert_array_equal(f["gt_cls"], cls)


def test_ground_truth_round_trips(tmp_path: Path) -> None:
    occ, cls = _truth(2)
    save_ground_truth(tmp_path / "gt.npz", GRID, occ, cls)
    grid, occ2, cls2 = load_ground_truth(tmp_path / "gt.npz")
    assert grid == GRID
    assert occ2.dtype == bool
    assert cls2.dtype == np.int8
    np.testing.assert_array_equal(occ2, occ)
    np.testing.assert_array_equal(cls2, cls)


def _run_folder(d: Path, steps: int) -> None:
    d.mkdir()
    (d / "config.json").write_text(RunConfig().model_dump_json())
    (d / "scene.json").write_text(json.dumps({"name": "empty", "objects": []}))
    (d / "steps.jsonl").write_text("".join(json.dumps({"step": i, "skill": "view"}) + "\n" for i in range(steps)))
    _belief(3).save(d / "belief_final.npz")


def test_load_run_reads_snapshots_in_step_order_and_falls_back_to_the_final_belief(tmp_path: Path) -> None:
    d = tmp_path / "run"
    _run_folder(d, steps=12)
    for step in (10, 2):
        save_snapshot(d / f"belief_step{step}.npz", _belief(step), *_truth(step))
    occ, cls = _truth(4)
    save_ground_truth(d / "gt_final.npz", GRID, occ, cls)
    run = load_run(d)
    assert [s.step for s in run.snapshots] == [2, 10, 11]
    assert run.snapshots[0].label == "after step 2"
    assert run.final.label == "final (after step 11)"
    np.testing.assert_array_equal(run.final.belief.alpha, _belief(3).alpha)
    np.testing.assert_array_equal(run.final.gt_occ, occ)
    assert len(run.steps) == 12
    assert run.metrics == {}


def test_load_run_without_final_ground_truth_reports_an_empty_one(tmp_path: Path) -> None:
    d = tmp_path / "run"
    _run_folder(d, steps=1)
    run = load_run(d)
    assert [s.step for s in run.snapshots] == [0]
    assert not run.final.gt_occ.any()
    assert run.final.gt_occ.shape == GRID.shape


@pytest.mark.parametrize("missing", ["config.json", "scene.json", "steps.jsonl", "belief_final.npz"])
def test_load_run_names_the_missing_file_of_an_incomplete_folder(tmp_path: Path, missing: str) -> None:
    d = tmp_path / "run"
    _run_folder(d, steps=1)
    (d / missing).unlink()
    with pytest.raises(UserError, match=missing):
        load_run(d)


def _metrics(n: int, **over: object) -> dict[str, object]:
    return {"steps": n, "scene": "empty", "method": RunConfig().method, "occupancy_iou": 0.5} | over


def _with_metrics(d: Path, n: int, last: float = 0.5, **over: object) -> None:
    lines = [json.dumps({"step": i, "skill": "view", "metrics": {"occupancy_iou": 0.1 if i < n - 1 else last}})
             for i in range(n)]
    (d / "steps.jsonl").write_text("\n".join(lines) + "\n")
    (d / "metrics.json").write_text(json.dumps(_metrics(n, **over)))


def test_load_run_accepts_a_consistent_folder_with_metrics(tmp_path: Path) -> None:
    d = tmp_path / "run"
    _run_folder(d, steps=3)
    _with_metrics(d, 3)
    save_snapshot(d / "belief_step2.npz", _belief(2), *_truth(2))
    assert load_run(d).metrics["occupancy_iou"] == 0.5


@pytest.mark.parametrize(("plant", "message"), [
    (lambda d: _with_metrics(d, 3, steps=5), "counts 5 steps, steps.jsonl holds 3"),
    (lambda d: _with_metrics(d, 3, scene="gen-4"), "scene 'gen-4'"),
    (lambda d: _with_metrics(d, 3, method="push-only"), "method 'push-only'"),
    (lambda d: _with_metrics(d, 3, last=0.25), "final occupancy_iou differ"),
    (lambda d: (_with_metrics(d, 3), save_snapshot(d / "belief_step7.npz", _belief(7), *_truth(7))),
     "belief_step7.npz is of a step"),
])
def test_load_run_refuses_a_folder_that_mixes_two_runs_and_says_what_disagrees(
        tmp_path: Path, plant: object, message: str) -> None:
    d = tmp_path / "run"
    _run_folder(d, steps=3)
    plant(d)  # type: ignore[operator]
    with pytest.raises(UserError, match="mixes files of different runs") as e:
        load_run(d)
    assert message in str(e.value)
    assert "--overwrite" in str(e.value)
