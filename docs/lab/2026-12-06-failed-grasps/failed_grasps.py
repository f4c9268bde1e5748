"""What went wrong in each grasp of a run folder that did not hold its object.

    .venv/bin/python docs/lab/2026-12-06-failed-grasps/failed_grasps.py RUN_FOLDER...

Reads each folder's ``steps.jsonl`` (``msmem run`` writes it) and sorts every grasp step whose
object was not held (``info.held`` is None) into one of three kinds, from what the simulator
reported after the fingers closed:

- ``stopped short``: the gripper ended more than 1 cm from the planned grasp pose
  (``info.pose_error_m``): something blocked it on the way in;
- ``closed on nothing``: it reached the pose, and after closing no object touched the fingers;
- ``slipped``: it reached the pose and closed on an object, which the lift did not carry.

A grasp counts as a ``retry`` when an earlier grasp of the episode failed on an object of the same
class with its contact point within 5 cm. Prints one row per failed grasp, then the counts.
"""

import json
import sys
from collections import Counter
from pathlib import Path

import numpy as np

from msmem_core.world.placement import load_scene

STOPPED_SHORT_M = 0.01
RETRY_M = 0.05


def kind(info: dict) -> str:
    if info.get("pose_error_m", 0.0) > STOPPED_SHORT_M:
        return "stopped short"
    return "closed on nothing" if info.get("touching_after_close") is None else "slipped"


def failed(run: Path) -> list[dict]:
    scene = load_scene(str(run / "scene.json"))
    names = {o.id: o.class_name for o in scene.objects}
    class_names = {o.class_id: o.class_name for o in scene.objects}
    rows, earlier = [], []
    for line in (run / "steps.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r["skill"] != "grasp":
            continue
        info, action = r["info"], r["action"]
        contact = np.asarray(action["contact_m"])
        if info.get("held") is not None:
            continue
        target = class_names.get(action.get("target_class"))
        retry = any(t == target and np.linalg.norm(contact - c) <= RETRY_M for t, c in earlier)
        earlier.append((target, contact))
        rows.append({
            "run": run.name, "step": r["step"], "kind": kind(info), "retry": retry,
            "target": target,
            "touched": names.get(info.get("touching_after_close")),
            "pose_error_cm": 100 * info.get("pose_error_m", 0.0), "closed_cm": 100 * info["closed_opening_m"],
            "approach": [round(float(v), 2) for v in np.asarray(action["pose"])[:3, 2]],
            "contact": [round(float(v), 3) for v in contact],
            "moved": [names[m] for m in info.get("moved", [])], "fell": [names[m] for m in r["fell_or_left"]],
        })
    return rows


def main(folders: list[str]) -> None:
    rows = [row for f in folders for row in failed(Path(f))]
    for x in rows:
        print(f"{x['run']} step {x['step']:2d} {x['kind']:17s}{' (retry)' if x['retry'] else '        '} "
              f"target {x['target']!s:16s} touched {x['touched']!s:16s} stopped {x['pose_error_cm']:4.1f} cm short, "
              f"closed to {x['closed_cm']:4.1f} cm, approach {x['approach']}, contact {x['contact']}, "
              f"moved {x['moved']}, fell {x['fell']}")
    counts = Counter(x["kind"] for x in rows)
    print(f"failed grasps {len(rows)}: " + ", ".join(f"{k} {counts[k]}" for k in
                                                     ("stopped short", "closed on nothing", "slipped"))
          + f"; retries {sum(x['retry'] for x in rows)}")


if __name__ == "__main__":
    main(sys.argv[1:])
