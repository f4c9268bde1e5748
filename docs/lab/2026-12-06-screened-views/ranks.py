"""Per step of an episode run with the library defaults (one thread): where the view with the most
full-density IG ranks in the screening's order (every 2nd ray in u and v), and the IG the best of the
first K screened views falls short of it by, for K = 8 ... 128. One JSON line per step.

    python ranks.py SUITE SCENE METHOD > runs/ranks-SUITE-SCENE-METHOD.jsonl
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

import msmem_core.msas as msas
from msmem_core.config import load_config
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.runner import build_episode, run_episode

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[2]
KS = (8, 16, 32, 64, 128)


def main(suite: str, scene: str, method: str) -> None:
    cfg = load_config(method, str(HERE / "configs" / "one-thread.yaml"),
                      {"scene": {"file": str(ROOT / "msmem_core" / "suites" / suite / f"scene_{scene}.json")},
                       "steps": 40})
    ep = build_episode(cfg, get_plugin_manager())
    decide = msas.decide

    def hook(ctx, *args, **kwargs):  # type: ignore[no-untyped-def]
        ig, field = ctx.ig, ctx.field
        full, coarse = ig.view_ig(field), ig.sweep(field, ray_step=2)
        cand = np.array([v for v in range(ig.num_views) if v not in ctx.visited])
        best = cand[np.argmax(full[cand])]
        order = cand[np.argsort(-coarse[cand], kind="stable")]
        short = {k: float((full[best] - full[order[:k]].max()) / full[best]) for k in KS}
        print(json.dumps({"step": ctx.step, "rank": int(np.flatnonzero(order == best)[0]), "short": short,
                          "manipulation_allowed": ctx.manipulation_allowed}), flush=True)
        return decide(ctx, *args, **kwargs)

    msas.decide = hook
    run_episode(ep)


if __name__ == "__main__":
    main(*sys.argv[1:4])
