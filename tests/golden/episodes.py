"""Golden episodes: for every method preset, a short seeded run's actions and metrics.

They guard behaviour-preserving refactors: ``tests/test_golden.py`` reruns each episode and compares
it with ``tests/data/golden/<preset>.json``. Regenerate (only when behaviour is *meant* to change,
and say so in the commit) with::

    .venv/bin/python -m tests.golden.episodes
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from msmem_core.config import METHODS, deep_merge, load_config, read_config_file
from msmem_core.plugins import get_plugin_manager
from msmem_core.run.runner import build_episode, run_episode
from msmem_core.world.scenegen import generate_scene

ROOT = Path(__file__).resolve().parents[2]
GOLDEN_DIR = ROOT / "tests" / "data" / "golden"
STEPS = 5
SCENE_SEED = 3
SCENE_FILE = GOLDEN_DIR / "scene.json"
"""``generate_scene(SCENE_SEED)`` as written by ``main`` (generating it takes 15-20 s; the slow
``test_the_golden_scene_is_the_generated_one`` checks that it still is)."""
# manipulation may start at step 1, so five steps exercise every skill of a preset
OVERRIDES: dict[str, Any] = {"steps": STEPS, "scene": {"file": str(SCENE_FILE)},
                             "msas": {"manipulation_window": [1, 38]}, "report_steps": []}
PRESET_OVERRIDES: dict[str, dict[str, Any]] = {
    # with the default blocked_exit (skip) no grasp of this scene leaves without meeting a believed object
    # in five steps: the grasp this episode executes needs blocked_exit: lift_m to be proposed
    "grasp-only": {"skill_params": {"grasp": {"blocked_exit": "lift_m"}}},
}


# The presets' episodes run the analytic models (examples/analytic.yaml: the analytic update and the
# effect models trained on its beliefs), so that they still guard the analytic path and every manipulation
# skill; ``library-defaults`` is the default method under today's library defaults (cnabu-map).
ANALYTIC = {**read_config_file(ROOT / "examples" / "analytic.yaml"), "ig": {"predicted_entropy": "as-predicted"}}
"""The preset episodes run the analytic models with MEM's IG for predictions (the entropy a prediction adds
counts), under which the push and grasp of this scene win within five steps, so that every manipulation
skill's path stays guarded; ``library-defaults`` runs today's defaults as they are."""
DEFAULTS_EPISODE = "library-defaults"
NAMES = (*METHODS, DEFAULTS_EPISODE)


def _round(x: Any) -> Any:
    if isinstance(x, float):
        return round(x, 5)
    if isinstance(x, dict):
        return {str(k): _round(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_round(v) for v in x]
    if isinstance(x, np.generic):
        return _round(x.item())
    if isinstance(x, np.ndarray):
        return _round(x.tolist())
    return x


def record(name: str) -> dict[str, Any]:
    """One golden episode (a preset under the analytic defaults, or ``library-defaults``): per step the
    skill, the action, the objective and the metrics."""
    if name == DEFAULTS_EPISODE:
        method, cfg = "ours", load_config("ours", None, OVERRIDES)
    else:
        method = name
        cfg = load_config(method, None, deep_merge(OVERRIDES | PRESET_OVERRIDES.get(method, {}), ANALYTIC))
    ep = build_episode(cfg, get_plugin_manager())
    final = run_episode(ep)
    steps = [{"step": r["step"], "skill": r["skill"], "action": _round(r["action"]),
              "objective": _round(r["objective"]), "success": r["success"], "metrics": _round(r["metrics"])}
             for r in ep.records]
    return {"method": method, "scene_seed": SCENE_SEED, "steps": steps, "actions": final["actions"]}


def main(argv: list[str]) -> None:
    GOLDEN_DIR.mkdir(parents=True, exist_ok=True)
    generate_scene(SCENE_SEED).to_json(SCENE_FILE)
    for name in argv or NAMES:
        rec = record(name)
        (GOLDEN_DIR / f"{name}.json").write_text(json.dumps(rec, indent=1) + "\n")
        print(name, rec["actions"])


if __name__ == "__main__":
    main(sys.argv[1:])
