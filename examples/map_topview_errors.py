"""Where cnabu-map's top view goes wrong: the analytic update's 40 views replayed through both models.

    .venv/bin/python examples/map_topview_errors.py --scenes 0,1 [--weights W] [--suite tune10]

For each scene, a view-only episode with the analytic update chooses 40 views; they are replayed
open loop through the analytic update and cnabu-map. Printed per model, over the shelf interior's
columns of the paper's top-view class map: columns with the right object class, a wrong object
class, an object where the truth is free, free where the truth holds an object, and the classes
predicted that are not in the scene (each is a class with IoU 0 in the mean) with their columns.
Last, the 2-D semantic mIoU over the classes in the scene only (background included): the same
mean without the absent classes' zeros.
"""

from __future__ import annotations

import argparse

import numpy as np

from msmem_core.config import load_config
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import parse_range, suite_scenes
from msmem_core.run.metrics import class_iou_counts, prediction_from_belief, top_view_classes
from msmem_core.run.runner import MetricTracker, build_episode, run_episode


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--suite", default="tune10")
    ap.add_argument("--scenes", default="0")
    ap.add_argument("--weights", default=None, help="cnabu-map weights (default: the shipped ones)")
    args = ap.parse_args()
    pm = get_plugin_manager()
    scenes = suite_scenes(args.suite)
    net_cfg = {"observation_model": {"name": "cnabu-map", "params": {"weights": args.weights} if args.weights else {}}}
    for i in parse_range(args.scenes, len(scenes)):
        ana = build_episode(load_config("view-only", None, {"steps": 40, "threads": 1}), pm, scene=scenes[i])
        net = build_episode(load_config("view-only", None, {**net_cfg, "steps": 40, "threads": 1}), pm, scene=scenes[i])
        run_episode(ana)
        views = [ana.start_view] + [r["action"]["view"] for r in ana.records]
        net.sim.reset(net.scene)
        truth = MetricTracker(net)
        bn, ba = EvidentialMap.empty(net.ig.grid), EvidentialMap.empty(net.ig.grid)
        for v in views:
            obs = net.sim.observe(net.viewpoints[v])
            bn, ba = net.observe_model.update(bn, obs), ana.observe_model.update(ba, obs)
        inside, keep = truth.interior, truth.interior.any(axis=2)
        gt = top_view_classes(np.where(inside, truth.gt_cls, 0))[keep]
        for name, b in (("analytic", ba), ("cnabu-map", bn)):
            m = truth(b)
            _, cls = prediction_from_belief(b.expected_occupancy(), b.class_probs())
            cls[truth.walls] = 0
            top = top_view_classes(np.where(inside, cls, 0))[keep]
            obj, truth_obj = top > 0, gt > 0
            counts = {"right class": (top == gt) & truth_obj, "wrong class": (top != gt) & truth_obj & obj,
                      "object on free": ~truth_obj & obj, "free on object": truth_obj & ~obj}
            inter, union = class_iou_counts(top, gt, b.num_classes)
            present = np.bincount(gt, minlength=b.num_classes) > 0
            absent = np.flatnonzero((union > 0) & ~present)
            print(f"scene {i} {name:10s} 2-D semantic mIoU {m['semantic_miou_2d']:.3f}: "
                  + ", ".join(f"{k} {int(v.sum())}" for k, v in counts.items())
                  + f", classes not in the scene {len(absent)} (columns: {union[absent].tolist()}), "
                  f"mIoU over the scene's classes {np.mean(inter[present] / union[present]):.3f}", flush=True)


if __name__ == "__main__":
    main()
