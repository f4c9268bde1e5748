"""The grasp skill's candidate funnel at every step where manipulation is allowed, in one episode.

    L=docs/lab/2026-12-05-decision-oracle      # from the repository root
    .venv/bin/python $L/step_funnel.py grasp-only 5,7 $L/configs/three-cm-lift.yaml > $L/runs/step-funnel-3cm.txt

Runs the method's episode (40 steps, the library defaults, or a config file over them) on each
``hard25`` scene given and prints
one line per allowed step: the step of the last manipulation, the FE-UMGF buffer's size, the grasps
proposed and the count after every stage of ``GraspSkill.executable``.
"""

from __future__ import annotations

import sys
from typing import Any

import msmem_grasp.skill as grasp_skill

from msmem_core.config import load_config, read_config_file
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.bench import suite_scenes
from msmem_core.run.runner import build_episode, run_episode

rows: list[tuple[Any, ...]] = []
propose = grasp_skill.GraspSkill.propose


def traced_propose(self, ctx):  # type: ignore[no-untyped-def]
    out = propose(self, ctx)
    if ctx.manipulation_allowed:
        rows.append((ctx.step, ctx.last_manipulation, len(self.buffer.hypotheses()), len(out),
                     ctx.funnel.stages(ctx.funnel.skill)))
    return out


grasp_skill.GraspSkill.propose = traced_propose  # type: ignore[method-assign]

if __name__ == "__main__":
    over = read_config_file(sys.argv[3]) if len(sys.argv) > 3 else {}
    for si in (int(a) for a in sys.argv[2].split(",")):
        rows.clear()
        ep = build_episode(load_config(sys.argv[1], None, {**over, "steps": 40, "threads": 1}), get_plugin_manager(),
                           scene=suite_scenes("hard25")[si])
        run_episode(ep)
        ep.sim.close()
        print("scene", si, flush=True)
        for step, last, buffer, proposed, stages in rows:
            print(f" step {step:2d} last manipulation {last:2d} buffer {buffer:5d} proposed {proposed:2d} {stages}",
                  flush=True)
