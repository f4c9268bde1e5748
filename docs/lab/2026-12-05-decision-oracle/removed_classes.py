"""Do the classes of objects a grasp took out survive in the final map?

    L=docs/lab/2026-12-05-decision-oracle      # from the repository root
    .venv/bin/python $L/removed_classes.py 'finals10/grasp-only-*' 'finals10/ours-*'

Per run folder (``msmem run`` with its beliefs): the classes of the objects that grasps took out
(``info.held`` of the successful grasp steps, looked up in ``scene.json``), and, in the final belief's
top-view class map (the paper's 2-D semantics, as ``zero_classes.py``), the columns that still name a
removed class the scene no longer holds. Such a class scores IoU 0 and costs 1 / (classes present) of
the per-scene mean; the last line sums what it costs over the folders, and what the per-scene mean
would be with those columns given the ground truth's class (the gain if the removed class's evidence
were gone where it was).
"""

from __future__ import annotations

import glob
import json
import os
import sys

import numpy as np

from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import shelf_interior_mask, shelf_wall_mask
from msmem_core.run.metrics import prediction_from_belief, top_view_classes
from msmem_core.run.runfolder import load_ground_truth
from msmem_core.world.scene import CLASS_NAMES, SceneSpec


def miou(pred: np.ndarray, gt: np.ndarray) -> float:
    present = [c for c in range(len(CLASS_NAMES)) if (pred == c).any() or (gt == c).any()]
    return float(np.mean([((pred == c) & (gt == c)).sum() / ((pred == c) | (gt == c)).sum() for c in present]))


def main() -> None:
    folders = sorted(d for pattern in sys.argv[1:] for d in glob.glob(pattern) if os.path.isdir(d))
    before, after, events, grasped = [], [], 0, 0
    for d in folders:
        scene = SceneSpec.from_json(f"{d}/scene.json")
        cls_of = {o.id: CLASS_NAMES.index(o.object_class.name) for o in scene.objects}
        removed = [cls_of[r["info"]["held"]] for r in map(json.loads, open(f"{d}/steps.jsonl"))
                   if r["skill"] == "grasp" and r["success"] and r["info"].get("held") is not None]
        grasped += len(removed)
        belief = EvidentialMap.load(f"{d}/belief_step39.npz")
        _, occ, cls = load_ground_truth(f"{d}/gt_final.npz")
        inside = shelf_interior_mask(belief.grid, scene.shelf)
        columns = inside.any(axis=2)
        pred_occ, pred_cls = prediction_from_belief(belief.expected_occupancy(), belief.class_probs())
        pred_occ &= ~shelf_wall_mask(belief.grid, scene.shelf)
        top_pred = top_view_classes(np.where(inside & pred_occ, pred_cls, 0))[columns]
        top_gt = top_view_classes(np.where(inside & occ, cls, 0))[columns]
        stray = [c for c in sorted(set(removed)) if (top_pred == c).any() and not (top_gt == c).any()]
        fixed = top_pred.copy()
        for c in stray:
            fixed[top_pred == c] = top_gt[top_pred == c]
        events += len(stray)
        before.append(miou(top_pred, top_gt))
        after.append(miou(fixed, top_gt))
        names = ", ".join(f"{CLASS_NAMES[c]} ({int((top_pred == c).sum())} columns)" for c in stray)
        print(f"{os.path.basename(d)}: took out {[CLASS_NAMES[c] for c in removed]}; "
              f"2-D semantic mIoU {before[-1]:.3f}" + (f", {after[-1]:.3f} without {names}" if stray else ""))
    print(f"{len(folders)} runs, {grasped} objects taken out; a removed class left in the final map: {events} times; "
          f"per-scene mean 2-D semantic mIoU {np.mean(before):.3f}, {np.mean(after):.3f} with those columns right")


if __name__ == "__main__":
    main()
