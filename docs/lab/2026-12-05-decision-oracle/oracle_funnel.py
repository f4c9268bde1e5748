"""The grasp funnel on the belief against the same funnel on the ground truth, at a scene's start.

    L=docs/lab/2026-12-05-decision-oracle      # from the repository root
    .venv/bin/python $L/oracle_funnel.py hard25 0,1,2,3,4,5,6,7,8,9 10 > $L/runs/oracle-funnel-hard25-0-9.jsonl

Per scene: N evenly spaced views are integrated by the default observation model. The grasp skill of
the ``grasp-only`` preset (library defaults) then fuses one FE-vMF prediction per view prefix into
its buffer, as an episode's first N steps would (with the virtual front cameras), once on that belief
and once on a *ground-truth belief* (every voxel certain: evidence 200 on the true occupancy and
class). ``GraspSkill.executable`` runs on each; one JSON line per scene gives the stage counts, the
executable grasps and their target classes. The ground truth is used only here, as an oracle: it
tells whether the belief or the scene's geometry removes the candidates.
"""

from __future__ import annotations

import json
import sys

import numpy as np
from msmem_grasp.fpp import virtual_front_views

from msmem_core.config import load_config, read_config_file
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import suite_scenes
from msmem_core.run.ceiling import evenly_spaced
from msmem_core.run.runner import MetricTracker, build_episode
from msmem_core.world.grid import GridSpec

EVIDENCE = 200.0


def truth_belief(grid: GridSpec, occ: np.ndarray, cls: np.ndarray, num_classes: int) -> EvidentialMap:
    """Every voxel certain: occupancy and class evidence ``EVIDENCE`` on the ground truth."""
    alpha = (1 + EVIDENCE * occ).astype(np.float32)
    beta = (1 + EVIDENCE * ~occ).astype(np.float32)
    eta = np.ones((num_classes, *occ.shape), np.float32)
    np.put_along_axis(eta, np.where(occ, cls, 0).astype(np.int64)[None], 1 + EVIDENCE, axis=0)
    return EvidentialMap(grid, alpha, beta, eta)


def main() -> None:
    suite, scenes, num_views = sys.argv[1], [int(s) for s in sys.argv[2].split(",")], int(sys.argv[3])
    over = read_config_file(sys.argv[4]) if len(sys.argv) > 4 else {}
    pm = get_plugin_manager()
    for si in scenes:
        ep = build_episode(load_config("grasp-only", None, {**over, "steps": 40, "threads": 1}), pm,
                           scene=suite_scenes(suite)[si])
        ep.sim.reset(ep.scene)
        gt = MetricTracker(ep)
        views = evenly_spaced(len(ep.viewpoints), num_views)
        belief = EvidentialMap.empty(ep.ig.grid, ep.scene.num_classes)
        beliefs = []
        for v in views:
            belief = ep.observe_model.update(belief, ep.sim.observe(ep.viewpoints[v]))
            beliefs.append(belief)
        truth = truth_belief(ep.ig.grid, gt.gt_occ, gt.gt_cls, ep.scene.num_classes)
        skill = next(b.skill for b in ep.skills if b.skill.category == "manipulation")
        front = virtual_front_views(skill.config.viewpoints)
        row: dict[str, object] = {"scene": si}
        for name in ("belief", "truth"):
            skill.buffer.clear()
            for k in range(len(views)):
                cams = np.concatenate([ep.viewpoints[views[: k + 1]].reshape(-1, 4, 4), front])
                b = beliefs[k] if name == "belief" else truth
                skill.buffer.update(skill.predict(b, ep.scene.shelf, cams, 7 + k), b)
            stages: dict[str, int] = {}
            b = beliefs[-1] if name == "belief" else truth
            actions = skill.executable(b, ep.scene.shelf, stages, ep.workspace.classes)
            row[name] = {"stages": stages, "executable": len(actions),
                         "target_classes": sorted({a.target_class for a in actions})}
        print(json.dumps(row), flush=True)
        ep.sim.close()


if __name__ == "__main__":
    main()
