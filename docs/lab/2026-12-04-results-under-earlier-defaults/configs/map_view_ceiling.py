"""How far views alone can take a map: the analytic update after every one of the 300 viewpoints.

    L=docs/lab/2026-12-04-results-under-earlier-defaults/configs   # from the repository root
    .venv/bin/python $L/map_view_ceiling.py --suite tune10 --scenes 0-4 [--label-noise 0.05]

For each scene, the analytic update integrates all viewpoints of the run's viewpoint set (300 by
default) in their index order; printed: the paper's occupancy mIoU and 2-D semantic mIoU, and the
observable IoU, per scene and over the scenes (per-scene mean and suite-cumulative). No planner can
choose better views than all of them, so this is the most a map made of what rays reach can score.
"""

from __future__ import annotations

import argparse

import numpy as np

from msmem_core.config import load_config
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import parse_range, suite_scenes
from msmem_core.run.metrics import paper_metrics_from_counts, sum_paper_counts
from msmem_core.run.runner import MetricTracker, build_episode


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--suite", default="tune10")
    ap.add_argument("--scenes", default="0-4")
    ap.add_argument("--label-noise", type=float, default=0.05, help="the PyBullet backend's label_noise")
    args = ap.parse_args()
    pm = get_plugin_manager()
    scenes = suite_scenes(args.suite)
    over = {"threads": 1, "simulator": {"name": "pybullet", "params": {"label_noise": args.label_noise}}}
    rows, counts = [], []
    for i in parse_range(args.scenes, len(scenes)):
        ep = build_episode(load_config("view-only", None, over), pm, scene=scenes[i])
        ep.sim.reset(ep.scene)
        truth = MetricTracker(ep)
        belief = EvidentialMap.empty(ep.ig.grid)
        for pose in ep.viewpoints:
            belief = ep.observe_model.update(belief, ep.sim.observe(pose))
        m = truth(belief)
        rows.append((m["occupancy_miou"], m["semantic_miou_2d"], m["observable_iou"]))
        counts.append(truth.paper_counts)
        print(f"scene {i}: {len(ep.viewpoints)} views, occupancy mIoU {rows[-1][0]:.3f}, "
              f"2-D semantic mIoU {rows[-1][1]:.3f}, observable IoU {rows[-1][2]:.3f}", flush=True)
    mean = np.mean(rows, axis=0)
    suite = paper_metrics_from_counts(sum_paper_counts(counts))
    print(f"mean over {len(rows)} scenes: occupancy mIoU {mean[0]:.3f}, 2-D semantic mIoU {mean[1]:.3f}, "
          f"observable IoU {mean[2]:.3f}; suite-cumulative: occupancy mIoU {suite['occupancy_miou']:.3f}, "
          f"2-D semantic mIoU {suite['semantic_miou_2d']:.3f}")


if __name__ == "__main__":
    main()
