"""What the belief holds around a point at given steps of a ``hard25`` episode (one thread, as the
bench runs it), against the ground truth: for a grasp that closed on nothing, whether the object the
belief still held there was a ghost, and how much evidence it had.

    .venv/bin/python docs/lab/2026-12-06-failed-grasps/ghost.py METHOD SCENE X,Y,Z OBJECT_ID STEP...

The episode runs as ``msmem run -m METHOD -c configs/one-thread.yaml`` does, up to the last STEP. At
each STEP, before the decision, it prints for the voxels within 2 cm of the point (X, Y, Z), metres:
how many the ground truth occupies, how many the belief holds occupied (p > 0.5), their evidence
alpha + beta (median, max) and most likely class; and how far OBJECT_ID's nearest voxel is.
"""

import sys
from pathlib import Path

import numpy as np

import msmem_core.msas as msas
from msmem_core.config import load_config
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.runner import build_episode, run_episode
from msmem_core.world.voxelize import voxelize_instances

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]


def main(method: str, scene: str, point: list[float], target: int, steps: list[int]) -> None:
    cfg = load_config(method, str(HERE / "configs" / "one-thread.yaml"),
                      {"scene": {"file": str(ROOT / "msmem_core" / "suites" / "hard25" / f"scene_{scene}.json")},
                       "steps": max(steps) + 1})
    ep = build_episode(cfg, get_plugin_manager())
    names = {o.class_id: o.class_name for o in ep.scene.objects}
    centres = ep.ig.grid.centers().reshape(-1, 3)
    near = np.linalg.norm(centres - np.asarray(point), axis=1) <= 0.02
    decide = msas.decide

    def report(ctx, *args, **kwargs):  # type: ignore[no-untyped-def]
        if ctx.step in steps:
            b = ctx.belief
            poses = ep.sim.object_poses()
            inst = voxelize_instances([o for o in ep.scene.objects if o.id in poses], b.grid, poses=poses).ravel()
            held = near & (b.expected_occupancy().ravel() > 0.5)
            evidence = (b.alpha + b.beta).ravel()[held]
            cls = b.class_probs().reshape(b.num_classes, -1).argmax(0)[held]
            classes = {names.get(int(c), int(c)): int((cls == c).sum()) for c in np.unique(cls)}
            own = centres[inst == target]
            where = (f"{100 * np.linalg.norm(own - np.asarray(point), axis=1).min():.1f} cm away" if len(own)
                     else "not in the grid")
            print(f"step {ctx.step:2d}: within 2 cm, ground truth {(near & (inst >= 0)).sum():2d} of {near.sum()} "
                  f"voxels (object {target}: {(near & (inst == target)).sum():2d}); belief occupied {held.sum():2d}, "
                  f"alpha+beta median {np.median(evidence) if held.any() else 0:6.1f} "
                  f"max {evidence.max() if held.any() else 0:6.1f}, classes {classes}; object {target} {where}",
                  flush=True)
        return decide(ctx, *args, **kwargs)

    msas.decide = report
    run_episode(ep)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], [float(v) for v in sys.argv[3].split(",")], int(sys.argv[4]),
         [int(v) for v in sys.argv[5:]])
