"""Where should the Panda (or the UR5e) stand to push? A sweep of base poses (docs/explanation/robots.md, "Limits").

For each base position (shelf frame: y in front of the shelf, z below its floor) it counts

- the default candidate views the wrist camera reaches (of 300), and
- the straight pushes the arm can follow with the hand pointing down (as the push skill pushes today)
  and with the hand pointing into the shelf (fingers closing along the shelf; the wrist camera under
  or above the hand), at several heights.

A push here is three waypoints of the gripper frame: 8 cm in front of the shelf at the push's start x
and height, the start (5, 15 or 25 cm deep; x from -0.3 to 0.3 m in 10 cm steps), and the end 10 cm
further left, right or inwards (``Robot.reach_path``: points 2 cm apart, each reached by IK from the
previous one, collision-free against the shelf and the arm itself). Nothing is random.

    .venv/bin/python examples/robots/push_reach_sweep.py            # the default sweep
    .venv/bin/python examples/robots/push_reach_sweep.py --bases=-0.55,-0.3   # one base
    .venv/bin/python examples/robots/push_reach_sweep.py --robot ur5e --bases=-0.65,-0.3
"""

from __future__ import annotations

import argparse
import itertools
import time

import numpy as np
from msmem_robots.config import PandaConfig, UR5eConfig
from msmem_robots.panda import PandaRobot
from msmem_robots.ur5e import UR5eRobot

from msmem_core.world.scene import ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

DOWN = np.column_stack([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
"""Gripper frame pointing down (z to -z), fingers closing along the shelf (x)."""
FORWARD = np.column_stack([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Gripper frame pointing into the shelf (z to +y), fingers closing along the shelf (x), its y down: the
Panda's wrist camera (on the gripper frame's +y) under the hand."""
FORWARD_UP = np.column_stack([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
"""The same rolled 180 degrees about the approach: the wrist camera above the hand."""
TOOLS = {"down": DOWN, "forward, camera under": FORWARD, "forward, camera above": FORWARD_UP}
XS = np.round(np.arange(-0.3, 0.301, 0.1), 3)
DEPTHS = (0.05, 0.15, 0.25)
MOVES = {"left": (-0.1, 0.0), "right": (0.1, 0.0), "in": (0.0, 0.1)}


def pose(rot: np.ndarray, p: tuple[float, float, float]) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rot, p
    return t


def pushes(rot: np.ndarray, height: float) -> list[np.ndarray]:
    out = []
    for x, d, (dx, dy) in itertools.product(XS, DEPTHS, MOVES.values()):
        out.append(np.stack([pose(rot, (x, -0.08, height)), pose(rot, (x, d, height)),
                             pose(rot, (x + dx, d + dy, height))]))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bases", default=";".join(f"{y},{z}" for y in (-0.45, -0.55, -0.65, -0.75)
                                                 for z in (-0.3, -0.1, 0.0, 0.1)),
                    help="base positions 'y,z;y,z;...' (m, shelf frame; x = 0)")
    ap.add_argument("--heights", default="0.04,0.085,0.14", help="push heights (m above the shelf floor)")
    ap.add_argument("--robot", choices=("panda", "ur5e"), default="panda")
    args = ap.parse_args()
    shelf = ShelfSpec()
    views = generate_viewpoints(ViewpointConfig(), shelf)
    heights = [float(h) for h in args.heights.split(",")]
    n = len(pushes(DOWN, 0.0))
    cols = [f"{tool} {h * 100:g} cm" for tool in TOOLS for h in heights]
    print(f"| base y (m) | base z (m) | views (of {len(views)}) | " + " | ".join(f"{c} (of {n})" for c in cols)
          + " | s |")
    print("|" + "---|" * (len(cols) + 4))
    for base in args.bases.split(";"):
        y, z = (float(v) for v in base.split(","))
        t0 = time.perf_counter()
        robot = (UR5eRobot(UR5eConfig(base_position_m=(0.0, y, z), disk_cache=False)) if args.robot == "ur5e"
                 else PandaRobot(PandaConfig(base_position_m=(0.0, y, z), disk_cache=False)))
        try:
            nviews = int(robot.reachable_views(views, shelf).sum())
            counts = [sum(robot.reach_path(p, shelf).reachable for p in pushes(rot, h))
                      for rot in TOOLS.values() for h in heights]
        finally:
            robot.close()
        print(f"| {y:g} | {z:g} | {nviews} | " + " | ".join(str(c) for c in counts)
              + f" | {time.perf_counter() - t0:.0f} |", flush=True)


if __name__ == "__main__":
    main()
