"""Where cnabu-map loses 2-D semantic mIoU in closed loop: the views, or the model?

    L=docs/lab/2026-12-04-results-under-earlier-defaults/configs   # from the repository root
    .venv/bin/python $L/map_view_replay.py --suite tune10 --scenes 0-4 [--weights W]

For each scene, two view-only episodes of 40 steps choose their views by IG on their own belief: one
with the analytic update, one with cnabu-map. Each of the two view sequences is then replayed open
loop through three models: the analytic update, cnabu-map, and a hybrid that takes the analytic
belief wherever a ray of the sequence reached the voxel and cnabu-map's everywhere else. Printed:
the paper's 2-D semantic mIoU per scene, averaged over the scenes, after 10, 20 and 40 views.
"""

from __future__ import annotations

import argparse

import numpy as np

from msmem_core.config import load_config
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import parse_range, suite_scenes
from msmem_core.run.runner import MetricTracker, build_episode, run_episode

STEPS = (10, 20, 40)


def hybrid(net: EvidentialMap, ana: EvidentialMap) -> EvidentialMap:
    """cnabu-map's belief with the analytic one wherever a ray reached the voxel."""
    reached = ((ana.eta[1:] - 1).sum(0) > 0) | ((ana.alpha + ana.beta) > 2)
    out = net.copy()
    out.alpha[reached], out.beta[reached] = ana.alpha[reached], ana.beta[reached]
    out.eta[:, reached] = ana.eta[:, reached]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--suite", default="tune10")
    ap.add_argument("--scenes", default="0-4")
    ap.add_argument("--weights", default=None, help="cnabu-map weights (default: the shipped ones)")
    args = ap.parse_args()
    pm = get_plugin_manager()
    scenes = suite_scenes(args.suite)
    # the network's own output (unlabelled_objects: keep; the default is unknown)
    params = {"unlabelled_objects": "keep", **({"weights": args.weights} if args.weights else {})}
    configs = {"analytic": {"observation_model": {"name": "analytic-observation"}},
               "cnabu-map": {"observation_model": {"name": "cnabu-map", "params": params}}}
    scores: dict[tuple[str, str], list[list[float]]] = {}
    for i in parse_range(args.scenes, len(scenes)):
        episodes, views = {}, {}
        for name, over in configs.items():
            ep = build_episode(load_config("view-only", None, {**over, "steps": 40, "threads": 1}), pm, scene=scenes[i])
            run_episode(ep)
            episodes[name], views[name] = ep, [ep.start_view] + [r["action"]["view"] for r in ep.records]
        ana_ep, net_ep = episodes["analytic"], episodes["cnabu-map"]
        for seq_name, seq in views.items():
            net_ep.sim.reset(net_ep.scene)
            truth = MetricTracker(net_ep)
            bn, ba = EvidentialMap.empty(net_ep.ig.grid), EvidentialMap.empty(net_ep.ig.grid)
            rows: dict[str, list[float]] = {"analytic": [], "cnabu-map": [], "hybrid": []}
            for t, v in enumerate(seq):
                obs = net_ep.sim.observe(net_ep.viewpoints[v])
                bn, ba = net_ep.observe_model.update(bn, obs), ana_ep.observe_model.update(ba, obs)
                if t in STEPS:
                    for model, b in (("analytic", ba), ("cnabu-map", bn), ("hybrid", hybrid(bn, ba))):
                        rows[model].append(truth(b)["semantic_miou_2d"])
            for model, r in rows.items():
                scores.setdefault((seq_name, model), []).append(r)
            print(f"scene {i}, views chosen with {seq_name}: "
                  + ", ".join(f"{m} {' / '.join(f'{x:.3f}' for x in r)}" for m, r in rows.items()), flush=True)
    print(f"\n2-D semantic mIoU (paper, per scene), mean over {len(next(iter(scores.values())))} scenes, "
          f"after {' / '.join(map(str, STEPS))} views:")
    print("| views chosen with | replayed through | " + " | ".join(f"after {s}" for s in STEPS) + " |")
    print("|---|---|" + "---|" * len(STEPS))
    for (seq_name, model), r in scores.items():
        print(f"| {seq_name} | {model} | " + " | ".join(f"{x:.3f}" for x in np.mean(r, axis=0)) + " |")


if __name__ == "__main__":
    main()
