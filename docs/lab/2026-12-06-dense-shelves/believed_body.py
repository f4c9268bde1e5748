"""At a grasp step of an analytic-model grasp-only episode on a dense shelf: per 1 cm slice along x,
the ground-truth voxels of the given objects, how many of them the belief holds occupied (p > 0.5),
and how many no ray has reached.

    .venv/bin/python docs/lab/2026-12-06-dense-shelves/believed_body.py SCENE STEP IDS

SCENE: 00-05 (``scenes/scene_SCENE.json``); STEP: the episode step of the grasp; IDS: object ids,
comma-separated. The episode runs as ``msmem run -m grasp-only -c examples/scenes/analytic-effects.yaml``
does, up to and including that step (the grasp is then executed as usual).
"""

import sys
from pathlib import Path

import numpy as np
from msmem_grasp.skill import GraspSkill

from msmem_core.config import load_config
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.runner import build_episode, run_episode
from msmem_core.world.voxelize import voxelize_instances

HERE = Path(__file__).resolve().parent


def main(scene: str, step: int, ids: list[int]) -> None:
    cfg = load_config("grasp-only", "examples/scenes/analytic-effects.yaml",
                      {"scene": {"file": str(HERE / "scenes" / f"scene_{scene}.json")}, "steps": step + 1})
    ep = build_episode(cfg, get_plugin_manager())
    execute = GraspSkill.execute

    def report(self, sim, action, ctx):  # type: ignore[no-untyped-def]
        if ctx.step == step:
            grid = ctx.belief.grid
            p = ctx.belief.expected_occupancy()
            never = ctx.belief.never_seen(0.5)
            poses = sim.object_poses()
            inst = voxelize_instances([o for o in ep.scene.objects if o.id in poses], grid, poses=poses)
            for i in ids:
                real = inst == i
                print(f"object {i}: {real.sum()} voxels; believed occupied {(real & (p > 0.5)).sum()}, "
                      f"never seen {(real & never).sum()}")
                for x in np.flatnonzero(real.any(axis=(1, 2))):
                    col = real[x]
                    print(f"  x slice {x} ({grid.origin[0] + (x + 0.5) * grid.voxel_m:+.3f} m): real {col.sum():4d}, "
                          f"believed occupied {(col & (p[x] > 0.5)).sum():4d}, never seen {(col & never[x]).sum():4d}")
            print("grasp at", np.round(np.asarray(action.pose)[:3, 3], 3).tolist(), "contact",
                  np.round(action.contact_m, 3).tolist())
        return execute(self, sim, action, ctx)

    GraspSkill.execute = report  # type: ignore[method-assign]
    run_episode(ep)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), [int(v) for v in sys.argv[3].split(",")])
