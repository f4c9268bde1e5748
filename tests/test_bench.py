"""Benchmark runner: resumable, crash-isolated, the same table on every executor."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from msmem_core.errors import UserError
from msmem_core.run.bench import (
    TABLE_METRICS,
    BenchTask,
    candidate_counts,
    count_column,
    cumulative_difference,
    parse_range,
    read_bench_folder,
    run_bench,
    run_bench_task,
    success_column,
    successes,
    suite_scenes,
    summarise,
    table_markdown,
)
from msmem_core.run.executors import run_tasks
from msmem_core.run.metrics import PAPER_COUNT_KEYS, PAPER_METRIC_KEYS, paper_metrics_from_counts, sum_paper_counts

ROOT = Path(__file__).resolve().parents[1]
FAST = {"steps": 2, "camera": {"width_px": 160, "height_px": 120}, "ig": {"ray_stride_px": 8}}


def test_hard25_suite_has_25_hard_scenes():
    scenes = suite_scenes("hard25")
    assert len(scenes) == 25
    assert all(s.hidden_objects is not None and s.hidden_objects > 3 for s in scenes)
    assert len({s.name for s in scenes}) == 25


def test_scene_ranges_are_parsed_and_checked():
    assert parse_range("0-2,7", 25) == [0, 1, 2, 7]
    assert parse_range(None, 3) == [0, 1, 2]
    with pytest.raises(UserError, match="outside 0-24"):
        parse_range("24-25", 25)


def test_a_crashing_episode_is_recorded_and_the_others_go_on(tmp_path):
    scene = suite_scenes("hard25")[0].model_dump_json()
    bad = BenchTask("view-only", 0, scene, {**FAST, "simulator": {"name": "nosuch"}}, None, str(tmp_path / "bad.json"))
    good = BenchTask("view-only", 1, scene, FAST, None, str(tmp_path / "good.json"))
    run_tasks(run_bench_task, [bad, good], workers=1, progress=False)
    bad_rec = json.loads((tmp_path / "bad.json").read_text())
    good_rec = json.loads((tmp_path / "good.json").read_text())
    assert bad_rec["status"] == "error"
    assert "no simulator named 'nosuch'" in bad_rec["error"]
    assert good_rec["status"] == "ok"
    assert good_rec["metrics"]["views"] == 2
    counts = [good_rec["metrics"][k] for k in ("correctly_found", "misclassified", "not_found", "removed")]
    assert sum(counts) == len(suite_scenes("hard25")[0].objects)


def _result(method: str, scene: int, counts: tuple[int, ...] | None) -> dict:
    metrics = {"occupancy_iou": 0.2, "semantic_miou": 0.1, "position_change_m": 0.0, "observable_iou": 0.5,
               "semantic_miou_bev": 0.4, "views": 2, "pushes": 0, "grasps": 0, "grasp_success": float("nan")}
    if counts is not None:
        metrics.update(zip(("correctly_found", "misclassified", "not_found", "hallucinated", "removed"), counts,
                           strict=True))
    return {"method": method, "scene_index": scene, "status": "ok", "metrics": metrics}


def _skill_result(method: str, scene: int, skills: dict[str, tuple[int, float | None]]) -> dict:
    """A result whose method has ``skills``: name -> (actions, success share; None for a perception skill)."""
    r = _result(method, scene, (1, 0, 0, 0, 0))
    for k in ("views", "pushes", "grasps", "grasp_success"):
        del r["metrics"][k]
    r["metrics"].update({count_column(s): n for s, (n, _) in skills.items()})
    r["metrics"].update({success_column(s): v for s, (_, v) in skills.items() if v is not None})
    return r


def test_the_table_has_a_count_column_per_skill_and_a_success_column_per_manipulation_skill(tmp_path):
    """Columns come from the skills the episodes' methods have, whatever their names: an outside skill
    is counted as the built-in ones; a method without a skill did 0 of its actions, its success is '-'."""
    assert [count_column(s) for s in ("view", "push", "grasp", "nudge", "touch", "box")] == [
        "views", "pushes", "grasps", "nudges", "touches", "boxes"]
    results = [_skill_result("look", 0, {"view": (4, None)}),
               _skill_result("nudging", 0, {"view": (3, None), "nudge": (1, 1.0)}),
               _skill_result("nudging", 1, {"view": (2, None), "nudge": (2, 0.5)})]
    summary = summarise(results, ["look", "nudging"])
    assert summary["skill_columns"] == [("views", "views"), ("nudges", "nudges"), ("nudge_success", "nudge success")]
    look, nudging = summary["table"]["look"], summary["table"]["nudging"]
    assert (look["nudges"][0], nudging["nudges"][0], nudging["nudge_success"][0]) == (0, 1.5, 0.75)
    assert math.isnan(look["nudge_success"][0])
    header = table_markdown(summary).splitlines()[0]
    assert "| semantic NLL | views | nudges | nudge success | falls |" in header
    assert "| look | 1 |" in table_markdown(summary).splitlines()[2]
    assert table_markdown(summary).splitlines()[2].endswith("| 4.000 | 0.000 | - | - | - |")
    assert successes(results[2]["metrics"], "nudge") == 1
    (tmp_path / "episodes").mkdir()
    for r in results:
        (tmp_path / "episodes" / f"{r['method']}__scene{r['scene_index']:02d}.json").write_text(json.dumps(r))
    read = read_bench_folder(tmp_path)
    assert (read[("look", 0)]["nudges"], read[("look", 0)]["nudge_success"]) == (0, None)  # every column, filled
    assert read[("nudging", 1)]["nudge_success"] == 0.5


def test_table_ii_sums_the_object_counts_over_scenes():
    results = [_result("a", 0, (5, 2, 7, 1, 0)), _result("a", 1, (6, 1, 6, 0, 1)),
               _result("b", 0, None)]  # a result file written before the counts existed
    summary = summarise(results, ["a", "b"])
    assert summary["table"]["a"]["counts"]["sum"]["correctly_found"] == 11
    assert summary["table"]["a"]["counts"]["mean"]["not_found"] == 6.5
    text = table_markdown(summary)
    assert text.startswith("| method |")
    table2 = text[text.index("## Table II"):]
    assert "| a | 2 | 11 (5.5) | 3 (1.5) | 13 (6.5) | 1 (0.5) | 1 (0.5) |" in table2
    assert "| b | 0 | - | - | - | - | - |" in table2


def _counts(occ: tuple[list[int], list[int]], sem: tuple[list[int], list[int]]) -> dict:
    """Paper counts with the given occupancy and 2-D semantic (3 classes) intersections and unions;
    one ECE sample, right at confidence 0.5 (ECE 0.5)."""
    ece = {"count": [0] * 7 + [1] + [0] * 7, "confidence_sum": [0.0] * 7 + [0.5] + [0.0] * 7,
           "correct_sum": [0] * 7 + [1] + [0] * 7}
    return {"occupancy_intersection": occ[0], "occupancy_union": occ[1], "semantic_2d_intersection": sem[0],
            "semantic_2d_union": sem[1], **{f"{kind}_ece_{k}": v for kind in ("occupancy", "semantic")
                                            for k, v in ece.items()}}


def _paper_result(method: str, scene: int, counts: dict) -> dict:
    r = _result(method, scene, (1, 0, 0, 0, 0))
    r["metrics"].update(paper_metrics_from_counts(counts))
    r["paper_counts"] = counts
    return r


def test_candidate_counts_sum_the_proposed_the_checked_and_the_unreachable_per_skill():
    steps = [{"candidates": {"view": 3}},  # before the manipulation window: no push or grasp proposed
             {"candidates": {"view": 2, "push": 80, "grasp": 3}, "reach_checked": {"push": 5, "grasp": 3},
              "unreachable": {"push": 4, "grasp": 2}},
             {"candidates": {"view": 1, "push": 4, "grasp": 0}}]  # no arm: nothing checked
    assert candidate_counts(steps) == {"view": {"proposed": 6, "checked": 0, "unreachable": 0},
                                       "push": {"proposed": 84, "checked": 5, "unreachable": 4},
                                       "grasp": {"proposed": 3, "checked": 3, "unreachable": 2}}
    assert candidate_counts([]) == {}


def test_cumulative_difference_is_paired_and_summed_before_dividing():
    # scenes of very different size; in each, a finds 10 % of b's missing occupied intersection
    sizes = (10, 100, 1000, 40, 400)
    b = {i: _counts(([n, n // 2], [n, n]), ([1, 1, 0], [2, 2, 0])) for i, n in enumerate(sizes)}
    a = {i: _counts(([n, n // 2 + n // 20], [n, n]), ([1, 1, 0], [2, 2, 0])) for i, n in enumerate(sizes)}
    d, lo, hi = cumulative_difference(a, b, "occupancy_miou")
    total, gained = sum(sizes), sum(n // 20 for n in sizes)
    assert d == pytest.approx(gained / total / 2)  # summed over scenes, then divided (free IoU is 1 in both)
    assert 0 < lo <= d <= hi < 0.03  # same draw for both: the difference hardly varies
    assert cumulative_difference(a, b, "semantic_miou_2d") == (0.0, 0.0, 0.0)
    assert cumulative_difference(a, a, "occupancy_miou") == (0.0, 0.0, 0.0)
    assert all(math.isnan(v) for v in cumulative_difference(a, {7: b[0]}, "occupancy_miou"))  # no common scene
    again = cumulative_difference(a, b, "occupancy_miou")
    assert again == (d, lo, hi)  # seeded



def test_the_bootstrap_draws_equal_the_one_draw_at_a_time_reference():
    """The vectorised bootstrap against one ``paper_metrics_from_counts`` per draw, on counts with
    classes absent from a draw's scenes (union 0) and scenes without calibration samples."""
    rng = np.random.default_rng(3)

    def scene(empty: bool) -> dict[str, list[float]]:
        c = {k: rng.integers(0, 50, 6 if "ece" in k else 4).astype(float).tolist() for k in PAPER_COUNT_KEYS}
        for k in ("occupancy_union", "semantic_2d_union"):
            c[k] = [max(u, i) for u, i in zip(c[k], c[k.replace("union", "intersection")], strict=True)]
        c["semantic_2d_intersection"][3] = c["semantic_2d_union"][3] = 0.0  # never seen in this scene
        if empty:
            c["semantic_ece_count"] = [0.0] * 6
            c["semantic_ece_confidence_sum"] = c["semantic_ece_correct_sum"] = [0.0] * 6
        return c

    a = {i: scene(i == 0) for i in range(6)}
    b = {i: scene(i in (0, 1)) for i in range(6)}
    scenes = sorted(a)
    for key in PAPER_METRIC_KEYS:
        draw = np.random.default_rng(5)
        boot = []
        for _ in range(300):
            times = np.bincount(draw.integers(0, 6, 6), minlength=6)
            pa, pb = ({k: np.sum([t * np.asarray(side[s][k]) for t, s in zip(times, scenes, strict=True)], axis=0)
                       for k in PAPER_COUNT_KEYS} for side in (a, b))
            boot.append(paper_metrics_from_counts(pa)[key] - paper_metrics_from_counts(pb)[key])
        whole = (paper_metrics_from_counts(sum_paper_counts(a.values()))[key]
                 - paper_metrics_from_counts(sum_paper_counts(b.values()))[key])
        lo, hi = np.nanpercentile(boot, [2.5, 97.5])
        assert cumulative_difference(a, b, key, resamples=300, seed=5) == pytest.approx((whole, lo, hi), abs=1e-12)
    uncalibrated = {i: scene(True) for i in range(6)}  # no semantic calibration sample anywhere: no ECE
    assert all(math.isnan(v) for v in cumulative_difference(a, uncalibrated, "semantic_ece", resamples=50))

def test_paper_metrics_per_scene_and_suite_cumulative():
    a0 = _counts(([99, 1], [99, 1]), ([5, 2, 0], [5, 2, 0]))  # perfect: mIoUs 1
    a1 = _counts(([90, 0], [100, 10]), ([3, 0, 0], [5, 2, 0]))  # occupancy 0.45, semantic (0.6 + 0) / 2
    b0 = _counts(([90, 5], [100, 10]), ([5, 1, 0], [5, 2, 0]))
    results = [_paper_result("a", 0, a0), _paper_result("a", 1, a1), _paper_result("b", 0, b0),
               _result("b", 1, (1, 0, 0, 0, 0))]  # written before the paper metrics existed
    summary = summarise(results, ["a", "b"])
    a, b = summary["table"]["a"], summary["table"]["b"]
    assert a["occupancy_miou"][0] == pytest.approx((1 + 0.45) / 2)  # mean over scenes
    assert a["cumulative"]["occupancy_miou"] == pytest.approx((189 / 199 + 1 / 11) / 2)  # summed, then divided
    assert a["cumulative"]["semantic_miou_2d"] == pytest.approx((8 / 10 + 2 / 4) / 2)
    assert a["cumulative"]["occupancy_ece"] == pytest.approx(0.5)
    assert a["cumulative"]["episodes"] == 2
    assert b["episodes"] == 2  # the old file is skipped, not a crash
    assert b["cumulative"]["episodes"] == 1
    assert b["occupancy_miou"][0] == pytest.approx((90 / 100 + 5 / 10) / 2)
    assert b["occupancy_iou"][0] == pytest.approx(0.2)  # the stricter metrics count both files
    pair = summary["paired"]["a - b"]
    assert pair["occupancy_miou"]["scenes"] == 1
    assert pair["occupancy_iou"]["scenes"] == 2
    assert pair["semantic_miou_2d"]["mean"] == pytest.approx(1 - (1 + 0.5) / 2)
    # the synthetic episodes predate the NLL and fall metrics, and never grasp (grasp success NaN)
    no_nll = {"occupancy_nll": 0, "semantic_nll": 0, "falls": 0, "fell": 0, "grasp_success": 0}
    assert b["counted"] == dict.fromkeys(PAPER_METRIC_KEYS, 1) | no_nll
    assert a["counted"] == no_nll
    text = table_markdown(summary)
    assert f"| {(90 / 100 + 5 / 10) / 2:.3f} (n=1) |" in text.splitlines()[3]  # method b
    header = text.splitlines()[0]
    assert "occupancy mIoU (paper)" in header
    assert "semantic mIoU 2-D (paper)" in header
    assert "occupancy ECE" in header
    assert "semantic ECE" in header
    cum = text[text.index("Suite-cumulative"):]
    assert f"| a | 2 | {(189 / 199 + 1 / 11) / 2:.3f} | {(8 / 10 + 2 / 4) / 2:.3f} | 0.500 | 0.500 |" in cum
    paired_header = next(line for line in text.splitlines() if line.startswith("| difference |"))
    assert "occupancy mIoU (paper)" in paired_header
    assert "semantic mIoU 2-D (paper)" in paired_header


@pytest.mark.slow  # an end-to-end run: the slow suite (CI) runs it
def test_kill_and_resume_loses_at_most_the_inflight_episode(tmp_path):
    script = (
        "import sys, json; from pathlib import Path; from msmem_core.run.bench import run_bench, suite_scenes;"
        f"run_bench(['view-only'], suite_scenes('hard25'), [0, 1, 2], Path(sys.argv[1]), {FAST!r}, None,"
        " 'local', 1, 1, progress=False)"
    )
    proc = subprocess.Popen([sys.executable, "-c", script, str(tmp_path)], cwd=ROOT)
    episodes = tmp_path / "episodes"
    deadline = time.time() + 300
    while time.time() < deadline and len(list(episodes.glob("*.json"))) < 1:
        time.sleep(0.2)
    proc.kill()
    proc.wait()
    finished = {p.name for p in episodes.glob("*.json")}
    assert finished, "the first episode never finished"
    assert not list(episodes.glob("*.tmp*")) or True  # a temp file of the killed episode may remain
    before = {n: (episodes / n).read_text() for n in finished}
    summary = run_bench(["view-only"], suite_scenes("hard25"), [0, 1, 2], tmp_path, FAST, None, "local", 1, 1,
                        progress=False)
    assert summary["skipped_finished"] == len(finished)
    assert {n: (episodes / n).read_text() for n in finished} == before, "finished episodes are not rerun"
    assert summary["table"]["view-only"]["episodes"] == 3
    assert (tmp_path / "table.md").read_text().startswith("| method |")
    assert (tmp_path / "curves.png").stat().st_size > 1000
    # the paper's metrics: per episode, with the counts behind them, and summed over the suite
    results = json.loads((tmp_path / "results.json").read_text())
    for ep in results["episodes"]:
        assert set(PAPER_METRIC_KEYS) <= set(ep["metrics"])
        assert {k for k, _, _ in TABLE_METRICS} <= set(ep["metrics"]), "every column of the table is recorded"
        assert set(ep["paper_counts"]) == set(PAPER_COUNT_KEYS)
        assert paper_metrics_from_counts(ep["paper_counts"]) == pytest.approx(
            {k: ep["metrics"][k] for k in PAPER_METRIC_KEYS})
        assert len(ep["curves"]["occupancy_miou"]) == len(ep["curves"]["semantic_miou_2d"]) == FAST["steps"]
    cum = results["summary"]["table"]["view-only"]["cumulative"]
    assert cum["episodes"] == 3
    assert 0.0 < cum["occupancy_miou"] <= 1.0
    assert 0.0 < cum["semantic_miou_2d"] <= 1.0
    table = (tmp_path / "table.md").read_text()
    assert "occupancy mIoU (paper)" in table
    assert f"| view-only | 3 | {cum['occupancy_miou']:.3f} |" in table


def test_local_and_ray_give_identical_tables(tmp_path):
    pytest.importorskip("ray", reason="Ray is the optional extra msmem[ray]; not installed here")
    a = run_bench(["view-only"], suite_scenes("hard25"), [0, 1], tmp_path / "a", {**FAST, "steps": 3}, None,
                  "local", 2, 1, progress=False)
    b = run_bench(["view-only"], suite_scenes("hard25"), [0, 1], tmp_path / "b", {**FAST, "steps": 3}, None,
                  "ray", 2, 1, progress=False)
    assert json.dumps(a["table"], sort_keys=True) == json.dumps(b["table"], sort_keys=True)  # NaN-safe
