"""Paired comparison of bench folders, per method: steps with grasp candidates / asked, grasps, objects
taken out, episodes with a fall, and the per-scene mean of both map metrics, with the paired difference
(mean ± 95% t half-width) against the first folder over the scenes all folders finished.

    python compare.py BASE_FOLDER:METHOD OTHER_FOLDER:METHOD [...]
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
from scipy import stats


def load(folder: str, method: str) -> dict[int, dict]:
    out = {}
    for f in sorted(Path(folder, "episodes").glob(f"{method}__scene*.json")):
        d = json.loads(f.read_text())
        if d.get("status") == "ok":
            out[d["scene_index"]] = d
    return out


def paired(x: list[float]) -> str:
    a = np.asarray(x, dtype=float)
    if len(a) < 2:
        return f"{a.mean():+.3f}"
    h = stats.t.ppf(0.975, len(a) - 1) * a.std(ddof=1) / np.sqrt(len(a))
    return f"{a.mean():+.3f} ± {h:.3f}"


def main(specs: list[str]) -> None:
    runs = [(s, load(*s.rsplit(":", 1))) for s in specs]
    common = sorted(set.intersection(*(set(r) for _, r in runs)))
    base = runs[0][1]
    print(f"scenes {common[0]}-{common[-1]} ({len(common)})" if common else "no common scenes")
    print("| run | steps with grasp candidates / asked | grasps | taken out | episodes with a fall | "
          "2-D semantic mIoU | occupancy mIoU | semantic minus the first | occupancy minus the first |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, r in runs:
        eps = [r[s] for s in common]
        fun = [e["funnel"].get("grasp", {}) for e in eps]
        asked, wc = sum(f.get("asked", 0) for f in fun), sum(f.get("with_candidates", 0) for f in fun)
        m = [e["metrics"] for e in eps]
        sem = [x["semantic_miou_2d"] for x in m]
        occ = [x["occupancy_miou"] for x in m]
        dsem = [r[s]["metrics"]["semantic_miou_2d"] - base[s]["metrics"]["semantic_miou_2d"] for s in common]
        docc = [r[s]["metrics"]["occupancy_miou"] - base[s]["metrics"]["occupancy_miou"] for s in common]
        share = f" ({wc / asked:.0%})" if asked else ""
        print(f"| {name} | {wc} / {asked}{share} | {sum(x.get('grasps', 0) for x in m)} | "
              f"{sum(x.get('removed', 0) for x in m)} | {sum(1 for x in m if x.get('falls', 0) > 0)} | "
              f"{np.mean(sem):.3f} | {np.mean(occ):.3f} | {paired(dsem)} | {paired(docc)} |")


if __name__ == "__main__":
    main(sys.argv[1:])
