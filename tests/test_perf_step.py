"""`msmem perf step` times every stage of a real `ours` decision and returns a valid action (no timing
assertions: speed is reported by the benchmark, not tested)."""

from __future__ import annotations

from pathlib import Path

import pytest

from msmem_core.interfaces import Action
from msmem_core.perf.step import is_valid_action, perf_step

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "msmem_core" / "suites" / "hard25" / "scene_00.json"


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, list[str]]:
    """One timed decision of the `ours` preset on a small camera and 27 viewpoints (fast)."""
    cfg = tmp_path_factory.mktemp("perf") / "small.yaml"
    cfg.write_text("camera: {width_px: 160, height_px: 120}\nviewpoints: {grid: 3}\nig: {ray_stride_px: 4}\n")
    lines: list[str] = []
    res = perf_step(repeats=1, views=4, view_seed=0, reference=True, beliefs=1, config=cfg, scene=SCENE,
                    reference_views=1, report=lines.append)
    return res, lines


def test_every_stage_of_every_skill_is_timed(small):
    res, lines = small
    stages = res["stages"]
    for skill in ("view", "push", "grasp"):
        assert f"{skill}: track" in stages
        assert f"{skill}: propose" in stages
    assert "grasp: track / FPP (frontier points)" in stages
    assert "grasp: track / FE-UMGF fusion" in stages
    # 27 views, no more than the view finalists: every view is scored at full density, none screened
    assert any(k.startswith("view: score / term ig") and k.endswith("IG of the finalist views (full density)")
               for k in stages)
    assert not any(k.startswith("view: score") and "screening" in k for k in stages)
    for skill, n in res["candidates"].items():  # a manipulation skill with candidates is predicted and scored
        if n and skill != "view":
            assert f"{skill}: effect prediction" in stages
            assert f"{skill}: score / term ig" in stages
            assert f"{skill}: score / term cdc" in stages
    assert res["candidates"]["push"] > 0
    assert res["decide_s"] > 0.0
    assert sum(1 for line in lines if line.startswith("  ")) >= len(stages)  # one table row per stage


def test_the_decision_is_a_valid_action(small):
    res, _ = small
    d = res["decision"]
    assert isinstance(d.action, Action)
    assert d.skill.name in res["candidates"]
    assert res["candidates"][d.skill.name] > 0
    assert is_valid_action(d.action, num_views=27)


def test_references_and_approximation_check_are_reported(small):
    res, lines = small
    assert res["reference/sweep_cpu_s"] > 0.0
    assert res["reference/push_ig_max_rel_diff"] < 1e-9  # incremental IG equals the full re-score
    assert isinstance(res["reference/same_decision"], bool)
    a = res["agreement"]
    assert a["beliefs"] == 1
    assert 0 <= a["same_as_unscreened"] <= 1
    assert 0 <= a["same_as_exact"] <= 1
    for skill in ("push", "grasp"):  # every manipulation skill of the method, by its config name
        assert 0 <= a[f"{skill}_best_differs"] <= a[f"{skill}_batches"] <= 1
    assert "view_batches" not in a
    line = next(line for line in lines if "approximations" in line)
    assert f"push in {a['push_best_differs']}/{a['push_batches']}" in line
    assert f"grasp in {a['grasp_best_differs']}/{a['grasp_batches']}" in line


def test_the_observation_update_is_timed_and_reported(small):
    res, lines = small
    assert res["observe_s"] > 0
    assert 0 <= res["observe_view"] < 27
    assert any(line.strip().startswith("observation update (cnabu-map)") for line in lines)
