"""How far inside its box-shaped target's end each grasp of a run folder was planned.

    .venv/bin/python docs/lab/2026-12-06-dense-shelves/end_margin.py RUN_FOLDER...

Per grasp step (``steps.jsonl``): the target is the object held, else the one touching the fingers
after closing. For a target whose main part is a box, the grasp point (the gripper's pose) is taken
into the object's frame at its pose in the scene file. The fingers close across one horizontal axis
of the box. The margin is how far the point lies inside the box's end along the other axis: half the
extent minus the point's offset, negative beyond the end. Prints one row per grasp, then a summary.
"""

import json
import math
import sys
from pathlib import Path

import numpy as np

from msmem_core.world.scene import object_class


def margins(run: Path) -> list[tuple[int, str, float, bool, bool]]:
    scene = json.loads((run / "scene.json").read_text())
    objects = {o["id"]: o for o in scene["objects"]}
    rows = []
    for line in (run / "steps.jsonl").read_text().splitlines():
        r = json.loads(line)
        if r["skill"] != "grasp":
            continue
        info = r["info"]
        target = info.get("held") if info.get("held") is not None else info.get("touching_after_close")
        if target is None:
            continue
        o = objects[target]
        size = object_class(o["class_name"]).parts[0].size_m
        if len(size) != 3:
            continue  # cylinders: no end
        qx, qy, qz, qw = o.get("quat_xyzw", (0.0, 0.0, 0.0, 1.0))
        yaw = math.atan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))
        rot = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
        pose = np.asarray(r["action"]["pose"])
        local = rot.T @ (pose[:2, 3] - np.asarray(o["position_m"][:2]))
        closing = rot.T @ pose[:2, 0]
        along = 1 if abs(closing[0]) > abs(closing[1]) else 0  # the axis the fingers do not close across
        margin = size[along] / 2 - abs(local[along])
        rows.append((r["step"], o["class_name"], float(margin), bool(r["success"]), bool(r["fell_or_left"])))
    return rows


def main(folders: list[str]) -> None:
    every = []
    for f in folders:
        for step, name, m, ok, fell in margins(Path(f)):
            every.append((m, ok, fell))
            print(f"{Path(f).name} step {step:2d} {name:16s} margin {100 * m:+5.1f} cm  "
                  f"{'held' if ok else 'not held'}{', something fell' if fell else ''}")
    if not every:
        return
    m = np.array([e[0] for e in every])
    ok = np.array([e[1] for e in every])
    fell = np.array([e[2] for e in every])
    near = m < 0.01
    print(f"box grasps {len(m)}: margin median {100 * np.median(m):.1f} cm; within 1 cm of an end {near.sum()} "
          f"(held {ok[near].sum()}, a fall {fell[near].sum()}); further in {(~near).sum()} "
          f"(held {ok[~near].sum()}, a fall {fell[~near].sum()})")


if __name__ == "__main__":
    main(sys.argv[1:])
