"""Table I with the episodes of a variant swapped in where it ran them, against Table I as committed.

    .venv/bin/python docs/lab/2026-12-06-failed-manipulation-rays/table.py docs/results/table1 RUNS VARIANT

RUNS/VARIANT/METHOD/sceneNN are `msmem run` folders. The variant acts only after a failed manipulation,
so every Table I episode without one is the same under it, and `run-hard25.sh` ran only the others.
Prints, per method: the swapped episodes' changes, then the pooled metrics of all 25 scenes with them
swapped in, and paired per-scene differences over the 25 against view-only and grasp-only.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from msmem_core.run.bench import cumulative, mean_ci
from msmem_core.run.tracking import load_episodes

KEYS = ("semantic_miou_2d", "occupancy_miou")


def failed(m: dict) -> str:
    """An episode's grasps, and in brackets how many failed."""
    n = m.get("grasps") or 0
    return f"{n} ({round(n * (1 - (m.get('grasp_success') or 0)))})"


def main(table: str, runs: str, variant: str) -> None:
    a = {(e["method"], e["scene_index"]): e for e in load_episodes(Path(table))}
    b = dict(a)
    swapped = []
    for run in sorted((Path(runs) / variant).glob("*/scene*")):
        if not (run / "metrics.json").exists():
            continue
        m = json.loads((run / "metrics.json").read_text())
        key = (run.parent.name, int(run.name.removeprefix("scene")))
        steps = [json.loads(line) for line in (run / "steps.jsonl").read_text().splitlines()]
        grasps = [r for r in steps if r["skill"] == "grasp"]
        m = {**m, "grasps": len(grasps), "grasp_success": (sum(r["success"] for r in grasps) / len(grasps)
                                                            if grasps else None)}
        b[key] = {**a[key], "metrics": m, "paper_counts": m["paper_counts"]}
        swapped.append(key)
    print(f"{len(swapped)} episodes swapped in from {runs}/{variant}\n")
    print("| method, scene | 2-D semantic mIoU before -> after | occupancy mIoU | Position Change (m) "
          "| grasps (failed) |")
    print("|---|---|---|---|---|")
    for key in sorted(swapped):
        ma, mb = a[key]["metrics"], b[key]["metrics"]
        print(f"| {key[0]} {key[1]} | {ma['semantic_miou_2d']:.3f} -> {mb['semantic_miou_2d']:.3f} "
              f"| {ma['occupancy_miou']:.3f} -> {mb['occupancy_miou']:.3f} "
              f"| {ma['position_change_m']:.3f} -> {mb['position_change_m']:.3f} | {failed(ma)} -> {failed(mb)} |")
    methods = sorted({k[0] for k in a})
    scenes = sorted({k[1] for k in a})
    print("\n| method | pooled 2-D semantic before / after | pooled occupancy before / after "
          "| Position Change before / after (m) | after - view-only, semantic per scene "
          "| after - grasp-only (after), semantic per scene |")
    print("|---|---|---|---|---|---|")
    for meth in methods:
        pa, pb = (cumulative([side[meth, s] for s in scenes]) for side in (a, b))
        pc = [mean_ci([side[meth, s]["metrics"]["position_change_m"] for s in scenes])[0] for side in (a, b)]
        dv = mean_ci([b[meth, s]["metrics"]["semantic_miou_2d"] - b["view-only", s]["metrics"]["semantic_miou_2d"]
                      for s in scenes])
        dg = mean_ci([b[meth, s]["metrics"]["semantic_miou_2d"] - b["grasp-only", s]["metrics"]["semantic_miou_2d"]
                      for s in scenes])
        print(f"| {meth} | {pa['semantic_miou_2d']:.3f} / {pb['semantic_miou_2d']:.3f} "
              f"| {pa['occupancy_miou']:.3f} / {pb['occupancy_miou']:.3f} | {pc[0]:.3f} / {pc[1]:.3f} "
              f"| {dv[0]:+.3f} ± {dv[1]:.3f} | {dg[0]:+.3f} ± {dg[1]:.3f} |")


if __name__ == "__main__":
    main(*sys.argv[1:4])
