"""Replay the analytic update's views through belief models and count the top view's errors.

    .venv/bin/python docs/lab/2026-12-05-mesh-columns/topview_errors.py --suite mesh25 --scenes 0-4 \
        --config examples/scenes/mesh25-defaults.yaml
    .venv/bin/python docs/lab/2026-12-05-mesh-columns/topview_errors.py --suite hard25 --scenes 0-4

For each scene a view-only episode with the analytic update chooses its views (40 steps); the same
views are replayed open loop through the analytic update and through ``cnabu-map`` under each
setting below (the run config's ``class_map``, if any, goes to it). Printed per model: both paper map
metrics and, over the shelf interior's columns of the top-view class map, the columns with the right
object class, a wrong object class, an object where the truth is free, and free where the truth
holds an object. The last lines are the per-scene means.
"""

from __future__ import annotations

import argparse

import numpy as np

from msmem_core.config import load_config, read_config_file
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import parse_range, suite_scenes
from msmem_core.run.metrics import prediction_from_belief, top_view_classes
from msmem_core.run.runner import MetricTracker, build_episode, run_episode

SETTINGS = {
    "keep": {"unlabelled_columns": "keep", "unreached_occupied": "keep"},
    "unknown": {"unlabelled_columns": "unknown", "unreached_occupied": "keep"},
    "keep+ray-classes-4": {"unlabelled_columns": "keep", "unreached_occupied": "keep", "ray_classes_within": 4},
}
"""cnabu-map's params per replayed model (the rest: the library defaults). ``unreached_occupied`` changes
only evidence, not the maps these scores read, so it is left at ``keep``."""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--suite", default="hard25")
    ap.add_argument("--scenes", default="0")
    ap.add_argument("--config", default=None, help="a run config whose class_map the models take")
    args = ap.parse_args()
    pm = get_plugin_manager()
    scenes = suite_scenes(args.suite)
    extra = {k: v for k, v in (read_config_file(args.config) if args.config else {}).items() if k == "class_map"}
    totals: dict[str, list[tuple[float, float]]] = {}
    for i in parse_range(args.scenes, len(scenes)):
        base = {**extra, "steps": 40, "threads": 1}
        ana = build_episode(load_config("view-only", None, {**base, "observation_model": {
            "name": "analytic-observation"}}), pm, scene=scenes[i])
        run_episode(ana)
        views = [ana.start_view] + [r["action"]["view"] for r in ana.records]
        models = {"analytic": ana}
        for name, params in SETTINGS.items():
            models[name] = build_episode(load_config("view-only", None, {**base, "observation_model": {
                "name": "cnabu-map", "params": params}}), pm, scene=scenes[i])
        sim = models["keep"]
        sim.sim.reset(sim.scene)
        truth = MetricTracker(sim)
        beliefs = {n: EvidentialMap.empty(sim.ig.grid, sim.scene.num_classes) for n in models}
        for v in views:
            obs = sim.sim.observe(sim.viewpoints[v])
            beliefs = {n: models[n].observe_model.update(b, obs) for n, b in beliefs.items()}
        inside, keep = truth.interior, truth.interior.any(axis=2)
        gt = top_view_classes(np.where(inside, truth.gt_cls, 0))[keep]
        for name, b in beliefs.items():
            m = truth(b)
            _, cls = prediction_from_belief(b.expected_occupancy(), b.class_probs())
            cls[truth.walls] = 0
            top = top_view_classes(np.where(inside, cls, 0))[keep]
            obj, truth_obj = top > 0, gt > 0
            counts = {"right class": (top == gt) & truth_obj, "wrong class": (top != gt) & truth_obj & obj,
                      "object on free": ~truth_obj & obj, "free on object": truth_obj & ~obj}
            cols = ", ".join(f"{k} {int(c.sum())}" for k, c in counts.items())
            print(f"scene {i} {name:19s} occupancy mIoU {m['occupancy_miou']:.3f}, 2-D semantic mIoU "
                  f"{m['semantic_miou_2d']:.3f}; columns: {cols}", flush=True)
            totals.setdefault(name, []).append((m["occupancy_miou"], m["semantic_miou_2d"]))
        for model in models.values():
            model.sim.close()
    for name, rows in totals.items():
        occ, sem = np.mean(rows, axis=0)
        print(f"mean over {len(rows)} scenes: {name:19s} occupancy mIoU {occ:.3f}, 2-D semantic mIoU {sem:.3f}")


if __name__ == "__main__":
    main()
