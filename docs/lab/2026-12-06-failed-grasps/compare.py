"""Two bench folders of the same methods and scenes under two configs (A: the defaults, B: a change):
per method, paired per scene, the change in 2-D semantic and occupancy mIoU (mean and 95 %
t-interval), pooled values, Position Change, grasps and grasps held, and how many scenes took the
same episode (the same skill at every step and final metrics within 1e-3).

    .venv/bin/python docs/lab/2026-12-06-failed-grasps/compare.py FOLDER_A FOLDER_B
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy import stats

from msmem_core.run.bench import cumulative

KEYS = ("semantic_miou_2d", "occupancy_miou")


def load(folder: str) -> dict[tuple[str, int], dict]:
    out = {}
    for f in sorted(Path(folder, "episodes").glob("*__scene*.json")):
        d = json.loads(f.read_text())
        if d.get("status") == "ok":
            out[(d["method"], d["scene_index"])] = d
    return out


def interval(d: np.ndarray) -> str:
    if len(d) < 2:
        return f"{d.mean():+.3f}"
    half = stats.t.ppf(0.975, len(d) - 1) * d.std(ddof=1) / np.sqrt(len(d))
    return f"{d.mean():+.3f} ± {half:.3f}"


def held(d: dict) -> int:
    m = d["metrics"]
    return round(m.get("grasps", 0) * m.get("grasp_success", 0.0))


def main(fa: str, fb: str) -> None:
    a, b = load(fa), load(fb)
    print("| method | scenes | same episode | 2-D semantic mIoU, B - A per scene | pooled A / B "
          "| occupancy mIoU, B - A | pooled A / B | Position Change A / B (m) | grasps held A / B |")
    print("|---|---|---|---|---|---|---|---|---|")
    for m in sorted({k[0] for k in a} & {k[0] for k in b}):
        scenes = sorted({s for mm, s in a if mm == m} & {s for mm, s in b if mm == m})
        same = sum(a[m, s]["skills"] == b[m, s]["skills"] and all(
            abs(a[m, s]["metrics"][k] - b[m, s]["metrics"][k]) <= 1e-3 for k in KEYS) for s in scenes)
        diff = {k: np.array([b[m, s]["metrics"][k] - a[m, s]["metrics"][k] for s in scenes]) for k in KEYS}
        pa, pb = (cumulative([side[m, s] for s in scenes]) for side in (a, b))
        pc = [np.mean([side[m, s]["metrics"]["position_change_m"] for s in scenes]) for side in (a, b)]
        g = [(sum(held(side[m, s]) for s in scenes), sum(side[m, s]["metrics"].get("grasps", 0) for s in scenes))
             for side in (a, b)]
        print(f"| {m} | {len(scenes)} | {same} | {interval(diff['semantic_miou_2d'])} | "
              f"{pa['semantic_miou_2d']:.3f} / {pb['semantic_miou_2d']:.3f} | {interval(diff['occupancy_miou'])} | "
              f"{pa['occupancy_miou']:.3f} / {pb['occupancy_miou']:.3f} | {pc[0]:.3f} / {pc[1]:.3f} | "
              f"{g[0][0]} of {g[0][1]} / {g[1][0]} of {g[1][1]} |")


if __name__ == "__main__":
    main(*sys.argv[1:3])
