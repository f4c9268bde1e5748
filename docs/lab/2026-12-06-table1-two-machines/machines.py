"""Two bench folders of the same command, run on two machines: per method, how many episodes took the
same actions step for step (the same skill at every step and final metrics within 1e-3), how far
the others' final 2-D semantic and occupancy mIoU moved, and each folder's pooled values.

    python machines.py FOLDER_A FOLDER_B
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from msmem_core.run.bench import cumulative

KEYS = ("semantic_miou_2d", "occupancy_miou")


def load(folder: str) -> dict[tuple[str, int], dict]:
    out = {}
    for f in sorted(Path(folder, "episodes").glob("*__scene*.json")):
        d = json.loads(f.read_text())
        if d.get("status") == "ok":
            out[(d["method"], d["scene_index"])] = d
    return out


def same_episode(a: dict, b: dict) -> bool:
    return a.get("skills") == b.get("skills") and all(
        abs(a["metrics"][k] - b["metrics"][k]) <= 1e-3 for k in KEYS)


def main(fa: str, fb: str) -> None:
    a, b = load(fa), load(fb)
    methods = sorted({m for m, _ in a} & {m for m, _ in b})
    print("| method | scenes | same episode | largest move, 2-D semantic / occupancy "
          "| pooled 2-D semantic A / B | pooled occupancy A / B |")
    print("|---|---|---|---|---|---|")
    for m in methods:
        scenes = sorted({s for mm, s in a if mm == m} & {s for mm, s in b if mm == m})
        same = sum(same_episode(a[m, s], b[m, s]) for s in scenes)
        moves = [max(abs(a[m, s]["metrics"][k] - b[m, s]["metrics"][k]) for s in scenes) for k in KEYS]
        pa, pb = (cumulative([side[m, s] for s in scenes]) for side in (a, b))
        print(f"| {m} | {len(scenes)} | {same} | {moves[0]:.3f} / {moves[1]:.3f} | "
              f"{pa['semantic_miou_2d']:.3f} / {pb['semantic_miou_2d']:.3f} | "
              f"{pa['occupancy_miou']:.3f} / {pb['occupancy_miou']:.3f} |")


if __name__ == "__main__":
    main(*sys.argv[1:3])
