"""``floating``: the gripper and the camera float; every pose is reachable and nothing collides."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from msmem_core.interfaces import Reach, Robot, RobotModel
from msmem_core.world.scene import ShelfSpec
from msmem_robots.config import FloatingConfig


class FloatingRobot(Robot):
    """No arm: what msmem did before robots (the default)."""

    arm: ClassVar[bool] = False

    def __init__(self, config: FloatingConfig | None = None) -> None:
        self.config = config or FloatingConfig()

    def model(self) -> RobotModel:
        return RobotModel(name="floating", urdf=None, base_pose=np.eye(4))

    def camera_mount(self) -> NDArray[np.float64]:
        return np.eye(4)

    def ik(self, flange_pose: NDArray[np.float64], shelf: ShelfSpec) -> Reach:
        return Reach(reachable=True, joints=())

    def collisions(self, joints: Sequence[float], shelf: ShelfSpec) -> list[str]:
        return []

    def reachable_views(self, viewpoints: NDArray[np.float64], shelf: ShelfSpec) -> NDArray[np.bool_]:
        return np.ones(len(viewpoints), dtype=bool)
