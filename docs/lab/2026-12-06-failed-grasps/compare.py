"""Two bench folders of the same methods and scenes under two configs (A: the defaults, B: a change):
per method, paired per scene, the change in 2-D semantic and occupancy mIoU (mean and 95 %
t-interval), pooled values, Position Change, grasps held, and on how many scenes B took A's episode
(the same skill at every step and the same map metrics after it, ``results.same_episodes``).

    .venv/bin/python docs/lab/2026-12-06-failed-grasps/compare.py FOLDER_A FOLDER_B
"""

from __future__ import annotations

import sys
from pathlib import Path

from msmem_core.run.bench import cumulative, mean_ci
from msmem_core.run.results import same_episodes
from msmem_core.run.tracking import load_episodes

KEYS = ("semantic_miou_2d", "occupancy_miou")


def main(fa: str, fb: str) -> None:
    a = {(e["method"], e["scene_index"]): e for e in load_episodes(Path(fa))}
    b = {(e["method"], e["scene_index"]): e for e in load_episodes(Path(fb))}
    print("| method | scenes | same episode | 2-D semantic mIoU, B - A per scene | pooled A / B "
          "| occupancy mIoU, B - A | pooled A / B | Position Change A / B (m) | grasps held A / B |")
    print("|---|---|---|---|---|---|---|---|---|")
    for m in sorted({k[0] for k in a} & {k[0] for k in b}):
        scenes = sorted({s for mm, s in a if mm == m} & {s for mm, s in b if mm == m})
        pair = [{**a[m, s], "method": "A"} for s in scenes] + [{**b[m, s], "method": "B"} for s in scenes]
        same = len(same_episodes(pair, scenes).get(("A", "B"), []))
        diff = {k: mean_ci([b[m, s]["metrics"][k] - a[m, s]["metrics"][k] for s in scenes]) for k in KEYS}
        pa, pb = (cumulative([side[m, s] for s in scenes]) for side in (a, b))
        pc = [mean_ci([side[m, s]["metrics"]["position_change_m"] for s in scenes])[0] for side in (a, b)]
        held = [(sum(round(side[m, s]["metrics"].get("grasps", 0) * (side[m, s]["metrics"].get("grasp_success") or 0))
                     for s in scenes), sum(side[m, s]["metrics"].get("grasps", 0) for s in scenes))
                for side in (a, b)]
        cells = [f"{d[0]:+.3f} ± {d[1]:.3f}" for d in (diff[k] for k in KEYS)]
        print(f"| {m} | {len(scenes)} | {same} | {cells[0]} "
              f"| {pa['semantic_miou_2d']:.3f} / {pb['semantic_miou_2d']:.3f} | {cells[1]} "
              f"| {pa['occupancy_miou']:.3f} / {pb['occupancy_miou']:.3f} | {pc[0]:.3f} / {pc[1]:.3f} | "
              f"{held[0][0]} of {held[0][1]} / {held[1][0]} of {held[1][1]} |")


if __name__ == "__main__":
    main(*sys.argv[1:3])
