"""Write ``shared-positions.poses.yaml``: 300 views from 100 camera positions, each looking at three targets.

MEM's reference camera set reuses about 100 camera positions for three look-at targets (left, middle,
right of the shelf), which msmem's parametric grids (one grid of positions per target) cannot express.
This writes such a set as a poses file (docs/how-to/viewpoints.md): the positions are the default middle
grid's (radius 0.55 m around the middle target, azimuth -30..30 deg, elevation -10..35 deg, 10 x 10),
and view ``k * 100 + i`` is position ``i`` looking at target ``k``.

    .venv/bin/python examples/viewpoints/make_shared_positions.py   # rewrites the YAML beside it
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msmem_core.world.viewpoints import ViewpointConfig, generate_viewpoints

TARGETS_X_M = (-0.25, 0.0, 0.25)


def main() -> None:
    base = ViewpointConfig()
    middle = generate_viewpoints(ViewpointConfig(targets_x_m=(0.0,)))[:, :3, 3]  # the 100 positions
    lines = ["# 300 views: 100 camera positions x 3 look-at targets (examples/viewpoints/make_shared_positions.py)",
             "views:"]
    for tx in TARGETS_X_M:
        target = [tx, base.target_y_m, base.target_z_m]
        for pos in middle:
            p = ", ".join(f"{v:.4f}" for v in pos)
            t = ", ".join(f"{v:.4f}" for v in target)
            lines.append(f"  - {{position_m: [{p}], target_m: [{t}]}}")
    out = Path(__file__).with_name("shared-positions.poses.yaml")
    out.write_text("\n".join(lines) + "\n")
    positions = len(np.unique(middle.round(6), axis=0))
    print(f"wrote {out}: {len(TARGETS_X_M) * len(middle)} views from {positions} positions")


if __name__ == "__main__":
    main()
