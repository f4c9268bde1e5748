"""``panda``: the Franka Panda that ships with ``pybullet_data`` (``franka_panda/panda.urdf``, Apache 2.0),
with a wrist camera on its flange; IK, collisions and paths by ``msmem_robots.arm.PybulletArm``.
"""

from __future__ import annotations

from pathlib import Path

from msmem_core.util.quiet import quiet_stdio

with quiet_stdio():  # pybullet prints its build time on import
    import pybullet_data
from msmem_robots.arm import PybulletArm
from msmem_robots.config import PandaConfig

URDF = Path(pybullet_data.getDataPath()) / "franka_panda" / "panda.urdf"
ARM_JOINTS = 7
FLANGE_LINK = "panda_link8"
FINGER_OPEN_M = 0.04
FINGER_JOINTS = ("panda_finger_joint1", "panda_finger_joint2")
FINGERTIP_M = 0.112
"""Distance along the flange's z from ``panda_link8`` to the tips of the open fingers (the finger joints sit
at 0.0584 m in the hand, the fingers reach 0.112 m: their collision boxes in pybullet, less its margin)."""
CAMERA_CARRIERS = ("panda_link7", "panda_link8", "panda_hand", "panda_leftfinger", "panda_rightfinger")
"""The links that move rigidly with the wrist camera (the fingers open along the hand only): a mount into
them is refused once (``_camera_overlap``), and configurations do not check the camera against them or
against ``panda_link6``, next to the flange."""
STARTS: tuple[tuple[float, ...], ...] = (  # chosen greedily from 48 candidates by views and shelf-interior poses
    (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.0),  # Franka's "ready" pose, hand rolled level
    (0.6, -0.785, 0.0, -2.356, 0.0, 1.571, -0.785),  # ready, turned to its left
    (-0.6, -0.785, 0.0, -2.356, 0.0, 1.571, -0.785),  # ready, turned to its right
    (0.0, -0.3, 0.0, -2.4, 0.0, 3.67, 0.785),  # hand level, pointing forward, high
    (-0.6, 0.3, 0.0, -1.9, 0.0, 3.77, -0.785),  # hand level, forward and low, to its right
    (0.6, 0.3, 0.0, -1.9, 0.0, 3.77, -0.785),  # the same to its left
    (0.6, -0.3, 0.0, -2.4, 0.0, 3.67, -0.785),
    (0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 2.356),  # ready, hand rolled the other way
)
"""Start configurations (and null-space rest poses) of the IK, tried in this order; ``ik_starts`` of them."""


class PandaRobot(PybulletArm):
    """Franka Panda with a wrist camera; base in front of the shelf (``PandaConfig``)."""

    name = "panda"
    arm_joints = ARM_JOINTS
    flange_link = FLANGE_LINK
    finger_joints = FINGER_JOINTS
    finger_open = (FINGER_OPEN_M, FINGER_OPEN_M)
    fingertip_m = FINGERTIP_M
    tool_yaw_deg = 45.0  # the hand is turned -45 deg about the flange's z, its fingers close along its y
    camera_carriers = CAMERA_CARRIERS
    camera_skip = ("panda_link6",)
    last_link = "panda_hand"
    starts = STARTS

    def __init__(self, config: PandaConfig | None = None) -> None:
        super().__init__(config or PandaConfig())

    def urdf(self) -> Path:
        return URDF
