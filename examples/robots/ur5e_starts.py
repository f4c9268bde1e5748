"""How the UR5e's IK start configurations were chosen (docs/explanation/robots.md, "The UR5e"): greedily, from 48
seeded random configurations and 6 hand-made ones, by how many probe targets each adds that no chosen
one reaches: every sixth of the 300 views and the forward push tool's start and end points at 5 x across
the shelf, 3 heights (4.5, 8.5 and 14 cm) and 2 depths (in front of the shelf and 10 cm into it).

    python examples/robots/ur5e_starts.py [--base 0,-0.65,-0.3]
"""

from __future__ import annotations

import argparse

import numpy as np
from msmem_push.geometry import gripper_pose
from msmem_robots.config import UR5eConfig
from msmem_robots.ur5e import UR5eRobot

from msmem_core.world.scene import ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="0,-0.65,-0.3", help="base position x,y,z (m) in the shelf frame")
    ap.add_argument("--keep", type=int, default=8, help="how many starts to choose")
    args = ap.parse_args()
    base = tuple(float(v) for v in args.base.split(","))
    rng = np.random.default_rng(0)
    cands = [(0.0, -1.57, 1.57, -1.57, -1.57, 0.0), (0.0, -1.2, 1.8, -0.6, 1.57, 0.0),
             (0.0, -1.0, 1.5, -0.5, 1.57, 0.0), (0.0, -1.4, 2.0, -0.6, 1.57, 3.14),
             (0.3, -1.2, 1.8, -0.6, 1.57, 0.0), (-0.3, -1.2, 1.8, -0.6, 1.57, 0.0)]
    cands += [tuple(float(v) for v in np.round(rng.uniform([-1.2, -2.5, 0.3, -3.14, -3.14, -1.6],
                                                            [1.2, -0.5, 2.6, 0.5, 0.5, 1.6]), 3)) for _ in range(48)]
    robot = UR5eRobot(UR5eConfig(base_position_m=base, disk_cache=False))  # type: ignore[arg-type]
    shelf = ShelfSpec()
    views = generate_viewpoints(ViewpointConfig())
    cam_inv, tool_inv = np.linalg.inv(robot.camera_mount()), np.linalg.inv(robot.tool_mount())
    targets = [("view", views[v] @ cam_inv) for v in range(0, len(views), 6)]
    for x in (-0.25, -0.12, 0.0, 0.12, 0.25):
        for z in (0.045, 0.085, 0.14):
            for y in (-0.12, 0.1):
                targets.append(("push", gripper_pose((x, y), z, (0.0, 1.0), "forward") @ tool_inv))
    robot._use_shelf(shelf)
    cfg = robot.config
    cover = np.zeros((len(cands), len(targets)), dtype=bool)
    for i, start in enumerate(cands):
        for k, (_, target) in enumerate(targets):
            _, perr, aerr = robot._solve(target, np.array(start), check_start=False)
            ok = perr <= cfg.position_tolerance_m and aerr <= cfg.orientation_tolerance_deg
            cover[i, k] = ok and not robot._hits()
    kinds = np.array([k for k, _ in targets])
    got = np.zeros(len(targets), dtype=bool)
    for _ in range(args.keep):
        gain = (cover & ~got).sum(axis=1)
        i = int(np.argmax(gain))
        if gain[i] == 0:
            break
        got |= cover[i]
        print(f"    {cands[i]},  # +{gain[i]}")
    for kind in ("view", "push"):
        print(f"{kind}: {int(got[kinds == kind].sum())} of {int((kinds == kind).sum())} probe targets reached")


if __name__ == "__main__":
    main()
