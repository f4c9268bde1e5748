"""Diagnose the grasps of one episode against the simulator's ground truth.

    .venv/bin/python examples/diagnose_grasps.py METHOD SCENE.json STEPS [CONFIG.yaml]
    .venv/bin/python examples/diagnose_grasps.py no-cdc msmem_core/suites/tune10/scene_00.json 11

A tracer on the episode (``msmem_core.util.trace``): before each grasp the episode executes (the
``execute`` span of a grasp skill begins), it prints the planned grasp (E[q], 2/S, contact, approach
a, closing axis b), which ground-truth object lies between the contacts, how many voxels of each
object the open gripper covers at the grasp and along the approach, then replays approach, grasp
and close from a simulator snapshot, prints which objects moved in each phase and restores the
snapshot; MSAS then executes the grasp as usual, and when the span ends the outcome is printed.
Ground truth is only read for printing.
"""

import json
import sys
from typing import Any

import numpy as np
from msmem_grasp.planning import gripper_points, path_offsets, swept_indices
from msmem_grasp.skill import GraspAction, GraspSkill

from msmem_core.config import load_config
from msmem_core.plugins.manager import get_plugin_manager
from msmem_core.run.runner import Episode, build_episode, run_episode
from msmem_core.util.trace import Span, Tracer
from msmem_core.world.voxelize import voxelize_instances


class GraspDiagnosis(Tracer):
    def __init__(self, ep: Episode) -> None:
        self.ep = ep

    @staticmethod
    def _grasp(span: Span) -> tuple[GraspSkill, GraspAction] | None:
        if span.stage != "execute":
            return None
        decision = span.info["decision"]
        skill, action = decision.skill.skill, decision.action
        return (skill, action) if isinstance(skill, GraspSkill) and isinstance(action, GraspAction) else None

    def begin(self, span: Span) -> None:
        grasp = self._grasp(span)
        if grasp is None:
            return
        skill, action = grasp
        sim, ctx = span.info["sim"], span.info["ctx"]
        grid = ctx.grid
        s = grid.voxel_m
        poses = sim.object_poses()
        inst = voxelize_instances([o for o in self.ep.scene.objects if o.id in poses], grid, poses=poses).ravel()
        m = action.matrix
        b, c = m[:3, 0], np.array(action.contact_m)

        def gt_at(p: np.ndarray) -> int | None:
            ijk = grid.index_of(np.asarray(p)[None])
            if not grid.contains_index(ijk)[0]:
                return None
            i, j, k = ijk[0]
            return int(inst[(i * grid.shape[1] + j) * grid.shape[2] + k])

        def covered(path: np.ndarray) -> dict[int, int]:
            body = gripper_points(ctx.gripper, action.opening_m, s / 2)
            voxels = swept_indices(grid, m[:3, :3], body, path_offsets(path, s / 2))
            ids, n = np.unique(inst[voxels], return_counts=True)
            return dict(zip(ids.tolist(), n.tolist(), strict=True))

        print(json.dumps({
            "step": ctx.step, "last_manipulation": ctx.last_manipulation, "visited": sorted(ctx.visited),
            "affordance": round(action.affordance, 3), "uncertainty": round(action.uncertainty, 3),
            "width_m": round(action.width_m, 3), "contact": c.round(3).tolist(), "a": m[:3, 2].round(2).tolist(),
            "b": b.round(2).tolist(),
            "gt_between_contacts": [gt_at(c + t * action.width_m * b) for t in (0.1, 0.5, 0.9)],
            "gt_under_gripper_at_grasp": covered(m[:3, 3][None]),
            "gt_under_gripper_on_approach": covered(np.array([*action.approach_m, m[:3, 3]])),
        }))
        token = sim.snapshot()
        before = sim.object_poses()

        def phase(tag: str) -> None:
            now = sim.object_poses()
            moved = {i: round(float(np.linalg.norm(now[i][:3, 3] - before[i][:3, 3])), 3) for i in before if i in now}
            print(f"  {tag}: moved > 3 mm {({i: d for i, d in moved.items() if d > 0.003})}, "
                  f"gripper at {sim.gripper_pose()[:3, 3].round(3).tolist()}")

        for k, wp in enumerate(action.approach_m):
            sim.move_gripper([action.at(wp)], opening_m=action.opening_m, speed_mps=skill.config.travel_speed_mps)
            phase(f"approach {k}")
        sim.move_gripper([m], opening_m=action.opening_m, speed_mps=skill.config.approach_speed_mps)
        phase("at the grasp")
        closed = sim.set_gripper(0.0)
        phase(f"closed to {closed:.4f} m")
        sim.restore(token)

    def end(self, span: Span) -> None:
        if self._grasp(span) is None or span.result is None:
            return
        out: Any = span.result
        info = {k: out.info.get(k) for k in ("held", "touching_after_close", "closed_opening_m", "moved")}
        print("  ->", "success" if out.success else "FAIL", info, "fell or left:", out.fell_or_left, flush=True)


def main(method: str, scene: str, steps: int, config: str | None = None) -> None:
    cfg = load_config(method=method, config_file=config, overrides={"scene": {"file": scene}, "steps": steps})
    ep = build_episode(cfg, get_plugin_manager())
    final = run_episode(ep, None, tracer=GraspDiagnosis(ep))
    print({k: round(v, 3) for k, v in final.items() if isinstance(v, float)}, final["actions"])


if __name__ == "__main__":
    if len(sys.argv) < 4:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4] if len(sys.argv) > 4 else None)
