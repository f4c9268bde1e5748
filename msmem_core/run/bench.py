"""Benchmark: methods x scenes episodes on an executor, resumable, summarised as the paper's Tables I and II.

One result file per (method, scene) is written atomically under ``OUT/episodes/``; rerunning skips
finished episodes, and a crashed episode is recorded with its error while the rest go on.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from msmem_core.errors import UserError
from msmem_core.run.metrics import PAPER_COUNT_KEYS, PAPER_METRIC_KEYS, paper_metrics_from_counts, sum_paper_counts
from msmem_core.world.scene import SceneSpec

SUITES = ("hard25", "tune10")
"""hard25: the benchmark (seeds 25000-25024); tune10: for tuning defaults (seeds 30000-30009), never hard25."""
TABLE_METRICS = (
    ("occupancy_iou", "occupancy IoU", "higher"),
    ("semantic_miou", "semantic mIoU", "higher"),
    ("position_change_m", "Position Change (m)", "lower"),
    ("observable_iou", "observable IoU", "higher"),
    ("semantic_miou_bev", "semantic mIoU (BEV)", "higher"),
    ("occupancy_miou", "occupancy mIoU (paper)", "higher"),
    ("semantic_miou_2d", "semantic mIoU 2-D (paper)", "higher"),
    ("occupancy_ece", "occupancy ECE", "lower"),
    ("semantic_ece", "semantic ECE", "lower"),
    ("occupancy_nll", "occupancy NLL", "lower"),
    ("semantic_nll", "semantic NLL", "lower"),
    ("views", "views", None),
    ("pushes", "pushes", None),
    ("grasps", "grasps", None),
    ("grasp_success", "grasp success", None),
)
COUNT_METRICS = (
    ("correctly_found", "correctly found"),
    ("misclassified", "misclassified but found"),
    ("not_found", "not found"),
    ("hallucinated", "hallucinated"),
    ("removed", "removed"),
)
"""Table II: final object counts (``metrics.object_counts``) plus objects no longer in the shelf."""
PAIRED_METRICS = ("occupancy_iou", "semantic_miou", "position_change_m", "observable_iou", "semantic_miou_bev",
                  "occupancy_miou", "semantic_miou_2d", "occupancy_nll", "semantic_nll")
"""The metrics whose per-scene differences between methods ``table.md`` reports."""
CURVE_METRICS = ("occupancy_iou", "semantic_miou", "observable_iou", "position_change_m", "occupancy_miou",
                 "semantic_miou_2d")
"""Per-step metrics kept in each episode's result file (``curves``)."""


def suite_scenes(suite: str) -> list[SceneSpec]:
    """The scenes of a shipped suite, in order."""
    if suite not in SUITES:
        raise UserError(f"unknown suite {suite!r}; suites: {', '.join(SUITES)}")
    folder = resources.files("msmem_core.suites").joinpath(suite)
    files = sorted((f for f in folder.iterdir() if f.name.endswith(".json")), key=lambda f: f.name)
    return [SceneSpec.model_validate_json(f.read_text()) for f in files]


def parse_range(text: str | None, n: int) -> list[int]:
    """'0-4,7' -> [0, 1, 2, 3, 4, 7]; None -> all n."""
    if not text:
        return list(range(n))
    out: list[int] = []
    try:
        for part in text.split(","):
            lo, _, hi = part.partition("-")
            out.extend(range(int(lo), int(hi or lo) + 1))
    except ValueError as e:
        raise UserError(f"--scenes {text!r}: expected indices like 0-4,7") from e
    bad = [i for i in out if not 0 <= i < n]
    if bad:
        raise UserError(f"--scenes {text!r}: indices {bad} outside 0-{n - 1}")
    return sorted(set(out))


@dataclass(frozen=True)
class BenchTask:
    method: str
    scene_index: int
    scene_json: str
    overrides: dict[str, Any]
    config_file: str | None
    out_file: str


def write_atomic(path: Path, data: Any) -> None:
    tmp = path.with_suffix(path.suffix + f".tmp{os.getpid()}")
    tmp.write_text(json.dumps(data, indent=1))
    os.replace(tmp, path)


def run_bench_task(task: BenchTask) -> dict[str, Any]:
    """Run one episode and write its result file (module level: executors pickle it)."""
    import time

    from msmem_core.config import load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import build_episode, run_episode

    t0 = time.perf_counter()
    record: dict[str, Any] = {"method": task.method, "scene_index": task.scene_index}
    try:
        cfg = load_config(task.method, task.config_file, task.overrides)
        ep = build_episode(cfg, get_plugin_manager(), scene=SceneSpec.model_validate_json(task.scene_json))
        final = run_episode(ep, None)
        curves = {k: [r["metrics"][k] for r in ep.records] for k in CURVE_METRICS}
        kinds = [r["skill"] for r in ep.records]
        grasp_ok = [r["success"] for r in ep.records if r["skill"] == "grasp"]
        record.update({
            "scene": ep.scene.name, "status": "ok", "metrics": {
                **{k: final[k] for k in ("occupancy_iou", "semantic_miou", "observable_iou", "semantic_miou_bev",
                                         "position_change_m", *PAPER_METRIC_KEYS)},
                **{k: int(final[k]) for k, _ in COUNT_METRICS},
                "views": kinds.count("view"), "pushes": kinds.count("push"), "grasps": kinds.count("grasp"),
                "grasp_success": float(np.mean(grasp_ok)) if grasp_ok else float("nan"),
            },
            "paper_counts": final["paper_counts"], "curves": curves, "skills": kinds,
            "seconds": time.perf_counter() - t0,
        })
    except Exception as e:  # isolate the crash: the table reports it, the other episodes go on
        import traceback

        record.update({"status": "error", "error": f"{type(e).__name__}: {e}", "traceback": traceback.format_exc(),
                       "seconds": time.perf_counter() - t0})
    write_atomic(Path(task.out_file), record)
    return record


def mean_ci(x: list[float]) -> tuple[float, float]:
    """Mean and the half-width of its 95% t-interval (nan-safe)."""
    a = np.asarray([v for v in x if not (isinstance(v, float) and math.isnan(v))], dtype=float)
    if len(a) == 0:
        return float("nan"), float("nan")
    if len(a) == 1:
        return float(a[0]), float("nan")
    return float(a.mean()), float(stats.t.ppf(0.975, len(a) - 1) * a.std(ddof=1) / math.sqrt(len(a)))


def cumulative(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The paper's metrics over a suite as [MEM]'s ``Cumulative_mIoU``: intersections, unions and
    calibration bins summed over the episodes before dividing (episodes without counts are skipped)."""
    counted = [r["paper_counts"] for r in rows if all(k in r.get("paper_counts", {}) for k in PAPER_COUNT_KEYS)]
    values = (paper_metrics_from_counts(sum_paper_counts(counted)) if counted
              else dict.fromkeys(PAPER_METRIC_KEYS, float("nan")))
    return {"episodes": len(counted), **values}


def summarise(results: list[dict[str, Any]], methods: list[str]) -> dict[str, Any]:
    """Per method: mean and 95% CI over scenes of every table metric (episodes lacking a metric, written
    before it existed, are left out of its column), Table II counts, and the suite-cumulative paper metrics;
    plus paired differences against the first method."""
    ok = [r for r in results if r.get("status") == "ok"]
    table: dict[str, dict[str, Any]] = {}
    for m in methods:
        rows = [r for r in ok if r["method"] == m]
        table[m] = {k: mean_ci([r["metrics"][k] for r in rows if k in r["metrics"]]) for k, _, _ in TABLE_METRICS}
        table[m]["episodes"] = len(rows)
        table[m]["counted"] = {k: n for k, _, _ in TABLE_METRICS  # columns some (older) episodes lack
                               if (n := sum(k in r["metrics"] for r in rows)) < len(rows)}
        table[m]["cumulative"] = cumulative(rows)
        counted = [r for r in rows if all(k in r["metrics"] for k, _ in COUNT_METRICS)]  # older files lack them
        table[m]["counts"] = {
            "episodes": len(counted),
            "sum": {k: sum(int(r["metrics"][k]) for r in counted) for k, _ in COUNT_METRICS},
            "mean": {k: float(np.mean([r["metrics"][k] for r in counted])) if counted else float("nan")
                     for k, _ in COUNT_METRICS},
        }
    paired: dict[str, dict[str, Any]] = {}
    base = methods[0]
    by = {(r["method"], r["scene_index"]): r for r in ok}
    for m in methods[1:]:
        pair: dict[str, Any] = {}
        for k in PAIRED_METRICS:
            scenes = sorted(s for (mm, s) in by if mm == base and (m, s) in by
                            and k in by[(base, s)]["metrics"] and k in by[(m, s)]["metrics"])
            diffs = [by[(base, s)]["metrics"][k] - by[(m, s)]["metrics"][k] for s in scenes]
            pair[k] = {**dict(zip(("mean", "ci95"), mean_ci(diffs), strict=True)), "scenes": len(scenes)}
        paired[f"{base} - {m}"] = pair
    errors = [{"method": r["method"], "scene_index": r["scene_index"], "error": r["error"]}
              for r in results if r.get("status") == "error"]
    return {"methods": methods, "table": table, "paired": paired, "errors": errors}


def _fmt(mc: tuple[float, float]) -> str:
    m, c = mc
    if math.isnan(m):
        return "-"
    return f"{m:.3f}" if math.isnan(c) else f"{m:.3f} ± {c:.3f}"


LABELS = {k: label for k, label, _ in TABLE_METRICS}


def table_markdown(summary: dict[str, Any]) -> str:
    lines = ["| method | episodes | " + " | ".join(label for _, label, _ in TABLE_METRICS) + " |",
             "|---|---|" + "---|" * len(TABLE_METRICS)]
    for m in summary["methods"]:
        row = summary["table"][m]
        counted = row.get("counted", {})
        lines.append(f"| {m} | {row['episodes']} | " + " | ".join(
            _fmt(tuple(row[k])) + (f" (n={counted[k]})" if k in counted else "") for k, _, _ in TABLE_METRICS) + " |")
    lines += ["", "Mean ± half-width of the 95% t-interval over scenes. \"(paper)\" and ECE: the paper's own metrics",
              "([MEM]'s `Cumulative_mIoU`; docs/concepts.md), per scene; episodes written before they existed are",
              "left out of those columns (n=: the episodes a column counts, where fewer than all).", ""]
    lines += ["Suite-cumulative paper metrics (intersections, unions and ECE bins summed over scenes before",
              "dividing, as [MEM]):", "",
              "| method | episodes | " + " | ".join(LABELS[k] for k in PAPER_METRIC_KEYS) + " |",
              "|---|---|" + "---|" * len(PAPER_METRIC_KEYS)]
    for m in summary["methods"]:
        cum = summary["table"][m].get("cumulative", {"episodes": 0})
        lines.append(f"| {m} | {cum['episodes']} | "
                     + " | ".join(_fmt((cum.get(k, math.nan), math.nan)) for k in PAPER_METRIC_KEYS) + " |")
    lines.append("")
    if summary["paired"]:
        lines += ["Paired differences per scene (mean ± 95% CI; an interval excluding 0 is marked *):", "",
                  "| difference | " + " | ".join(LABELS[k] for k in PAIRED_METRICS) + " |",
                  "|---|" + "---|" * len(PAIRED_METRICS)]
        for name, cols in summary["paired"].items():
            cells = []
            for k in PAIRED_METRICS:
                if k not in cols:  # a summary from before this metric was paired
                    cells.append("-")
                    continue
                m, c = cols[k]["mean"], cols[k]["ci95"]
                star = "*" if not math.isnan(c) and abs(m) > c else ""
                cells.append(_fmt((m, c)) + star)
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    while lines[-1] == "":
        lines.pop()
    lines += ["", "## Table II: object counts", "",
              "Objects at the end of the episode, summed over scenes (mean per scene in brackets); the matching",
              "rule is `msmem_core.run.metrics.object_counts`. `removed`: objects no longer in the shelf (grasped out,",
              "or pushed out), left out of the other four columns.", "",
              "| method | episodes | " + " | ".join(label for _, label in COUNT_METRICS) + " |",
              "|---|---|" + "---|" * len(COUNT_METRICS)]
    for m in summary["methods"]:
        counts = summary["table"][m].get("counts", {"episodes": 0})
        n = counts["episodes"]
        cells = [f"{counts['sum'][k]} ({counts['mean'][k]:.1f})" if n else "-" for k, _ in COUNT_METRICS]
        lines.append(f"| {m} | {n} | " + " | ".join(cells) + " |")
    if summary["errors"]:
        lines += ["", "Crashed episodes:", ""] + [f"- {e['method']} scene {e['scene_index']}: {e['error']}"
                                                  for e in summary["errors"]]
    return "\n".join(lines) + "\n"


def plot_curves(results: list[dict[str, Any]], methods: list[str], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    keys = ("occupancy_iou", "observable_iou", "semantic_miou", "occupancy_miou", "position_change_m")
    fig, axes = plt.subplots(1, len(keys), figsize=(4.2 * len(keys), 3.4))
    for ax, k in zip(axes, keys, strict=True):
        for m in methods:
            curves = [r["curves"][k] for r in results
                      if r.get("status") == "ok" and r["method"] == m and k in r.get("curves", {})]
            if not curves:
                continue
            n = min(len(c) for c in curves)
            arr = np.array([c[:n] for c in curves])
            x = np.arange(1, n + 1)
            ax.plot(x, arr.mean(0), label=m)
            ax.fill_between(x, arr.mean(0) - arr.std(0), arr.mean(0) + arr.std(0), alpha=0.15)
        ax.set_xlabel("step")
        ax.set_title(k)
    axes[0].legend()
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def run_bench(methods: list[str], scenes: list[SceneSpec], scene_indices: list[int], out: Path,
              overrides: dict[str, Any], config_file: str | None, executor: str, workers: int,
              threads: int, progress: bool = True) -> dict[str, Any]:
    from msmem_core.run.executors import run_tasks

    (out / "episodes").mkdir(parents=True, exist_ok=True)
    tasks, done = [], []
    for m in methods:
        for i in scene_indices:
            f = out / "episodes" / f"{m}__scene{i:02d}.json"
            if f.exists():
                done.append(json.loads(f.read_text()))
                continue
            tasks.append(BenchTask(m, i, scenes[i].model_dump_json(), {**overrides, "threads": threads}, config_file,
                                   str(f)))
    if tasks:
        run_tasks(run_bench_task, tasks, executor=executor, workers=workers, threads=threads, progress=progress,
                  description="episodes")
    results = [json.loads(f.read_text()) for f in sorted((out / "episodes").glob("*.json"))
               if f.name.split("__")[0] in methods]
    summary = summarise(results, methods)
    summary["skipped_finished"] = len(done)
    (out / "table.md").write_text(table_markdown(summary))
    write_atomic(out / "results.json", {"summary": summary, "episodes": results})
    plot_curves(results, methods, out / "curves.png")
    return summary
