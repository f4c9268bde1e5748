"""A robot's arm in the PyBullet world, driven by joint control (docs/explanation/robots.md, "Execution by the arm").

``ArmDrive`` loads the robot's URDF into the simulator's own client at the robot's base pose, with a fixed
base, and moves it the way a position-controlled arm moves: every physics step of a gripper move, the
target gripper pose of that step (``msmem_core.sim.motion.path_targets``) becomes joint targets by
pybullet's IK, seeded with the arm's current joints, and the joint motors drive there within the URDF's
effort and velocity limits. Every link collides with the objects and the shelf, so what the arm touches
moves, and counts in Position Change like anything else that moves.

Two things are set instead of simulated, as the floating gripper's teleport from its parking pose is:
the arm's configuration for a view (the verified IK answer of ``Robot.reach_camera``; views are in
front of the shelf), and the start of a manipulation, its first waypoint (in front of the shelf too).
When the robot cannot reach either, nothing is set and a note says why (``robot_notes``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pybullet as p
from numpy.typing import NDArray

from msmem_core.errors import UserError
from msmem_core.interfaces import Robot
from msmem_core.sim.arm import ArmDriver
from msmem_core.util.quiet import quiet_stdio
from msmem_core.world.geometry import matrix_to_quat, pose_matrix

POSITION_GAIN = 0.3
"""Joint position gain of the motors (pybullet's default 0.1 lags a 5 cm/s path by centimetres)."""
TRACK_IK_ITERATIONS = 30
"""IK iterations per physics step while tracking (each starts from the current joints, a step away)."""


class ArmDrive(ArmDriver):
    """``robot`` built into the pybullet client ``client`` and driven by its joint motors."""

    def __init__(self, robot: Robot, client: int, finger_force_n: float, finger_friction: float) -> None:
        super().__init__(robot, "PyBullet")
        self.client = client
        self.finger_force_n, self.finger_friction = finger_force_n, finger_friction
        self.uid = -1

    # ------------------------------------------------------------------------------------ building
    def build(self) -> int:
        """Load the arm (after ``resetSimulation``) in its home configuration, hand open; its uid."""
        c, m = self.client, self.model
        pos = m.base_pose[:3, 3].tolist()
        quat = matrix_to_quat(m.base_pose[:3, :3]).tolist()
        with quiet_stdio():  # pybullet reports the URDF's missing inertias
            self.uid = p.loadURDF(m.urdf, pos, quat, useFixedBase=True, physicsClientId=c)
        by_name, link_by_name = {}, {}
        self.movable: list[int] = []
        self.max_force: dict[int, float] = {}
        self.max_speed: dict[int, float] = {}
        self.limits: dict[int, tuple[float, float]] = {}
        for j in range(p.getNumJoints(self.uid, physicsClientId=c)):
            info = p.getJointInfo(self.uid, j, physicsClientId=c)
            by_name[info[1].decode()] = j
            link_by_name[info[12].decode()] = j
            if info[2] != p.JOINT_FIXED:
                self.movable.append(j)
                self.max_force[j], self.max_speed[j] = float(info[10]), float(info[11])
                self.limits[j] = (float(info[8]), float(info[9]))
        missing = [n for n in (*m.joint_names, *m.finger_joints) if n not in by_name]
        if missing or m.flange_link not in link_by_name:
            raise UserError(f"robot {m.name!r}: its URDF has no joint or link named "
                            f"{', '.join(missing or [m.flange_link])}")
        self.joints = [by_name[n] for n in m.joint_names]
        self.fingers = [by_name[n] for n in m.finger_joints]
        self.flange = link_by_name[m.flange_link]
        self.finger_upper = [self.limits[j][1] for j in self.fingers]
        pads = [n for n in m.finger_pads if n not in link_by_name]
        if pads:
            raise UserError(f"robot {m.name!r}: its URDF has no link named {', '.join(pads)}")
        self.pads = [link_by_name[n] for n in m.finger_pads] or list(self.fingers)
        # what every physics step of a move needs, once: IK limits over the movable joints, where the arm's
        # joints sit in an IK answer, the arm motors' forces
        self._ik_lower = [self.limits[j][0] for j in self.movable]
        self._ik_upper = [self.limits[j][1] for j in self.movable]
        self._ik_ranges = [u - lw for u, lw in zip(self._ik_upper, self._ik_lower, strict=True)]
        self._ik_arm = [self.movable.index(j) for j in self.joints]
        self._forces = [self.max_force[j] for j in self.joints]
        for j in self.pads:
            p.changeDynamics(self.uid, j, lateralFriction=self.finger_friction, physicsClientId=c)
        self.set_joints(np.asarray(m.home, dtype=np.float64))
        self.set_fingers(self.max_opening(), reset=True)
        if len(self.gearing):
            self.calibrate_pads(*self._pad_positions())
        return self.uid

    def _pad_positions(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        left, right = (p.getLinkState(self.uid, j, computeForwardKinematics=True, physicsClientId=self.client)[4]
                       for j in self.pads)
        return np.asarray(left, dtype=np.float64), np.asarray(right, dtype=np.float64)

    # ------------------------------------------------------------------------------------ state
    def set_joints(self, q: NDArray[np.float64]) -> None:
        """Put the arm at ``q`` at rest and hold it there (the motors' target)."""
        for j, v in zip(self.joints, q, strict=True):
            p.resetJointState(self.uid, j, float(v), 0.0, physicsClientId=self.client)
        self.drive(q)

    def drive(self, q: NDArray[np.float64]) -> None:
        """Make ``q`` the arm motors' target."""
        self._target = np.asarray(q, dtype=np.float64).copy()
        p.setJointMotorControlArray(
            self.uid, self.joints, p.POSITION_CONTROL, targetPositions=[float(v) for v in q],
            forces=self._forces, positionGains=[POSITION_GAIN] * len(self.joints),
            physicsClientId=self.client)

    def joint_positions(self) -> NDArray[np.float64]:
        states = p.getJointStates(self.uid, self.joints, physicsClientId=self.client)
        return np.array([s[0] for s in states], dtype=np.float64)

    def state(self) -> tuple[tuple[float, float], ...]:
        """Position and velocity of every movable joint (for snapshots)."""
        return tuple((float(s[0]), float(s[1])) for s in p.getJointStates(self.uid, self.movable,
                                                                          physicsClientId=self.client))

    def set_state(self, state: Sequence[tuple[float, float]], arm_target: Sequence[float], opening_m: float) -> None:
        for j, (q, v) in zip(self.movable, state, strict=True):
            p.resetJointState(self.uid, j, q, v, physicsClientId=self.client)
        self.drive(np.asarray(arm_target, dtype=np.float64))
        self.set_fingers(opening_m)

    # ------------------------------------------------------------------------------------ hand
    def tool_pose(self) -> NDArray[np.float64]:
        """The gripper frame (``GripperSpec``'s) of the hand: the flange's pose times ``Robot.tool_mount``."""
        st = p.getLinkState(self.uid, self.flange, computeForwardKinematics=True, physicsClientId=self.client)
        return pose_matrix(st[4], st[5]) @ self.tool

    def opening(self) -> float:
        if len(self.gearing):
            return self.linkage_gap(*self._pad_positions())
        return float(sum(s[0] for s in p.getJointStates(self.uid, self.fingers, physicsClientId=self.client)))

    def finger_speed(self) -> float:
        return float(sum(abs(s[1]) for s in p.getJointStates(self.uid, self.fingers, physicsClientId=self.client)))

    def max_opening(self) -> float:
        if len(self.gearing):
            return float(self._drive_w.max())
        return float(sum(self.finger_upper))

    def set_fingers(self, opening_m: float, reset: bool = False) -> None:
        """Drive each finger to its share of ``opening_m`` with ``finger_force_n`` (``reset``: put it there); a
        linkage's joints to their gearing times the driving joint's position for that opening."""
        if len(self.gearing):
            share = self.linkage_targets(opening_m)
        else:
            share = [opening_m * u / self.max_opening() for u in self.finger_upper]
        for j, q in zip(self.fingers, share, strict=True):
            if reset:
                p.resetJointState(self.uid, j, q, 0.0, physicsClientId=self.client)
            p.setJointMotorControl2(self.uid, j, p.POSITION_CONTROL, targetPosition=q, force=self.finger_force_n,
                                    maxVelocity=self.max_speed[j], physicsClientId=self.client)

    # ------------------------------------------------------------------------------------ motion
    def track(self, position: NDArray[np.float64], quat_xyzw: NDArray[np.float64]) -> None:
        """Joint targets for the gripper frame at (``position``, ``quat_xyzw``): IK of the flange pose from
        the arm's current joints (also the null-space rest pose), clipped to the limits."""
        target = pose_matrix(position, quat_xyzw) @ self.tool_inv
        now = [float(s[0]) for s in p.getJointStates(self.uid, self.movable, physicsClientId=self.client)]
        sol = p.calculateInverseKinematics(
            self.uid, self.flange, target[:3, 3].tolist(), matrix_to_quat(target[:3, :3]).tolist(),
            lowerLimits=self._ik_lower, upperLimits=self._ik_upper, jointRanges=self._ik_ranges, restPoses=now,
            maxNumIterations=TRACK_IK_ITERATIONS, residualThreshold=1e-5, physicsClientId=self.client)
        self.drive(np.clip(np.asarray(sol)[self._ik_arm], self.model.joint_lower, self.model.joint_upper))

    def finger_links(self) -> list[int]:
        return list(self.pads)

    def touching(self, uids: Sequence[int], margin: float) -> bool:
        """Whether any link comes within ``margin`` of one of the bodies ``uids``."""
        return any(p.getClosestPoints(self.uid, u, margin, physicsClientId=self.client) for u in uids)
