"""Each executed grasp of grasp-only episodes: its lift, where the believed object lies between the
finger pads, and how the grasp ended.

    L=docs/lab/2026-12-05-whole-object-removal      # from the repository root
    .venv/bin/python $L/grasp_probe.py 4,5,6,7,8 $L/slide.yaml

For each ``tune10`` scene given, a grasp-only episode (40 steps, the config file over the preset) runs
with the grasp skill wrapped: when a grasp becomes an action, the region of the believed object its
fingers close on is taken into the grasp's frame (x: closing, y: across the pads, z: approach) and
its reach across the pads within the fingers' 5 cm (``cover``: less and more) is kept; when it is
executed, one line is printed with the outcome (``closed``: the opening after closing, m).
"""

from __future__ import annotations

import sys
from typing import Any

import msmem_grasp.skill as grasp_skill
from msmem_grasp.planning import voxel_centres

from msmem_core.config import load_config, read_config_file
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import suite_scenes
from msmem_core.run.runner import build_episode, run_episode

FINGER_M = 0.05
"""The fingers' length along the approach (the default gripper's)."""

seen: dict[Any, dict[str, Any]] = {}
action, executable, execute = (grasp_skill.GraspSkill.action, grasp_skill.GraspSkill.executable,
                               grasp_skill.GraspSkill.execute)


def traced_executable(self, belief, shelf, stages=None, classes=()):  # type: ignore[no-untyped-def]
    self._probe_grid = belief.grid
    return executable(self, belief, shelf, stages, classes)


def traced_action(self, c, i, approach, lift_m, shelf):  # type: ignore[no-untyped-def]
    a = action(self, c, i, approach, lift_m, shelf)
    grid, pose = self._probe_grid, c.poses[i]
    region = c.objects.region(grid, int(c.label[i]), pose, c.opening[i], self.config.max_object_radius_m)
    local = (voxel_centres(grid, region) - pose[:3, 3]) @ pose[:3, :3]
    pads = local[(local[:, 2] >= -FINGER_M) & (local[:, 2] <= grid.voxel_m / 2)]
    cover = [round(float(-pads[:, 1].min()), 3), round(float(pads[:, 1].max()), 3)] if len(pads) else None
    seen[a.pose] = {"lift_m": round(lift_m, 3), "z_m": round(float(pose[2, 3]), 3), "width_m": round(a.width_m, 3),
                    "approach": [round(float(v), 2) for v in pose[:3, 2]], "affordance": round(a.affordance, 2),
                    "cover_m": cover}
    return a


def traced_execute(self, sim, act, ctx):  # type: ignore[no-untyped-def]
    out = execute(self, sim, act, ctx)
    print({**seen.get(act.pose, {}), "held": out.success, "closed_m": round(out.info["closed_opening_m"], 4)},
          flush=True)
    return out


grasp_skill.GraspSkill.executable = traced_executable  # type: ignore[method-assign]
grasp_skill.GraspSkill.action = traced_action  # type: ignore[method-assign]
grasp_skill.GraspSkill.execute = traced_execute  # type: ignore[method-assign]

if __name__ == "__main__":
    over = read_config_file(sys.argv[2]) if len(sys.argv) > 2 else {}
    for si in (int(a) for a in sys.argv[1].split(",")):
        print("scene", si, flush=True)
        ep = build_episode(load_config("grasp-only", None, {**over, "steps": 40, "threads": 1}), get_plugin_manager(),
                           scene=suite_scenes("tune10")[si])
        run_episode(ep)
        ep.sim.close()
