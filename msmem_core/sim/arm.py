"""What the physics backends' arm drivers share (``msmem_pybullet.arm``, ``msmem_sapien.arm``).

A backend that drives a robot's arm (``Simulator.attach_robot``) subclasses ``ArmDriver`` with its
engine calls (``set_joints``, ...) and keeps the rest: the checks that the robot can be driven at all,
the tool mount, placing the arm for a view or a first waypoint by the robot's verified IK (or noting
why it cannot), parking, and the notes the loop puts in the step record.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import UserError
from msmem_core.interfaces import Reach, Robot, RobotModel
from msmem_core.world.scene import ShelfSpec


def check_drivable(model: RobotModel, simulator: str) -> None:
    """Refuse, in one line, a robot a simulator cannot build and drive as an arm: it needs a URDF and a
    flange link, finger joints to open and close its hand, and a home configuration to park it."""
    if model.urdf is None or model.flange_link is None:
        raise UserError(f"robot {model.name!r} has no URDF or flange link to build an arm from")
    if not model.finger_joints:
        raise UserError(f"robot {model.name!r} names no finger joints (RobotModel.finger_joints): {simulator} "
                        "cannot open or close its hand")
    if model.finger_gearing and (len(model.finger_gearing) != len(model.finger_joints)
                                 or len(model.finger_opening) < 2 or len(model.finger_pads) != 2):
        raise UserError(f"robot {model.name!r}: a linkage hand needs a gearing per finger joint "
                        f"({len(model.finger_gearing)} for {len(model.finger_joints)}), an opening table of at least "
                        f"two rows ({len(model.finger_opening)}) and two pads ({len(model.finger_pads)})")
    if len(model.home) != len(model.joint_names):
        raise UserError(f"robot {model.name!r} gives no home configuration (RobotModel.home) of its "
                        f"{len(model.joint_names)} joints: {simulator} needs one to park the arm")


class ArmDriver(ABC):
    """A robot's arm in one backend's world: the engine calls are the subclass's."""

    def __init__(self, robot: Robot, simulator: str) -> None:
        model = robot.model()
        check_drivable(model, simulator)
        self.robot, self.model = robot, model
        self.tool = robot.tool_mount()
        self.tool_inv = np.linalg.inv(self.tool)
        self.notes: list[str] = []
        self._target = np.asarray(model.home, dtype=np.float64)
        self.gearing = np.asarray(model.finger_gearing, dtype=np.float64)
        """A linkage hand's gearing (empty: prismatic fingers)."""
        table = np.asarray(model.finger_opening, dtype=np.float64).reshape(-1, 2)
        self._drive_q, self._drive_w = table[:, 0], table[:, 1]
        self._pad_offset = 0.0

    def linkage_targets(self, opening_m: float) -> list[float]:
        """A linkage hand's joint positions for ``opening_m``: the driving joint's from the opening table,
        the others geared to it."""
        q = float(np.interp(opening_m, self._drive_w[::-1], self._drive_q[::-1]))
        return [float(g * q) for g in self.gearing]

    def linkage_gap(self, left: NDArray[np.float64], right: NDArray[np.float64]) -> float:
        """A linkage hand's opening from its pads' frame origins: their distance along the closing axis less
        what it is beyond the opening table's at the widest (``calibrate_pads``). The linkage's loop is not
        closed in a URDF, so with an object between the pads the driving joint's angle does not tell."""
        x = self.tool_pose()[:3, 0]
        return abs(float(np.dot(np.asarray(right) - np.asarray(left), x))) - self._pad_offset

    def calibrate_pads(self, left: NDArray[np.float64], right: NDArray[np.float64]) -> None:
        """With the hand at its widest: the pads' origins are this much farther apart than the opening."""
        self._pad_offset = 0.0
        self._pad_offset = self.linkage_gap(left, right) - float(self._drive_w[0])

    @abstractmethod
    def set_joints(self, q: NDArray[np.float64]) -> None:
        """Put the arm at ``q`` (``RobotModel.joint_names`` order) at rest and hold it there."""

    @abstractmethod
    def tool_pose(self) -> NDArray[np.float64]:
        """The gripper frame of the hand: the flange's pose times ``Robot.tool_mount``."""

    @abstractmethod
    def track(self, position: NDArray[np.float64], quat_xyzw: NDArray[np.float64]) -> None:
        """Joint targets that bring the gripper frame to (``position``, ``quat_xyzw``), for one physics step."""

    @abstractmethod
    def max_opening(self) -> float:
        """The hand's widest opening (the sum of its finger joints' upper limits)."""

    def targets(self) -> tuple[float, ...]:
        """The arm drives' current targets (for snapshots)."""
        return tuple(float(q) for q in self._target)

    def place(self, tool_pose: NDArray[np.float64], shelf: ShelfSpec, what: str) -> Reach:
        """Set the arm where its gripper frame is at ``tool_pose`` (the robot's verified IK); when it cannot,
        leave the arm and note why (``what`` names the pose in the note)."""
        reach = self.robot.ik(np.asarray(tool_pose) @ self.tool_inv, shelf)
        self._apply(reach, what)
        return reach

    def place_camera(self, camera_to_world: NDArray[np.float64], shelf: ShelfSpec) -> Reach:
        """Set the arm where its wrist camera is at ``camera_to_world``; when it cannot, note why."""
        reach = self.robot.reach_camera(camera_to_world, shelf)
        self._apply(reach, "the camera pose")
        return reach

    def _apply(self, reach: Reach, what: str) -> None:
        if reach.reachable and reach.joints is not None:
            self.set_joints(np.asarray(reach.joints, dtype=np.float64))
        else:
            self.notes.append(f"{what}: {reach.reason} (the arm did not move)")

    def park(self) -> None:
        """The home configuration (out of the shelf)."""
        self.set_joints(np.asarray(self.model.home, dtype=np.float64))

    def take_notes(self) -> list[str]:
        """What the arm could not do since the last call, one line each."""
        out, self.notes = self.notes, []
        return out
