"""The built-in robots and the ``msmem robot`` commands (pybullet is imported only when a Panda is built)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from msmem_core.plugins import CommandSpec, RobotSpec, hookimpl
from msmem_robots.config import FloatingConfig, PandaConfig, UR5eConfig
from msmem_robots.floating import FloatingRobot


def make_panda(config: PandaConfig) -> Any:
    """Build a ``PandaRobot`` (imports pybullet)."""
    from msmem_robots.panda import PandaRobot

    return PandaRobot(config)


def make_ur5e(config: UR5eConfig) -> Any:
    """Build a ``UR5eRobot`` (imports pybullet; the URDFs come from airo-models)."""
    from msmem_robots.ur5e import UR5eRobot

    return UR5eRobot(config)


@hookimpl
def msmem_robots() -> Iterable[RobotSpec]:
    yield RobotSpec(name="floating", factory=FloatingRobot, config_model=FloatingConfig,
                    description="No arm: the gripper and the camera float, every pose is reachable (the default)")
    yield RobotSpec(name="panda", factory=make_panda, config_model=PandaConfig,
                    description="Franka Panda of pybullet_data with a wrist camera; pybullet IK checked by forward "
                                "kinematics and against the shelf's boards")
    yield RobotSpec(name="ur5e", factory=make_ur5e, config_model=UR5eConfig,
                    description="UR5e with a Robotiq 2F-85 (airo-models' URDFs) and a wrist camera; the same IK and "
                                "checks as the Panda")


@hookimpl
def msmem_commands() -> Iterable[CommandSpec]:
    """``msmem robot reach`` (the body imports what it needs on use)."""
    from msmem_robots.commands import COMMANDS

    yield from COMMANDS
