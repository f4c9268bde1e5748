"""Classes at IoU 0 in the final top-view class maps of run folders, and what kind of miss each is.

    L=docs/lab/2026-12-05-decision-oracle      # from the repository root
    for i in $(seq -w 0 24); do                # the runs: hard25 view-only episodes with their beliefs
      .venv/bin/msmem run -m view-only --scene hard25-$i.json --steps 40 --out finals/view-only-$i -q --no-report
    done                                       # (hard25-NN.json: suite_scenes("hard25")[NN].to_json)
    .venv/bin/python $L/zero_classes.py 'finals/view-only-*' > $L/runs/zero-classes-hard25-view-only.txt

Per run folder: the final belief's top-view class map (the paper's 2-D semantics: the class of each
interior column's highest believed-occupied voxel) against the ground truth's, the per-scene 2-D
semantic mIoU, and each class present in either map whose IoU is 0, as

- ``missed``: the belief names it in no column (a hidden object never found);
- ``stray``: the ground truth has it nowhere and the belief names it in at most 10 columns;
- ``hallucinated``: the ground truth has it nowhere, the belief in more than 10 columns;
- ``misplaced``: both have it, in different columns.

The last line sums them over the folders, with each kind's share of the per-scene mean (a class at 0
costs 1 / the number of classes present): what the scenes would gain if that kind were mapped right.
"""

from __future__ import annotations

import glob
import os
import sys
from collections import Counter

import numpy as np

from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import shelf_interior_mask, shelf_wall_mask
from msmem_core.run.metrics import prediction_from_belief, top_view_classes
from msmem_core.run.runfolder import load_ground_truth
from msmem_core.world.scene import CLASS_NAMES, SceneSpec


def main() -> None:
    kinds: Counter[str] = Counter()
    cost: Counter[str] = Counter()
    n = 0
    for d in sorted(p for p in glob.glob(sys.argv[1]) if os.path.isdir(p)):
        belief = EvidentialMap.load(f"{d}/belief_step39.npz")
        _, occ, cls = load_ground_truth(f"{d}/gt_final.npz")
        shelf = SceneSpec.from_json(f"{d}/scene.json").shelf
        inside = shelf_interior_mask(belief.grid, shelf)
        columns = inside.any(axis=2)
        pred_occ, pred_cls = prediction_from_belief(belief.expected_occupancy(), belief.class_probs())
        pred_occ &= ~shelf_wall_mask(belief.grid, shelf)
        top_pred = top_view_classes(np.where(inside & pred_occ, pred_cls, 0))[columns]
        top_gt = top_view_classes(np.where(inside & occ, cls, 0))[columns]
        present = [c for c in range(len(CLASS_NAMES)) if (top_pred == c).any() or (top_gt == c).any()]
        iou = {c: ((top_pred == c) & (top_gt == c)).sum() / ((top_pred == c) | (top_gt == c)).sum() for c in present}
        found = []
        for c in present:
            if iou[c] > 0:
                continue
            p, g = int((top_pred == c).sum()), int((top_gt == c).sum())
            kind = "missed" if p == 0 else ("misplaced" if g else ("stray" if p <= 10 else "hallucinated"))
            kinds[kind] += 1
            cost[kind] += 1 / len(present)
            found.append(f"{CLASS_NAMES[c]}:{kind}(belief {p}, truth {g} columns)")
        n += 1
        print(d.rstrip("/").split("/")[-1], f"{np.mean(list(iou.values())):.3f}", len(present), " ".join(found))
    print(f"{n} scenes; classes at IoU 0: {dict(kinds)}; share of the per-scene mean: "
          f"{ {k: round(v / n, 3) for k, v in cost.items()} }")


if __name__ == "__main__":
    main()
