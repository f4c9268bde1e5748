"""Benchmark: methods x scenes episodes on an executor, resumable, summarised as the paper's Tables I and II.

One result file per (method, scene) is written atomically under ``OUT/episodes/``, with the
fingerprint of what produced it (:func:`fingerprint`). A rerun into the same folder (docs/explanation/reliability.md):

- reuses a finished episode only if its fingerprint matches this run's; any mismatch stops the run
  before anything starts (:class:`FingerprintMismatch`, one line naming the file and what differs),
  unless ``rerun_mismatched`` (``--rerun-mismatched``), which reruns those episodes;
- reruns crashed episodes (``retry_crashed``, the default), keeping the old errors in ``history``;
- moves a corrupt or truncated episode file aside (``NAME.corrupt``), naming it, and reruns it.

The config and the plugins it names are checked once, before any episode starts. A crashed episode
(a worker that died included) is recorded with its error while the rest go on; the table is built
from exactly the planned episodes, and a planned episode left without a result file raises
:class:`~msmem_core.errors.IncompleteError` naming it.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import IncompleteError, UserError
from msmem_core.run.funnel import funnel_counts, funnel_markdown, sum_funnels
from msmem_core.run.metrics import (
    PAPER_COUNT_KEYS,
    PAPER_METRIC_COUNTS,
    PAPER_METRIC_KEYS,
    paper_metrics_from_counts,
    sum_paper_counts,
)
from msmem_core.util.jsonable import dumps, nan_from_null
from msmem_core.world.scene import SceneSpec
from msmem_core.world.viewpoints import read_poses_file

if TYPE_CHECKING:
    from msmem_core.config import RunConfig
    from msmem_core.interfaces import Category

SUITES = ("hard25", "tune10", "mesh25")
"""hard25: the benchmark (seeds 25000-25024); tune10: for tuning defaults (seeds 30000-30009), never hard25;
mesh25: hard scenes of ``pybullet_data`` meshes only (seeds 35000-35024, ``examples/suites/mesh25.generator.yaml``)."""
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
    ("falls", "falls", "lower"),
    ("fell", "episodes with a fall", "lower"),
)
"""The columns of Table I every episode records. Between ``semantic_nll`` and ``falls`` the table shows
its skills' columns (:func:`skill_columns`): how often each skill acted and, for manipulation skills,
the share of their actions that succeeded."""
COUNT_METRICS = (
    ("correctly_found", "correctly found"),
    ("misclassified", "misclassified but found"),
    ("not_found", "not found"),
    ("hallucinated", "hallucinated"),
    ("removed", "removed"),
)
"""Table II: final object counts (``metrics.object_counts``) plus objects no longer in the shelf."""
_FIXED = {k for k, _, _ in TABLE_METRICS} | {k for k, _ in COUNT_METRICS}
"""The metrics every episode records that are not its skills' columns."""
PAIRED_METRICS = ("occupancy_iou", "semantic_miou", "position_change_m", "observable_iou", "semantic_miou_bev",
                  "occupancy_miou", "semantic_miou_2d", "occupancy_nll", "semantic_nll")
"""The metrics whose per-scene differences between methods ``table.md`` reports."""
CURVE_METRICS = ("occupancy_iou", "semantic_miou", "observable_iou", "position_change_m", "occupancy_miou",
                 "semantic_miou_2d")
"""Per-step metrics kept in each episode's result file (``curves``)."""


def suite_scenes(suite: str) -> list[SceneSpec]:
    """The scenes of a suite, in order: a shipped suite by name (``SUITES``), a folder of scene JSON files
    (sorted by file name), or a suite file (YAML) whose ``scenes`` list names scene files relative to it.
    Every file is validated as ``msmem run --scene`` validates it (``placement.load_scene``); a name that
    is neither, an empty folder or a bad file is a one-line ``UserError`` naming it."""
    if suite in SUITES:
        folder = resources.files("msmem_core.suites").joinpath(suite)
        files = sorted((f for f in folder.iterdir() if f.name.endswith(".json")), key=lambda f: f.name)
        return [SceneSpec.model_validate_json(f.read_text()) for f in files]
    path = Path(suite)
    if path.is_dir():
        paths = sorted(path.glob("*.json"), key=lambda p: p.name)
        if not paths:
            raise UserError(f"--suite {suite}: the folder holds no scene file (*.json)")
    elif path.is_file():
        paths = _suite_file(path)
    else:
        raise UserError(f"unknown suite {suite!r}: not a shipped suite ({', '.join(SUITES)}), a folder of scene "
                        "files or a suite file")
    from msmem_core.plugins.manager import get_plugin_manager
    from msmem_core.world.placement import load_scene

    offered = get_plugin_manager().object_classes()
    return [load_scene(str(p), offered) for p in paths]


def _suite_file(path: Path) -> list[Path]:
    """The scene files a suite file names (``scenes: [a.json, ...]``, relative to the file)."""
    import yaml

    try:
        data = yaml.safe_load(path.read_text())
    except (yaml.YAMLError, UnicodeDecodeError) as e:
        raise UserError(f"--suite {path}: not a YAML suite file ({type(e).__name__})") from None
    scenes = data.get("scenes") if isinstance(data, dict) else None
    if not isinstance(scenes, list) or not scenes or not all(isinstance(x, str) for x in scenes):
        raise UserError(f"--suite {path}: a suite file lists its scene files under `scenes:` "
                        "(paths relative to it), e.g. scenes: [shelf_a.json, shelf_b.json]")
    out = [(path.parent / x) for x in scenes]
    missing = [str(p) for p in out if not p.is_file()]
    if missing:
        raise UserError(f"--suite {path}: scene file {missing[0]} does not exist"
                        + (f" (+{len(missing) - 1} more)" if len(missing) > 1 else ""))
    return out


def parse_methods(text: str) -> list[str]:
    """'view-only,push-only' -> ['view-only', 'push-only'], each a known method preset; a list naming
    none, or one twice, or an unknown preset is a one-line ``UserError``."""
    from msmem_core.config import preset

    methods = [m.strip() for m in text.split(",")]
    if not any(methods):
        raise UserError(f"--methods {text!r}: expected comma-separated method presets, e.g. view-only,push-only")
    if "" in methods:
        raise UserError(f"--methods {text!r}: an empty name between commas")
    if twice := sorted({m for m in methods if methods.count(m) > 1}):
        raise UserError(f"--methods {text!r}: {twice[0]!r} is named twice")
    for m in methods:
        preset(m)
    return methods


def parse_range(text: str | None, n: int) -> list[int]:
    """'0-4,7' -> [0, 1, 2, 3, 4, 7]; None -> all n."""
    if not text:
        return list(range(n))
    out: list[int] = []
    try:
        for part in text.split(","):
            lo, _, hi = part.partition("-")
            if int(hi or lo) < int(lo):
                raise UserError(f"--scenes {text!r}: the range {part!r} is empty (write it low-high)")
            out.extend(range(int(lo), int(hi or lo) + 1))
    except ValueError as e:
        raise UserError(f"--scenes {text!r}: expected indices like 0-4,7") from e
    bad = [i for i in out if not 0 <= i < n]
    if bad:
        raise UserError(f"--scenes {text!r}: indices {bad} outside 0-{n - 1}")
    return sorted(set(out))


FINGERPRINT_KEYS = ("method", "suite", "scene_sha256", "steps", "config_sha256", "plugins")
"""What an episode file records about what produced it; resume reuses a file only if all are equal."""


def sha256_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def fingerprint(cfg: RunConfig, suite: str, scene: SceneSpec, plugins: dict[str, str]) -> dict[str, Any]:
    """What produced an episode: method, suite, scene (hash of its JSON), steps, the resolved config
    (hash; ``threads`` left out, results do not depend on it, and so is ``robot`` while it is the default
    ``floating`` and ``class_map`` while it is unset, so results from before they existed still match; with a
    poses file, its content too) and the versions of the distributions providing the components it uses."""
    left_out = ({"threads"} | ({"robot"} if cfg.robot == type(cfg).model_fields["robot"].default else set())
                | ({"class_map"} if cfg.class_map is None else set()))
    config = json.dumps(cfg.model_dump(mode="json", exclude=left_out), sort_keys=True)
    if cfg.viewpoints.poses_file is not None:  # the file's content, not only its name
        config += read_poses_file(cfg.viewpoints.poses_file).sha256
    return {"method": cfg.method, "suite": suite, "scene_sha256": sha256_text(scene.model_dump_json()),
            "steps": cfg.steps, "config_sha256": sha256_text(config), "plugins": plugins}


def fingerprint_diff(old: Any, new: dict[str, Any]) -> str:
    """'' if ``old`` equals ``new``, else what differs, e.g. "steps 6 (now 2), suite hard25 (now tune10)"."""
    if not isinstance(old, dict):
        return "no fingerprint (written by an older msmem)"
    return ", ".join(f"{k} {old.get(k)} (now {new[k]})" for k in FINGERPRINT_KEYS if old.get(k) != new[k])


class FingerprintMismatch(UserError):
    """Episode files in the results folder were made by another method, suite, scene, steps, config
    or plugin versions than this run's."""


@dataclass(frozen=True)
class BenchTask:
    method: str
    scene_index: int
    scene_json: str
    overrides: dict[str, Any]
    config_file: str | None
    out_file: str
    fingerprint: dict[str, Any] = field(default_factory=dict)
    history: tuple[dict[str, Any], ...] = ()
    """Earlier crashes of this episode (error, traceback), kept in its new record."""


def write_atomic(path: Path, data: Any) -> None:
    """Strict JSON (``null`` for NaN), written to a temporary file and renamed into place."""
    write_text_atomic(path, dumps(data, indent=1))


def write_text_atomic(path: Path, text: str) -> None:
    """``text`` to a temporary file renamed into place; an ``OSError`` (a full disk) names ``path``."""
    tmp = path.with_suffix(path.suffix + f".tmp{os.getpid()}")
    try:
        tmp.write_text(text)
        os.replace(tmp, path)
    except OSError as e:
        tmp.unlink(missing_ok=True)
        raise OSError(e.errno, e.strerror or str(e), str(path)) from e


def read_episode(path: Path) -> dict[str, Any]:
    """An episode file; ``ValueError`` if it is corrupt or truncated. Metrics written as ``null``
    (non-finite) come back as NaN."""
    try:
        rec = json.loads(path.read_bytes())
    except (UnicodeDecodeError, json.JSONDecodeError, IsADirectoryError) as e:
        raise ValueError(f"not valid JSON ({type(e).__name__}: {e})") from e
    if not isinstance(rec, dict) or rec.get("status") not in ("ok", "error") or (
            rec["status"] == "ok" and not isinstance(rec.get("metrics"), dict)):
        raise ValueError("not an episode record")
    if rec["status"] == "ok":
        rec["metrics"] = nan_from_null(rec["metrics"])
        rec["curves"] = {k: [math.nan if v is None else v for v in c] for k, c in rec.get("curves", {}).items()}
    return rec


def _finished_records(folder: Path) -> list[dict[str, Any]]:
    """The finished episode records of a bench folder: from ``episodes/*.json``, or, in a folder kept
    without them, from the episodes ``results.json`` holds."""
    files = sorted((folder / "episodes").glob("*.json"))
    records = ([json.loads(f.read_text()) for f in files] if files
               else json.loads((folder / "results.json").read_text()).get("episodes", []))
    return [r for r in records if r.get("status") == "ok"]


def read_bench_folder(folder: Path) -> dict[tuple[str, int], dict[str, Any]]:
    """The finished episodes of a bench folder, as {(method, scene index): metrics}, each with every
    skill column of the folder (:func:`skill_columns`; a skill its method lacks: 0 actions, success
    None). For scripts that compare folders (``examples/paired_benches.py``, ``examples/table1.py``)."""
    records = _finished_records(folder)
    columns = skill_columns(records)
    return {(r["method"], r["scene_index"]): {**{k: _metric(r, k) for k, _ in columns}, **r["metrics"]}
            for r in records}


def count_column(skill: str) -> str:
    """The metric counting an episode's actions of ``skill`` (its config name): the name in the plural
    (``view`` -> ``views``, ``push`` -> ``pushes``)."""
    return skill + ("es" if skill.endswith(("s", "sh", "ch", "x", "z")) else "s")


def success_column(skill: str) -> str:
    """The metric holding the share of a manipulation skill's actions that succeeded (``Outcome.success``)."""
    return f"{skill}_success"


def successes(metrics: dict[str, Any], skill: str) -> int:
    """Actions of ``skill`` in an episode that succeeded (for a grasp skill: held their object);
    ``success_column(skill)`` is their share."""
    n = metrics.get(count_column(skill))
    return round(metrics[success_column(skill)] * n) if n else 0


def crash_record(task: BenchTask, error: str, trace: str, seconds: float | None = None) -> dict[str, Any]:
    return {"method": task.method, "scene_index": task.scene_index, "status": "error", "error": error,
            "traceback": trace, "seconds": seconds, "fingerprint": task.fingerprint,
            **({"history": list(task.history)} if task.history else {})}


def run_bench_task(task: BenchTask) -> dict[str, Any]:
    """Run one episode and write its result file (module level: executors pickle it)."""
    import time

    from msmem_core.config import load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import build_episode, run_episode

    t0 = time.perf_counter()
    record: dict[str, Any] = {"method": task.method, "scene_index": task.scene_index,
                              "fingerprint": task.fingerprint, **({"history": list(task.history)} if task.history
                                                                  else {})}
    try:
        cfg = load_config(task.method, task.config_file, task.overrides)
        ep = build_episode(cfg, get_plugin_manager(), scene=SceneSpec.model_validate_json(task.scene_json))
        final = run_episode(ep, None)
        curves = {k: [r["metrics"][k] for r in ep.records] for k in CURVE_METRICS}
        kinds = [r["skill"] for r in ep.records]
        categories = {b.name: b.skill.category for b in ep.skills}
        record.update({
            "scene": ep.scene.name, "status": "ok", "metrics": episode_metrics(final, ep.records, categories),
            "paper_counts": final["paper_counts"], "curves": curves, "skills": kinds,
            "skill_categories": categories,  # per skill of the method: perception or manipulation
            "terms": [r["terms"] for r in ep.records],  # the chosen action's objective terms, per step
            "candidates": candidate_counts(ep.records), "funnel": funnel_counts(ep.records),
            "seconds": time.perf_counter() - t0,
        })
    except Exception as e:  # isolate the crash: the table reports it, the other episodes go on
        import traceback

        record = crash_record(task, f"{type(e).__name__}: {e}", traceback.format_exc(), time.perf_counter() - t0)
    write_atomic(Path(task.out_file), record)
    return record


def candidate_counts(records: list[dict[str, Any]]) -> dict[str, dict[str, int]]:
    """Per skill, candidates proposed over an episode's steps, those checked against the robot (only
    candidates that could win are: ``msmem_core.msas.decide``) and those of them it cannot follow."""
    out: dict[str, dict[str, int]] = {}
    for r in records:
        checked, dropped = r.get("reach_checked", {}), r.get("unreachable", {})
        for skill in {*r.get("candidates", {}), *dropped}:
            c = out.setdefault(skill, {"proposed": 0, "checked": 0, "unreachable": 0})
            c["proposed"] += int(r.get("candidates", {}).get(skill, 0))
            c["checked"] += int(checked.get(skill, 0))
            c["unreachable"] += int(dropped.get(skill, 0))
    return out


def episode_metrics(final: dict[str, Any], records: list[dict[str, Any]],
                    skills: Mapping[str, Category]) -> dict[str, Any]:
    """An episode's table metrics from ``run_episode``'s final metrics, its step records and its
    method's skills (config name -> ``Skill.category``; a skill the records name beyond them takes its
    actions' category). Per skill, ``count_column``: how often it acted; per manipulation skill,
    ``success_column``: the share of its actions that succeeded (NaN if it never acted). ``falls``:
    manipulations after which an object fell or left the shelf; ``fell``: 1 if one did, 0 if not, NaN
    for an episode that never manipulated (so a column's mean is the share of manipulating episodes
    with a fall)."""
    kinds = [r["skill"] for r in records]
    category = {**{r["skill"]: r["action"]["category"] for r in records}, **skills}
    names = list(dict.fromkeys([*skills, *kinds]))
    outcomes = {s: [r["success"] for r in records if r["skill"] == s] for s in names}
    return {
        **{k: final[k] for k in ("occupancy_iou", "semantic_miou", "observable_iou", "semantic_miou_bev",
                                 "position_change_m", "occupancy_nll", "semantic_nll", *PAPER_METRIC_KEYS)},
        **{k: int(final[k]) for k, _ in COUNT_METRICS},
        **{count_column(s): len(outcomes[s]) for s in names},
        **{success_column(s): float(np.mean(outcomes[s])) if outcomes[s] else float("nan")
           for s in names if category[s] == "manipulation"},
        "falls": int(final["falls"]),
        "fell": (float(final["falls"] > 0) if any(category[k] == "manipulation" for k in kinds)
                 else float("nan")),
    }


def skill_columns(results: Iterable[dict[str, Any]]) -> list[tuple[str, str]]:
    """(metric, label) of the skills' columns of Table I, from what the finished episodes recorded: every
    metric of theirs outside ``TABLE_METRICS`` and ``COUNT_METRICS`` is one (``episode_metrics``), the
    action counts first, in the order the episodes name them, then the success shares."""
    keys = dict.fromkeys(k for r in results if r.get("status") == "ok" for k in r["metrics"] if k not in _FIXED)
    counts = [(k, k) for k in keys if not _is_success(k)]
    shares = [(k, k.removesuffix("_success") + " success") for k in keys if _is_success(k)]
    return counts + shares


def _is_success(metric: str) -> bool:
    return metric.endswith("_success")


def table_columns(skills: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """(metric, label) of every column of Table I: ``TABLE_METRICS`` with the skills' columns before ``falls``."""
    fixed = [(k, label) for k, label, _ in TABLE_METRICS]
    at = next(i for i, (k, _) in enumerate(fixed) if k == "falls")
    return [*fixed[:at], *skills, *fixed[at:]]


def _counts(v: Any) -> bool:
    """Whether a metric value enters its column's mean (present and not NaN)."""
    return v is not None and not (isinstance(v, float) and math.isnan(v))


def mean_ci(x: list[float]) -> tuple[float, float]:
    """Mean and the half-width of its 95% t-interval (nan-safe)."""
    from scipy import stats
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


def cumulative_difference(a: dict[int, dict[str, Any]], b: dict[int, dict[str, Any]], key: str,
                          resamples: int = 2000, seed: int = 0) -> tuple[float, float, float]:
    """Suite-cumulative paper metric ``key`` of ``a`` minus ``b`` over the scenes both hold (``a``, ``b``:
    ``paper_counts`` per scene index), and its paired percentile-bootstrap 95% interval: scenes are
    drawn with replacement, the same draw for both, and the counts of the draw summed before dividing."""
    scenes = sorted(set(a) & set(b))
    if not scenes:
        return float("nan"), float("nan"), float("nan")

    needed = PAPER_METRIC_COUNTS[key]
    stacked = [{k: np.stack([np.asarray(side[s][k], dtype=np.float64) for s in scenes]) for k in needed}
               for side in (a, b)]  # [scene, ...] per count, so a draw sums by its scene multiplicities

    def diff(times: NDArray[np.float64]) -> NDArray[np.float64]:
        """The difference for every row of ``times`` (draws x scenes: how often each scene is drawn)."""
        sa, sb = ({k: times @ v.reshape(len(scenes), -1) for k, v in side.items()} for side in stacked)
        return _metric_rows(key, sa) - _metric_rows(key, sb)

    rng = np.random.default_rng(seed)
    n = len(scenes)
    draws = rng.integers(0, n, (resamples, n))  # the same stream as one draw of n at a time
    times = np.zeros((resamples, n))
    np.add.at(times, (np.arange(resamples)[:, None], draws), 1.0)
    boot = diff(times)
    lo, hi = np.nanpercentile(boot, [2.5, 97.5]) if not np.isnan(boot).all() else (np.nan, np.nan)
    return float(diff(np.ones((1, n)))[0]), float(lo), float(hi)


def _metric_rows(key: str, counts: dict[str, NDArray[np.float64]]) -> NDArray[np.float64]:
    """``paper_metrics_from_counts(...)[key]`` for every row of ``counts`` (rows x classes or bins)."""
    if key.endswith("_ece"):
        count, conf, correct = (counts[k] for k in PAPER_METRIC_COUNTS[key])
        total = count.sum(axis=1)
        gap = np.abs(correct - conf).sum(axis=1)
        return np.divide(gap, total, out=np.full(len(total), np.nan), where=total > 0)
    inter, union = (counts[k] for k in PAPER_METRIC_COUNTS[key])
    seen = union > 0
    ratio = np.divide(inter, union, out=np.zeros_like(inter), where=seen)
    k = seen.sum(axis=1)
    return np.divide(ratio.sum(axis=1), k, out=np.full(len(k), np.nan), where=k > 0)


def read_paper_counts(folder: Path, method: str | None = None) -> dict[int, dict[str, Any]]:
    """``paper_counts`` per scene index of one method's finished episodes in a bench folder (the only
    method when ``method`` is None; episodes written before the counts existed are left out)."""
    ok = [r for r in _finished_records(folder) if "paper_counts" in r]
    methods = sorted({r["method"] for r in ok})
    if method is None and len(methods) > 1:
        raise UserError(f"{folder} holds methods {', '.join(methods)}; name one")
    return {r["scene_index"]: r["paper_counts"] for r in ok if method is None or r["method"] == method}


def summarise(results: list[dict[str, Any]], methods: list[str]) -> dict[str, Any]:
    """Per method: mean and 95% CI over scenes of every table metric (episodes lacking a metric, written
    before it existed, are left out of its column), Table II counts, and the suite-cumulative paper metrics;
    plus paired differences against the first method."""
    ok = [r for r in results if r.get("status") == "ok"]
    skills = skill_columns(ok)
    columns = [k for k, _ in table_columns(skills)]
    table: dict[str, dict[str, Any]] = {}
    for m in methods:
        rows = [r for r in ok if r["method"] == m]
        values = {k: [v for r in rows if (v := _metric(r, k)) is not None] for k in columns}
        table[m] = {k: mean_ci(values[k]) for k in columns}
        table[m]["episodes"] = len(rows)
        table[m]["counted"] = {k: n for k in columns  # columns some episodes lack (older files) or
                               if (n := sum(_counts(v) for v in values[k])) < len(rows)}  # leave NaN
        table[m]["cumulative"] = cumulative(rows)
        table[m]["funnel"] = sum_funnels(r["funnel"] for r in rows if "funnel" in r)  # older files lack it
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
    return {"methods": methods, "table": table, "paired": paired, "errors": errors, "skill_columns": skills}


def _metric(record: dict[str, Any], key: str) -> Any:
    """An episode's value of a Table I column; None if it lacks it (written before it existed), except an
    action count of a skill its method does not have, which is 0."""
    metrics = record["metrics"]
    if key in metrics:
        return metrics[key]
    return None if key in _FIXED or _is_success(key) else 0


def _fmt(mc: tuple[float, float]) -> str:
    m, c = mc
    if math.isnan(m):
        return "-"
    return f"{m:.3f}" if math.isnan(c) else f"{m:.3f} ± {c:.3f}"


LABELS = {k: label for k, label, _ in TABLE_METRICS}


def table_markdown(summary: dict[str, Any]) -> str:
    columns = table_columns([(k, label) for k, label in summary.get("skill_columns", [])])
    lines = ["| method | episodes | " + " | ".join(label for _, label in columns) + " |",
             "|---|---|" + "---|" * len(columns)]
    for m in summary["methods"]:
        row = summary["table"][m]
        counted = row.get("counted", {})
        lines.append(f"| {m} | {row['episodes']} | " + " | ".join(
            _fmt(tuple(row[k])) + (f" (n={counted[k]})" if counted.get(k) else "") for k, _ in columns) + " |")
    lines += ["", "Mean ± half-width of the 95% t-interval over scenes. \"(paper)\" and ECE: the paper's own metrics",
              "([MEM]'s `Cumulative_mIoU`; docs/reference/metrics.md), per scene; episodes written before they existed",
              "are left out of those columns (n=: the episodes a column counts, where fewer than all).", ""]
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
    lines += funnel_markdown(summary["table"], summary["methods"])
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
            arr = np.array([c[:n] for c in curves], dtype=float)
            x = np.arange(1, n + 1)
            ax.plot(x, arr.mean(0), label=m)
            ax.fill_between(x, arr.mean(0) - arr.std(0), arr.mean(0) + arr.std(0), alpha=0.15)
        ax.set_xlabel("step")
        ax.set_title(k)
    if axes[0].get_legend_handles_labels()[0]:  # no curve when every episode crashed
        axes[0].legend()
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


@dataclass
class BenchPlan:
    """The episodes of a bench run: every planned result file in order, and the tasks to run."""

    files: list[Path]
    tasks: list[BenchTask]
    reused: int = 0
    notes: list[str] = field(default_factory=list)
    corrupt: list[Path] = field(default_factory=list)


def plan_bench(methods: list[str], scenes: list[SceneSpec], scene_indices: list[int], out: Path,
               overrides: dict[str, Any], config_file: str | None, threads: int, suite: str,
               retry_crashed: bool = True, rerun_mismatched: bool = False) -> BenchPlan:
    """Check the config and plugins of every method (``UserError`` before anything is written) and
    decide, per planned episode, whether its file is reused or the episode (re)runs."""
    from msmem_core.config import load_config
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.run.runner import check_components

    pm = get_plugin_manager()
    plan = BenchPlan([], [])
    mismatched: list[tuple[Path, str]] = []
    for m in methods:
        over = {**overrides, "threads": threads}
        cfg = load_config(m, config_file, over)
        versions = check_components(cfg, pm)
        for i in scene_indices:
            fp = fingerprint(cfg, suite, scenes[i], versions)
            f = out / "episodes" / f"{m}__scene{i:02d}.json"
            plan.files.append(f)
            history: tuple[dict[str, Any], ...] = ()
            if f.exists():
                try:
                    rec = read_episode(f)
                except ValueError as e:
                    plan.corrupt.append(f)
                    plan.notes.append(f"{f} is corrupt ({e}): moved to {f.name}.corrupt, rerunning it")
                else:
                    if diff := fingerprint_diff(rec.get("fingerprint"), fp):
                        if not rerun_mismatched:
                            mismatched.append((f, diff))
                            continue
                        plan.notes.append(f"{f} was made with {diff}: rerunning it (--rerun-mismatched)")
                    elif rec["status"] == "error" and retry_crashed:
                        history = (*rec.get("history", []), {k: rec.get(k) for k in ("error", "traceback", "seconds")})
                        plan.notes.append(f"{f} crashed last time ({rec.get('error')}): retrying it")
                    else:
                        plan.reused += 1
                        continue
            plan.tasks.append(BenchTask(m, i, scenes[i].model_dump_json(), over, config_file, str(f), fp, history))
    if mismatched:
        f, diff = mismatched[0]
        more = f" (and {len(mismatched) - 1} more episode files)" if len(mismatched) > 1 else ""
        raise FingerprintMismatch(f"{f} was made with {diff}{more}; rerun them with --rerun-mismatched, "
                                  "or use another --out")
    return plan


def _move_aside(f: Path) -> None:
    aside, n = f.with_name(f.name + ".corrupt"), 1
    while aside.exists():
        aside, n = f.with_name(f"{f.name}.corrupt{n}"), n + 1
    os.replace(f, aside)


def _prepare_folder(folder: Path) -> None:
    """Create the episodes folder and check it is writable (``UserError`` naming it otherwise)."""
    probe = folder / f".write-check-{os.getpid()}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.write_text("")
        probe.unlink()
    except OSError as e:
        raise UserError(f"cannot write bench results to {folder}: {e.strerror or e}") from e


def run_bench(methods: list[str], scenes: list[SceneSpec], scene_indices: list[int], out: Path,
              overrides: dict[str, Any], config_file: str | None, executor: str, workers: int,
              threads: int, progress: bool = True, suite: str = "custom", retry_crashed: bool = True,
              rerun_mismatched: bool = False, wait: bool = False) -> dict[str, Any]:
    """Plan (:func:`plan_bench`), run the episodes to run, and write ``table.md``, ``results.json`` and
    ``curves.png`` from exactly the planned episodes. ``suite`` names the scenes in the fingerprints.

    The results folder is locked from before the plan until the table is written (``OUT/.msmem.lock``,
    ``msmem_core.run.lock``): another bench into it stops with :class:`~msmem_core.run.lock.FolderLocked`
    naming the process, or with ``wait`` waits for it."""
    from contextlib import ExitStack

    from msmem_core.run.lock import FolderLocked, folder_lock

    if workers < 1 or threads < 1:
        raise UserError(f"--workers and --threads must be >= 1 (got {workers} and {threads})")
    with ExitStack() as held:
        try:
            held.enter_context(folder_lock(out, wait=wait))
        except FolderLocked:
            raise
        except OSError as e:  # e.g. --out is a file
            raise UserError(f"cannot write bench results to {out / 'episodes'}: {e.strerror or e}") from e
        return _run_bench(methods, scenes, scene_indices, out, overrides, config_file, executor, workers, threads,
                          progress, suite, retry_crashed, rerun_mismatched)


def _episode_name(task: BenchTask) -> str:
    return f"{task.method} scene {task.scene_index}"


def _run_bench(methods: list[str], scenes: list[SceneSpec], scene_indices: list[int], out: Path,
               overrides: dict[str, Any], config_file: str | None, executor: str, workers: int,
               threads: int, progress: bool, suite: str, retry_crashed: bool,
               rerun_mismatched: bool) -> dict[str, Any]:
    from msmem_core.run.executors import TaskFailure, run_tasks

    plan = plan_bench(methods, scenes, scene_indices, out, overrides, config_file, threads, suite, retry_crashed,
                      rerun_mismatched)
    _prepare_folder(out / "episodes")
    for f in plan.corrupt:
        _move_aside(f)
    for note in plan.notes:
        print(f"msmem bench: {note}", file=sys.stderr)
    lost: dict[Path, str] = {}

    def on_result(index: int, res: Any) -> None:
        if isinstance(res, TaskFailure):  # e.g. a dead worker, or the episode file could not be written
            task = plan.tasks[index]
            if res.worker_died:
                print(f"msmem bench: episode {_episode_name(task)} killed its worker process (killed, e.g. by the "
                      f"out-of-memory killer, or crashed in native code): recorded as crashed in {task.out_file}; "
                      "the other episodes go on", file=sys.stderr, flush=True)
            try:
                write_atomic(Path(task.out_file), crash_record(task, res.error, res.traceback))
            except OSError as e:
                lost[Path(task.out_file)] = f"{res.error}; writing its crash record failed too: {e}"

    def on_worker_death(indices: list[int]) -> None:
        names = ", ".join(_episode_name(plan.tasks[i]) for i in indices)
        again = ("rerunning it alone" if len(indices) == 1
                 else "rerunning them one at a time to find the one that killed it")
        print(f"msmem bench: a worker process died while running episode{'s' * (len(indices) > 1)} {names}; "
              f"{again}", file=sys.stderr, flush=True)

    if plan.tasks:
        run_tasks(run_bench_task, plan.tasks, executor=executor, workers=workers, threads=threads,
                  progress=progress, description="episodes", on_result=on_result, on_worker_death=on_worker_death)
    results, missing = [], []
    for f in plan.files:
        try:
            results.append(read_episode(f))
        except (OSError, ValueError) as e:
            missing.append(f"{f} ({lost.get(f) or e})")
    if missing:
        raise IncompleteError(f"{len(missing)} of {len(plan.files)} planned episodes have no result: "
                              + "; ".join(missing))
    summary = summarise(results, methods)
    summary["skipped_finished"] = plan.reused
    summary["ran"] = len(plan.tasks)
    write_text_atomic(out / "table.md", table_markdown(summary))
    write_atomic(out / "results.json", {"summary": summary, "episodes": results})
    plot_curves(results, methods, out / "curves.png")
    return summary
