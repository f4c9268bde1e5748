"""The built-in robots and the ``msmem robot`` commands (pybullet is imported only when a Panda is built)."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from msmem_core.plugins import CommandSpec, RobotSpec, hookimpl
from msmem_robots.config import FloatingConfig, PandaConfig
from msmem_robots.floating import FloatingRobot


def make_panda(config: PandaConfig) -> Any:
    """Build a ``PandaRobot`` (imports pybullet)."""
    from msmem_robots.panda import PandaRobot

    return PandaRobot(config)


@hookimpl
def msmem_robots() -> Iterable[RobotSpec]:
    yield RobotSpec(name="floating", factory=FloatingRobot, config_model=FloatingConfig,
                    description="No arm: the gripper and the camera float, every pose is reachable (the default)")
    yield RobotSpec(name="panda", factory=make_panda, config_model=PandaConfig,
                    description="Franka Panda of pybullet_data with a wrist camera; pybullet IK checked by forward "
                                "kinematics and against the shelf's boards")


@hookimpl
def msmem_commands() -> Iterable[CommandSpec]:
    """``msmem robot reach`` (the body imports what it needs on use)."""
    from msmem_robots.commands import COMMANDS

    yield from COMMANDS
