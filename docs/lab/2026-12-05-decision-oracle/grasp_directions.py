"""Which way the fused grasps point, what stops their approach, and which grasps the geometry allows.

    L=docs/lab/2026-12-05-decision-oracle      # from the repository root
    .venv/bin/python $L/grasp_directions.py mesh25 0,1,2,3 examples/scenes/mesh25-defaults.yaml \
        > $L/runs/grasp-directions-mesh25-0-3.txt
    .venv/bin/python $L/grasp_directions.py hard25 0,1,2,3 > $L/runs/grasp-directions-hard25-0-3.txt

Per scene, as ``oracle_funnel.py`` sets it up (the ``grasp-only`` preset, 10 evenly spaced views, one
FE-vMF prediction fused per view):

- ``belief``: the confident fused grasps (E[q] and 2/S tests) by approach direction a: ``down``
  (a_z < -0.7, from above), ``front`` (|a_z| < 0.5 and a_y > 0.5, into the shelf) and the rest;
- ``truth``: the same fusion on the ground-truth belief; of the candidates whose open gripper is free
  at the grasp, what the gripper meets on its way in (from in front of the shelf to the first
  pre-grasp pose, then along a to the grasp, ``GraspSkill._plan_approach``'s two segments): the shelf
  top, a side or back board, the target's own voxels, another
  object, or nothing;
- ``antipodal``: per object, the class's antipodal grasps at its pose that clear the boards and the
  other objects at the grasp (``antipodal.grasps_in_scene``, the FE-vMF training labels): how many
  objects have one from the front (as above) and one from above.

The ground truth is used only here, as an oracle.
"""

from __future__ import annotations

import sys
from collections import Counter

import numpy as np
from msmem_grasp.antipodal import grasps_in_scene
from msmem_grasp.fpp import virtual_front_views
from msmem_grasp.planning import gripper_points, path_offsets, sweep_hits, swept_indices, voxel_centres
from oracle_funnel import truth_belief

from msmem_core.config import load_config, read_config_file
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import shelf_wall_mask
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import suite_scenes
from msmem_core.run.ceiling import evenly_spaced
from msmem_core.run.runner import MetricTracker, build_episode


def direction_counts(a: np.ndarray) -> dict[str, int]:
    down = a[:, 2] < -0.7
    front = (np.abs(a[:, 2]) < 0.5) & (a[:, 1] > 0.5)
    return {"down": int(down.sum()), "front": int(front.sum()), "other": int((~down & ~front).sum())}


def fuse(ep, skill, beliefs: list[EvidentialMap], views: list[int]) -> None:
    front = virtual_front_views(skill.config.viewpoints)
    skill.buffer.clear()
    for k, b in enumerate(beliefs):
        cams = np.concatenate([ep.viewpoints[views[: k + 1]].reshape(-1, 4, 4), front])
        skill.buffer.update(skill.predict(b, ep.scene.shelf, cams, 7 + k), b)


def approach_blocks(ep, skill, truth: EvidentialMap) -> Counter[str]:
    """What the free-at-grasp candidates on the ground truth meet on the way to the first pre-grasp pose."""
    grid, cfg = truth.grid, skill.config
    c = skill.candidates(truth, ep.scene.shelf, {})
    out: Counter[str] = Counter()
    if c is None:
        return out
    s, n = grid.voxel_m, len(c.grasps)
    pts = [gripper_points(cfg.gripper, float(c.opening[i]), s / 2, cfg.tolerance_m, cfg.hand_m) for i in range(n)]
    local = np.stack([pts[i] @ c.poses[i, :3, :3].T for i in range(n)])
    at = sweep_hits(grid, c.blocked, c.objects.labels, local, c.poses[:, :3, 3], np.arange(n + 1), np.arange(n),
                    c.label, c.poses, c.opening, cfg.max_object_radius_m)
    boards = shelf_wall_mask(grid, ep.scene.shelf).reshape(-1)
    labels = c.objects.labels.reshape(-1)
    top = float(ep.scene.shelf.interior_upper[2])
    for i in np.flatnonzero((c.label > 0) & ~at):
        pose = c.poses[i]
        grasp = pose[:3, 3]
        pre = grasp - cfg.approach_distances_m[0] * pose[:3, 2]
        outside = pre.copy()
        outside[1] = min(cfg.outside_y_m, pre[1])
        swept = np.union1d(swept_indices(grid, pose[:3, :3], pts[i], path_offsets(np.stack([outside, pre]), s / 2)),
                           swept_indices(grid, pose[:3, :3], pts[i], path_offsets(np.stack([pre, grasp]), s / 2)))
        hit = swept[c.blocked[swept]]
        kinds = []
        if boards[hit].any():
            z = voxel_centres(grid, hit[boards[hit]])[:, 2]
            kinds.append("shelf top" if (z >= top).any() else "side or back board")
        if (labels[hit] == c.label[i]).any():
            kinds.append("target")
        if ((labels[hit] > 0) & (labels[hit] != c.label[i])).any():
            kinds.append("other object")
        out[" + ".join(kinds) or "nothing"] += 1
    return out


def main() -> None:
    suite, scenes = sys.argv[1], [int(s) for s in sys.argv[2].split(",")]
    over = read_config_file(sys.argv[3]) if len(sys.argv) > 3 else {}
    pm = get_plugin_manager()
    for si in scenes:
        spec = suite_scenes(suite)[si]
        ep = build_episode(load_config("grasp-only", None, {**over, "steps": 40, "threads": 1}), pm, scene=spec)
        ep.sim.reset(ep.scene)
        gt = MetricTracker(ep)
        views = evenly_spaced(len(ep.viewpoints), 10)
        belief = EvidentialMap.empty(ep.ig.grid, ep.scene.num_classes)
        beliefs = []
        for v in views:
            belief = ep.observe_model.update(belief, ep.sim.observe(ep.viewpoints[v]))
            beliefs.append(belief)
        skill = next(b.skill for b in ep.skills if b.skill.category == "manipulation")
        cfg = skill.config
        fuse(ep, skill, beliefs, views)
        h = skill.buffer.hypotheses()
        ok = (h.affordance >= cfg.min_affordance) & (h.uncertainty <= cfg.max_uncertainty)
        a, _ = h.subset(np.flatnonzero(ok)).approach()
        truth = truth_belief(ep.ig.grid, gt.gt_occ, gt.gt_cls, ep.scene.num_classes)
        fuse(ep, skill, [truth] * len(views), views)
        blocks = approach_blocks(ep, skill, truth)
        per_object = grasps_in_scene(spec, gripper=cfg.gripper)
        front = sum(bool(direction_counts(g.approach)["front"]) for g in per_object.values())
        down = sum(bool(direction_counts(g.approach)["down"]) for g in per_object.values())
        print(f"{suite} {si}: belief, confident fused grasps {int(ok.sum())}: {direction_counts(a)}")
        print(f"  truth, free at the grasp {sum(blocks.values())}, met on the way in: {dict(blocks.most_common())}")
        print(f"  antipodal, {len(per_object)} objects: {front} with a grasp from the front, {down} from above",
              flush=True)
        ep.sim.close()


if __name__ == "__main__":
    main()
