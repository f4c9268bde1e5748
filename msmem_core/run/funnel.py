"""The candidate funnel over episodes: how many candidates each skill had after each stage of its
proposal (``interfaces.Funnel``, the step records' ``funnel``), summed over an episode's steps and over
a bench's episodes, and the bench table's section that reports it.

A skill is *asked* at a step when MSAS asks it to propose: every step for a perception skill, the
steps where manipulation is allowed for a manipulation skill. ``with_candidates`` counts the asked
steps at which it proposed at least one candidate, ``chosen`` the steps its action was taken.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any


def funnel_counts(records: Iterable[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per skill, over one episode's step records: ``asked``, ``with_candidates``, ``chosen`` and
    ``stages`` (each stage's candidates summed over the asked steps, in the skill's stage order)."""
    out: dict[str, dict[str, Any]] = {}
    for r in records:
        for skill, stages in r.get("funnel", {}).items():
            c = out.setdefault(skill, {"asked": 0, "with_candidates": 0, "chosen": 0, "stages": {}})
            c["asked"] += 1
            c["with_candidates"] += int(stages.get("proposed", 0) > 0)
            c["chosen"] += int(stages.get("chosen", 0))
            for stage, n in stages.items():
                c["stages"][stage] = c["stages"].get(stage, 0) + int(n)
    return out


def sum_funnels(funnels: Iterable[dict[str, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """``funnel_counts`` of several episodes added up per skill, with ``episodes``: how many had the skill."""
    out: dict[str, dict[str, Any]] = {}
    for f in funnels:
        for skill, c in f.items():
            s = out.setdefault(skill, {"episodes": 0, "asked": 0, "with_candidates": 0, "chosen": 0, "stages": {}})
            s["episodes"] += 1
            for k in ("asked", "with_candidates", "chosen"):
                s[k] += int(c[k])
            for stage, n in c["stages"].items():
                s["stages"][stage] = s["stages"].get(stage, 0) + int(n)
    return out


def funnel_markdown(table: dict[str, dict[str, Any]], methods: list[str]) -> list[str]:
    """The bench table's candidate-funnel section (lines), from each method's summed funnel
    (``table[method]["funnel"]``); nothing when no episode recorded one."""
    rows = [(m, skill, c) for m in methods for skill, c in table[m].get("funnel", {}).items()]
    if not rows:
        return []
    lines = ["", "## Candidate funnel", "",
             "Per method and skill, over the episodes: the steps at which the skill proposed at least one",
             "candidate of those it was asked at (a manipulation skill: the steps manipulation was allowed), the",
             "steps its action was taken, and its candidates after each stage of its proposal summed over the",
             "steps (the step records' `funnel`; `proposed`: returned to MSAS).", "",
             "| method | skill | episodes | steps with candidates / asked | chosen | candidates after each stage |",
             "|---|---|---|---|---|---|"]
    for m, skill, c in rows:
        share = f" ({c['with_candidates'] / c['asked']:.0%})" if c["asked"] else ""
        stages = " → ".join(f"{k} {v:,}" for k, v in c["stages"].items() if k != "chosen")
        lines.append(f"| {m} | {skill} | {c['episodes']} | {c['with_candidates']} / {c['asked']}{share} | "
                     f"{c['chosen']} | {stages} |")
    return lines
