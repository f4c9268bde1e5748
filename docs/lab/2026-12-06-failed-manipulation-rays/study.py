"""Two sets of `msmem run` folders (RUNS/VARIANT/METHOD/sceneNN) compared per method, paired per scene,
and every grasp of them sorted by its object's class and its approach.

    .venv/bin/python docs/lab/2026-12-06-failed-manipulation-rays/study.py RUNS A B

Prints, per method: B - A in 2-D semantic and occupancy mIoU (mean and 95 % t-interval over scenes),
the pooled values (the reference code's ``Cumulative_mIoU``), Position Change, grasps held, grasps
that closed on nothing, and on how many scenes B took A's episode (the same skill at every step and
the same final metrics). Then, for A and B, the grasps by target class and approach: ``above`` when
the approach points more than 45 deg below the horizontal, ``side`` otherwise, held or not.
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from msmem_core.run.bench import cumulative, mean_ci
from msmem_core.world.placement import load_scene

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "2026-12-06-failed-grasps"))
from failed_grasps import kind  # the failed-grasps study's sorting of a failed grasp

KEYS = ("semantic_miou_2d", "occupancy_miou")


def episode(run: Path) -> dict:
    metrics = json.loads((run / "metrics.json").read_text())
    steps = [json.loads(line) for line in (run / "steps.jsonl").read_text().splitlines()]
    scene = load_scene(str(run / "scene.json"))
    classes = {o.class_id: o.class_name for o in scene.objects}
    grasps = []
    for r in steps:
        if r["skill"] != "grasp":
            continue
        approach = np.asarray(r["action"]["pose"])[:3, 2]
        info = r["info"]
        grasps.append({
            "class": classes.get(r["action"].get("target_class")),
            "above": bool(approach[2] < -np.sqrt(0.5)),
            "held": info.get("held") is not None,
            "nothing": info.get("held") is None and kind(info) == "closed on nothing",
        })
    return {"metrics": metrics, "paper_counts": metrics.get("paper_counts", {}),
            "skills": [r["skill"] for r in steps], "grasps": grasps}


def load(root: Path) -> dict[tuple[str, str], dict]:
    return {(m.name, s.name): episode(s) for m in sorted(root.iterdir()) if m.is_dir()
            for s in sorted(m.iterdir()) if (s / "metrics.json").exists()}


def main(runs: str, va: str, vb: str) -> None:
    a, b = load(Path(runs) / va), load(Path(runs) / vb)
    print(f"A: {va}, B: {vb}\n")
    print("| method | scenes | same episode | 2-D semantic mIoU, B - A per scene | pooled A / B "
          "| occupancy mIoU, B - A | pooled A / B | Position Change A / B (m) | grasps held A / B "
          "| closed on nothing A / B |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for m in sorted({k[0] for k in a} & {k[0] for k in b}):
        scenes = sorted({s for mm, s in a if mm == m} & {s for mm, s in b if mm == m})
        same = sum(a[m, s]["skills"] == b[m, s]["skills"]
                   and all(a[m, s]["metrics"][k] == b[m, s]["metrics"][k] for k in KEYS) for s in scenes)
        diff = [mean_ci([b[m, s]["metrics"][k] - a[m, s]["metrics"][k] for s in scenes]) for k in KEYS]
        pa, pb = (cumulative([side[m, s] for s in scenes]) for side in (a, b))
        pc = [mean_ci([side[m, s]["metrics"]["position_change_m"] for s in scenes])[0] for side in (a, b)]
        held = [(sum(g["held"] for s in scenes for g in side[m, s]["grasps"]),
                 sum(len(side[m, s]["grasps"]) for s in scenes)) for side in (a, b)]
        nothing = [sum(g["nothing"] for s in scenes for g in side[m, s]["grasps"]) for side in (a, b)]
        print(f"| {m} | {len(scenes)} | {same} | {diff[0][0]:+.3f} ± {diff[0][1]:.3f} "
              f"| {pa['semantic_miou_2d']:.3f} / {pb['semantic_miou_2d']:.3f} "
              f"| {diff[1][0]:+.3f} ± {diff[1][1]:.3f} | {pa['occupancy_miou']:.3f} / {pb['occupancy_miou']:.3f} "
              f"| {pc[0]:.3f} / {pc[1]:.3f} | {held[0][0]} of {held[0][1]} / {held[1][0]} of {held[1][1]} "
              f"| {nothing[0]} / {nothing[1]} |")
    for name, side in ((va, a), (vb, b)):
        count = Counter((g["class"], "above" if g["above"] else "side", g["held"])
                        for e in side.values() for g in e["grasps"])
        print(f"\ngrasps of {name} (class, approach: held / all)")
        for cls, way in sorted({(c, w) for c, w, _ in count}, key=str):
            print(f"  {cls!s:20s} {way:5s} {count[cls, way, True]} / {count[cls, way, True] + count[cls, way, False]}")


if __name__ == "__main__":
    main(*sys.argv[1:4])
