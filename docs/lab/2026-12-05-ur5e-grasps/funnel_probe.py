"""The UR5e's grasp funnel on ``hard25`` scenes, and the lift test of every grasp that reaches it.

    L=docs/lab/2026-12-05-ur5e-grasps          # from the repository root
    .venv/bin/python $L/funnel_probe.py 1,3 examples/robots/ur5e.yaml 16

Runs a grasp-only episode (``STEPS`` steps, the config file over the preset) per scene given, sums the
grasp skill's stage counts over every decision, and prints one line per grasp that reaches the lift
test: the extents of its object's class, the grasp's height, the shelf top, the gripper's and the
believed object's top, and the lift (None: refused).
"""

from __future__ import annotations

import sys
from collections import Counter
from typing import Any

import msmem_grasp.skill as grasp_skill
from msmem_grasp.planning import gripper_points, voxel_centres

from msmem_core.config import load_config, read_config_file
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import suite_scenes
from msmem_core.run.runner import build_episode, run_episode

totals: Counter[str] = Counter()
lifts: Counter[tuple[Any, ...]] = Counter()
executable, lift = grasp_skill.GraspSkill.executable, grasp_skill.GraspSkill._lift


def traced_executable(self, belief, shelf, stages=None, classes=()):  # type: ignore[no-untyped-def]
    st: dict[str, int] = {} if stages is None else stages
    out = executable(self, belief, shelf, st, classes)
    totals.update(st)
    return out


def traced_lift(self, grid, p, objects, label, region, pose, width, top, stages=None, extents=None):  # type: ignore[no-untyped-def]
    cfg, s = self.config, grid.voxel_m
    pts = gripper_points(cfg.gripper, width, s / 2, cfg.tolerance_m, cfg.hand_m) @ pose[:3, :3].T
    body, _ = self._carried(grid, p, objects, label, region)
    obj_top = float(voxel_centres(grid, body)[:, 2].max()) + s / 2 if len(body) else float(pose[2, 3])
    out = lift(self, grid, p, objects, label, region, pose, width, top, stages, extents)
    lifts[(extents, round(float(pose[2, 3]), 2), round(top, 3), round(float(pts[:, 2].max() + pose[2, 3]), 2),
           round(obj_top, 2), out)] += 1
    return out


grasp_skill.GraspSkill.executable = traced_executable  # type: ignore[method-assign]
grasp_skill.GraspSkill._lift = traced_lift  # type: ignore[method-assign]

if __name__ == "__main__":
    over = read_config_file(sys.argv[2])
    steps = int(sys.argv[3]) if len(sys.argv) > 3 else 16
    for si in (int(a) for a in sys.argv[1].split(",")):
        ep = build_episode(load_config("grasp-only", None, {**over, "steps": steps, "threads": 1}),
                           get_plugin_manager(), scene=suite_scenes("hard25")[si])
        run_episode(ep)
        ep.sim.close()
    print("stages:", dict(totals))
    print("class extents, grasp z, shelf top, gripper top, object top, lift: count")
    for k, v in sorted(lifts.items(), key=str):
        print(k, v)
