"""Does predicted IG track what the map gains? Per step of bench episodes: the chosen action's IG term
against the realised change of both paper map metrics, and their rank correlation.

A view's realised gain is the change over its own step. A manipulation's IG is the IG of the best view
after it, and that view is the next step (its associated view): its realised gain is the change over
both steps (the manipulation and its view), and the associated view is not counted again.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Sequence
from functools import lru_cache
from pathlib import Path
from typing import Any

METRICS = ("occupancy_miou", "semantic_miou_2d")
VIEW = "view"  # the kind of a perception skill's decision rows, not a skill name
MANIPULATION = "manipulation"
KINDS = (VIEW, MANIPULATION)


def skill_categories(episode: dict[str, Any]) -> dict[str, str]:
    """Category (``Skill.category``) of each skill of an episode file, by its config name: as the file
    records them (``skill_categories``), or, in a file written before it did, as the registered skill
    of that name declares."""
    recorded = episode.get("skill_categories")
    if isinstance(recorded, dict):
        return recorded
    return dict(_registered_categories(tuple(dict.fromkeys(episode.get("skills") or []))))


@lru_cache(maxsize=64)
def _registered_categories(names: tuple[str, ...]) -> tuple[tuple[str, str], ...]:
    """(name, category) of the registered skills of these names (the plugin manager is built once per set)."""
    from msmem_core.plugins import get_plugin_manager

    specs = get_plugin_manager().skills()
    return tuple((name, category) for name in names
                 if name in specs and (category := getattr(specs[name].factory, "category", None)) is not None)


def step_rows(episode: dict[str, Any]) -> list[dict[str, Any]]:
    """One row per decision of an episode file: step, kind (view or manipulation: its skill's category
    is perception or not), predicted IG and the realised change of each metric. Steps without terms
    (files written before they were kept) give none."""
    terms, skills, curves = episode.get("terms"), episode.get("skills"), episode.get("curves", {})
    if not terms or not skills or any(k not in curves for k in METRICS):
        return []
    categories = skill_categories(episode)
    rows = []
    t = 1  # step 0 has no metric before it in the curves
    while t < len(skills):
        ig = (terms[t] or {}).get("ig")
        manip = categories.get(skills[t]) != "perception"
        end = t + 1 if manip and t + 1 < len(skills) else t
        if ig is not None and all(math.isfinite(curves[k][end]) and math.isfinite(curves[k][t - 1]) for k in METRICS):
            rows.append({"method": episode["method"], "scene": episode["scene_index"], "step": t,
                         "kind": MANIPULATION if manip else VIEW, "skill": skills[t], "ig": float(ig),
                         **{f"d_{k}": float(curves[k][end] - curves[k][t - 1]) for k in METRICS}})
        t = end + 1
    return rows


def spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rank correlation (average ranks for ties); nan for fewer than 3 pairs or no spread."""
    if len(x) < 3:
        return math.nan
    from scipy.stats import spearmanr

    r = spearmanr(x, y).statistic
    return float(r) if r is not None and math.isfinite(r) else math.nan


def tracking_summary(rows: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per method and kind (all decisions, views, manipulations): how many, and the rank correlation of
    predicted IG with each metric's realised change."""
    rows = list(rows)
    out = []
    for method in dict.fromkeys(r["method"] for r in rows):
        for kind in ("all", *KINDS):
            sel = [r for r in rows if r["method"] == method and kind in ("all", r["kind"])]
            if not sel:
                continue
            ig = [r["ig"] for r in sel]
            out.append({"method": method, "kind": kind, "decisions": len(sel),
                        **{f"rho_{k}": spearman(ig, [r[f"d_{k}"] for r in sel]) for k in METRICS}})
    return out


def load_episodes(folder: Path) -> list[dict[str, Any]]:
    """The ok episodes of a bench folder (``episodes/*.json``)."""
    eps = [json.loads(f.read_text()) for f in sorted((folder / "episodes").glob("*.json"))]
    return [e for e in eps if e.get("status") == "ok"]


def format_tracking(summary: Sequence[dict[str, Any]]) -> str:
    lines = ["| method | decisions | count | IG vs occupancy mIoU gain (Spearman) | IG vs 2-D semantic mIoU gain |",
             "|---|---|---|---|---|"]
    for s in summary:
        lines.append(f"| {s['method']} | {s['kind']} | {s['decisions']} | {s['rho_occupancy_miou']:+.2f} | "
                     f"{s['rho_semantic_miou_2d']:+.2f} |")
    return "\n".join(lines)


def per_step_figure(rows: Sequence[dict[str, Any]], out: Path) -> None:
    """Scatter of predicted IG against the realised 2-D semantic and occupancy gains, per kind."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), constrained_layout=True)
    for ax, k, label in zip(axes, METRICS, ("occupancy mIoU", "2-D semantic mIoU"), strict=True):
        for kind, marker in zip(KINDS, (".", "x"), strict=True):
            sel = [r for r in rows if r["kind"] == kind]
            if sel:
                ax.scatter([r["ig"] for r in sel], [r[f"d_{k}"] for r in sel], s=10, marker=marker, label=kind,
                           alpha=0.6)
        ax.set_xlabel("predicted IG of the chosen action (nats)")
        ax.set_ylabel(f"realised change of {label}")
        ax.axhline(0, color="grey", lw=0.5)
    axes[0].legend()
    fig.savefig(out, dpi=110)
    plt.close(fig)

