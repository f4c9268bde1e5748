"""Decisions under the library defaults against exact scoring (``ig: {screen_ray_step: 1}``: every view
and every manipulation candidate at full density over every view), on mid-episode beliefs (the start
view and N seeded random views, as ``msmem perf step`` builds them; manipulation allowed).

    python agree.py METHOD SUITE SCENES BELIEFS VIEWS > runs/agree-....txt

SCENES: comma-separated indices of the suite's scenes; BELIEFS: view seeds 0..BELIEFS-1 per scene.
"""

from __future__ import annotations

import sys
from pathlib import Path

from msmem_core.config import load_config
from msmem_core.perf.step import _decide, _describe, _same, objective_with
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.runner import build_episode, set_threads
from msmem_core.run.states import mid_episode_state

ROOT = Path(__file__).resolve().parents[3]


def main(method: str, suite: str, scenes: str, beliefs: int, views: int) -> None:
    same = total = 0
    for scene in (int(s) for s in scenes.split(",")):
        scene_file = ROOT / "msmem_core" / "suites" / suite / f"scene_{scene:02d}.json"
        cfg = load_config(method, None, {"scene": {"file": str(scene_file)}})
        set_threads(cfg.threads)
        ep = build_episode(cfg, get_plugin_manager())
        ep.sim.reset(ep.scene)
        exact = objective_with(ep, screen_ray_step=1)
        for seed in range(beliefs):
            state = mid_episode_state(ep, views, seed)
            d, e = _decide(ep, state), _decide(ep, state, exact)
            total += 1
            same += _same(d, e)
            print(f"scene {scene} views {views} seed {seed}: {'same' if _same(d, e) else 'DIFFERS'}; "
                  f"default {_describe(d)} | exact {_describe(e)}", flush=True)
    print(f"same decision in {same} of {total}")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4]), int(sys.argv[5]))
