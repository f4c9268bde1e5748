"""Classes that score IoU 0 in the 2-D semantic mIoU with a handful of columns, and where they come from.

    L=docs/lab/2026-12-05-stray-classes       # from the repository root
    .venv/bin/python $L/stray_columns.py hard25 3,6,8,10,13,21,24 view-only /tmp/stray

For each scene of the suite: a 40-step episode of the method (library defaults) is run into
OUT/scene_NN (skipped if its final belief is there), then the final belief is decoded as the metrics
do (``prediction_from_belief``: the most probable object class, the lowest index on a tie) and the
classes with intersection 0 and union of at most 10 top-view columns are listed. For each of their
predicted top voxels: the object-class evidence (``eta``) of the two strongest classes, and whether
they tie. The 2-D semantic mIoU is then recomputed with ties broken towards the class most common
among the voxel's 26 neighbours (a counterfactual decoding, not the library's).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from msmem_core.config import load_config
from msmem_core.map.ig import shelf_interior_mask
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import suite_scenes
from msmem_core.run.metrics import paper_counts, paper_metrics_from_counts, prediction_from_belief, top_view_classes
from msmem_core.run.runner import build_episode, run_episode
from msmem_core.world.grid import GridSpec

MAX_UNION = 10


def neighbour_tie_break(cls: np.ndarray, probs: np.ndarray, occ: np.ndarray) -> tuple[np.ndarray, int]:
    """``cls`` with every occupied voxel whose two most probable object classes tie given the tied class
    most common among its 26 neighbours' classes (unchanged if none of them holds one); and how many
    voxels changed."""
    obj = probs[1:]
    top2 = np.sort(obj, axis=0)[-2:]
    tied = occ & np.isclose(top2[1], top2[0], rtol=1e-6, atol=0.0)
    out = cls.copy()
    changed = 0
    pad = np.pad(cls, 1)
    for x, y, z in np.argwhere(tied):
        cands = np.flatnonzero(np.isclose(obj[:, x, y, z], top2[1, x, y, z], rtol=1e-6, atol=0.0)) + 1
        hood = pad[x:x + 3, y:y + 3, z:z + 3].reshape(-1)
        counts = [(int((hood == c).sum()) - int(cls[x, y, z] == c), c) for c in cands]
        best = max(counts)
        if best[0] > 0 and best[1] != cls[x, y, z]:
            out[x, y, z] = best[1]
            changed += 1
    return out, changed


def main(suite: str, scenes: str, method: str, out: str) -> None:
    pm = get_plugin_manager()
    base, fixed = [], []
    for si in (int(s) for s in scenes.split(",")):
        scene = suite_scenes(suite)[si]
        folder = Path(out) / f"scene_{si:02d}"
        if not (folder / "belief_final.npz").exists():
            ep = build_episode(load_config(method, None, {"steps": 40, "threads": 1}), pm, scene=scene)
            run_episode(ep, folder)
            ep.sim.close()
        b, g = np.load(folder / "belief_final.npz"), np.load(folder / "gt_final.npz")
        grid = GridSpec.model_validate_json(str(b["grid"]))
        from msmem_core.world.scene import SceneSpec

        spec = SceneSpec.model_validate_json((folder / "scene.json").read_text())
        inside = shelf_interior_mask(grid, spec.shelf)
        a, be, eta = (b[k].astype(np.float64) for k in ("alpha", "beta", "eta"))
        p = a / (a + be)
        probs = eta / eta.sum(0)
        occ, cls = prediction_from_belief(p, probs)
        gt_occ, gt_cls = g["occupancy"], g["classes"]
        counts = paper_counts(p, probs, cls, gt_occ, gt_cls, inside)
        inter, union = np.array(counts["semantic_2d_intersection"]), np.array(counts["semantic_2d_union"])
        top = top_view_classes(np.where(inside, cls, 0))
        for c in np.flatnonzero((inter == 0) & (union > 0) & (union <= MAX_UNION)):
            for x, y in np.argwhere(top == c):
                z = int(np.flatnonzero(np.where(inside[x, y], cls[x, y], 0) == c).max())
                e = eta[1:, x, y, z]
                first, second = np.argsort(e)[::-1][:2] + 1
                print(f"scene {si:02d} class {c} (union {union[c]}): column ({x}, {y}) top z {z}: eta[{first}] "
                      f"{eta[first, x, y, z]:.1f}, eta[{second}] {eta[second, x, y, z]:.1f}"
                      + (" (tie)" if np.isclose(eta[first, x, y, z], eta[second, x, y, z]) else ""))
        fixed_cls, changed = neighbour_tie_break(cls, probs, occ)
        after = paper_counts(p, probs, fixed_cls, gt_occ, gt_cls, inside)
        m0 = paper_metrics_from_counts(counts)["semantic_miou_2d"]
        m1 = paper_metrics_from_counts(after)["semantic_miou_2d"]
        base.append(m0)
        fixed.append(m1)
        print(f"scene {si:02d}: 2-D semantic mIoU {m0:.3f}; ties broken by the neighbours {m1:.3f} "
              f"({changed} voxels changed)", flush=True)
    print(f"mean over {len(base)} scenes: {np.mean(base):.3f} -> {np.mean(fixed):.3f}")


if __name__ == "__main__":
    main(*sys.argv[1:5])
