"""What CDC counts for a grasp: tune10 scenes 0-4 after 10 views of an `ours` episode (manipulation held
off), every executable grasp's predicted change under the default learned grasp model, and how many of
the voxels CDC counts (U_diff) belong to the grasped object's own believed component.

    python docs/lab/2026-12-05-whole-object-removal/removal_probe.py
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from msmem_grasp.planning import Objects
from msmem_objectives.cdc import disturbed_voxels

from msmem_core.config import load_config
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import suite_scenes
from msmem_core.run.runner import build_episode, run_episode


def main() -> None:
    cfg = load_config("ours", None, {"threads": 2, "steps": 10, "msas": {"manipulation_window": [999, 999]}})
    for si in range(5):
        ep = build_episode(cfg, get_plugin_manager(), scene=suite_scenes("tune10")[si])
        out = Path(tempfile.mkdtemp())
        run_episode(ep, out)
        belief = EvidentialMap.load(out / "belief_final.npz")
        bound = next(b for b in ep.skills if b.name == "grasp")
        grasps = bound.skill.executable(belief, ep.scene.shelf, {}, ep.workspace.classes)  # type: ignore[attr-defined]
        if not grasps or bound.effect_model is None:
            print(f"scene {si}: no grasp")
            continue
        pred = bound.effect_model.predict(belief, grasps, ep.workspace)
        objects = Objects.of(belief, ep.workspace.interior_box)
        labels = objects.labels.reshape(-1)
        eta0 = belief.eta.reshape(belief.num_classes, -1)
        assert pred.excluded is not None
        for k, (g, d) in enumerate(zip(grasps, pred.changes, strict=True)):
            u = d.idx[disturbed_voxels(eta0[:, d.idx], d.eta, cfg.msas.tau_chi, pred.excluded_among(k))]
            own = labels[pred.excluded[k]]
            target = int(np.bincount(own[own > 0]).argmax()) if (own > 0).any() else 0
            print(f"scene {si} grasp {k} class {g.target_class}: U_diff {len(u)}, of the grasped object's own "
                  f"component {int((labels[u] == target).sum()) if target else 0}")
        ep.sim.close()


if __name__ == "__main__":
    main()
