"""``msmem bench-grasp``: success rate of the top-1 fused grasp, executed in the simulator (``--sim``,
default PyBullet; any backend, built by the plugin manager).

Per scene seed (generated like the episodes' scenes) and trial: reset the simulator, observe the
episode's start view and ``views - 1`` random viewpoints (seeded by scene and trial) into an analytic
belief, running one FE-UMGF step of the grasp skill after each view (``GraspSkill.track``), then
execute the skill's best executable grasp (``GraspSkill.executable``, highest fused E[q]) with the
skill's own ``execute``. A trial succeeds when the object is still between the fingers after the
lift and the retreat out of the shelf (``Outcome.success``). Ground truth is read only to score:
the class of the object actually held against the believed target class, and the displacement of
the other objects. Trials where no grasp is executable count separately (not as failures).
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.plugins import ComponentRef


class GraspBenchConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    scene_seeds: list[int] = Field(default_factory=lambda: list(range(10)))
    """Seeds of the generated scenes."""
    trials: int = Field(2, ge=1)
    """Trials per scene: a fresh simulator and belief each (trial 0 starts at the episodes' start
    view, later ones at a random view), so the views and the fused grasps differ."""
    views: int = Field(8, ge=1, le=300)
    """Observations before the grasp (the start view, then ``view_policy``); one FE-UMGF step each."""
    view_policy: Literal["nbv", "random"] = "nbv"
    """nbv: each next view maximises IG (as a view-only episode); random: seeded random viewpoints."""
    require_hard: bool = False
    """Plain random arrangements (30-45 % floor occupancy, like FE-vMF's training scenes; default) or
    the episodes' hard scenes (a front row of tall objects hiding > 3 others: few graspable objects)."""
    label_noise: float = Field(0.05, ge=0.0, le=1.0)
    """The simulator's structured segmentation noise (its default)."""
    skill: dict[str, Any] = Field(default_factory=dict)
    """Parameters of the grasp skill (``GraspConfig``)."""
    simulator: ComponentRef = ComponentRef(name="pybullet")
    """The backend the grasps are executed in (``--sim``); its ``seed`` is set per scene and trial and
    its ``label_noise`` is the one above, unless ``params`` set them."""


@dataclass
class TrialResult:
    scene_seed: int
    trial: int
    candidates: int
    executed: bool
    success: bool
    target_class: int | None
    held_class: int | None
    affordance: float
    displaced_m: float
    """Summed XY displacement of the objects that stayed (the held one excluded)."""
    fell_or_left: int
    predictor: str
    seconds: float


def run_scene(task: tuple[int, GraspBenchConfig]) -> list[dict[str, Any]]:
    """All trials of one scene seed (a module-level function: executors pickle it)."""
    from msmem_analytic.observation import AnalyticObservationModel

    from msmem_core.map.belief import EvidentialMap
    from msmem_core.map.ig import IGService
    from msmem_core.msas import execute_measured
    from msmem_core.sim.build import build_simulator
    from msmem_core.world.camera import CameraConfig
    from msmem_core.world.grid import GridSpec
    from msmem_core.world.scenegen import SceneGenConfig, generate_scene
    from msmem_core.world.viewpoints import ViewpointConfig, default_start_view, generate_viewpoints
    from msmem_grasp.skill import GraspConfig, GraspSkill

    seed, cfg = task
    scene = generate_scene(seed, SceneGenConfig(require_hard=cfg.require_hard))
    classes = {o.id: o.class_id for o in scene.objects}
    vcfg = ViewpointConfig()
    viewpoints = generate_viewpoints(vcfg)
    grid = GridSpec.around_box(scene.shelf.interior_lower, scene.shelf.interior_upper, 0.01)
    observe = AnalyticObservationModel()
    ig = IGService(grid, CameraConfig(), viewpoints, scene.shelf) if cfg.view_policy == "nbv" else None
    out = []
    for trial in range(cfg.trials):
        t0 = time.perf_counter()
        sim = build_simulator(cfg.simulator, label_noise=cfg.label_noise, seed=1000 * seed + trial)
        try:
            sim.reset(scene)
            rng = np.random.default_rng([seed, trial])
            order = [int(v) for v in rng.permutation(len(viewpoints))]
            # trial 0 starts at the episodes' start view, later trials at a random one
            v = default_start_view(vcfg) if trial == 0 else order[0]
            skill = GraspSkill(GraspConfig(**{"seed": seed * 100 + trial, **cfg.skill}))
            belief = EvidentialMap.empty(grid)
            visited: set[int] = set()
            for step in range(cfg.views):
                if step > 0:
                    if ig is not None:
                        gain = ig.view_ig(ig.prepare(belief))
                        gain[sorted(visited)] = -np.inf
                        v = int(np.argmax(gain))
                    else:
                        v = next(u for u in order if u not in visited)
                belief = observe.update(belief, sim.observe(viewpoints[v]))
                visited.add(v)
                ctx = SimpleNamespace(step=step, belief=belief, visited=set(visited), viewpoints=viewpoints,
                                      shelf=scene.shelf, manipulation_allowed=True, last_manipulation=-1)
                skill.track(ctx)
            cands = skill.executable(belief, scene.shelf)
            res = TrialResult(seed, trial, len(cands), False, False, None, None, 0.0, 0.0, 0, skill.predictor, 0.0)
            if cands:
                a = cands[0]
                outcome = execute_measured(skill, sim, a, SimpleNamespace(shelf=scene.shelf))  # as MSAS does
                held = outcome.removed[0] if outcome.removed else None
                res.executed = True
                res.success = outcome.success
                res.target_class = a.target_class
                res.held_class = classes[held] if held is not None else None
                res.affordance = a.affordance
                res.displaced_m = float(sum(outcome.displacement_m.values()))
                res.fell_or_left = len(outcome.fell_or_left)
        finally:
            sim.close()
        res.seconds = time.perf_counter() - t0
        out.append(asdict(res))
    return out


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    executed = [r for r in rows if r["executed"]]
    ok = [r for r in executed if r["success"]]
    return {
        "trials": len(rows),
        "executed": len(executed),
        "no_candidate": len(rows) - len(executed),
        "successes": len(ok),
        "success_rate": len(ok) / len(executed) if executed else float("nan"),
        "held_believed_class": sum(r["held_class"] == r["target_class"] for r in ok),
        "mean_displaced_m": float(np.mean([r["displaced_m"] for r in executed])) if executed else float("nan"),
        "fell_or_left": sum(r["fell_or_left"] > 0 for r in executed),
        "predictor": rows[0]["predictor"] if rows else "",
        "seconds_per_trial": float(np.mean([r["seconds"] for r in rows])) if rows else float("nan"),
    }


def bench_grasp(cfg: GraspBenchConfig, out: Path | None = None, executor: str = "local", workers: int = 1,
                progress: bool = True) -> dict[str, Any]:
    """Run every scene (one task each) and return the summary; with ``out``, write ``trials.jsonl``
    and ``summary.json`` there."""
    from msmem_core.run.executors import TaskFailure, run_tasks
    from msmem_core.sim.build import check_simulator

    check_simulator(cfg.simulator, label_noise=cfg.label_noise)  # a bad --sim fails before any scene starts
    results = run_tasks(run_scene, [(s, cfg) for s in cfg.scene_seeds], executor=executor, workers=workers,
                        progress=progress, threads=1, description="bench-grasp", on_error="raise")
    rows = [r for res in results if not isinstance(res, TaskFailure) for r in res]
    summary = summarise(rows)
    summary["config"] = cfg.model_dump()
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        (out / "trials.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
        (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return {"summary": summary, "rows": rows}
