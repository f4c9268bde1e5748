"""Class by class, the pooled 2-D semantic IoU of one method in two bench folders (the top-view counts
of every episode summed, as the results page pools them), with each class's summed union in columns.

    python classes.py FOLDER_A FOLDER_B METHOD
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from msmem_core.world.scene import CLASS_NAMES


def pooled(folder: str, method: str) -> tuple[np.ndarray, np.ndarray]:
    inter, union = np.zeros(len(CLASS_NAMES)), np.zeros(len(CLASS_NAMES))
    for f in sorted(Path(folder, "episodes").glob(f"{method}__scene*.json")):
        counts = json.loads(f.read_text())["paper_counts"]
        inter += np.asarray(counts["semantic_2d_intersection"])
        union += np.asarray(counts["semantic_2d_union"])
    return inter, union


def main(fa: str, fb: str, method: str) -> None:
    (ia, ua), (ib, ub) = pooled(fa, method), pooled(fb, method)
    print("| class | IoU A | IoU B | union A (columns) | union B |")
    print("|---|---|---|---|---|")
    for c, name in enumerate(CLASS_NAMES):
        a = f"{ia[c] / ua[c]:.2f}" if ua[c] else "-"
        b = f"{ib[c] / ub[c]:.2f}" if ub[c] else "-"
        print(f"| {name} | {a} | {b} | {int(ua[c])} | {int(ub[c])} |")
    for tag, i, u in (("A", ia, ua), ("B", ib, ub)):
        print(f"pooled 2-D semantic mIoU {tag}: {np.mean(i[u > 0] / u[u > 0]):.3f} over {int((u > 0).sum())} classes")


if __name__ == "__main__":
    main(*sys.argv[1:4])
