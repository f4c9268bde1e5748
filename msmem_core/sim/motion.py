"""How the physics backends move their floating gripper, independent of the engine.

``FloatingGripperSimulator`` holds what the PyBullet and SAPIEN backends share: parking out of view,
the teleport next to the first waypoint when a move starts from the parking pose (the nearest start
with room around it), waypoint following (linear position, slerped rotation, timed by
``speed_mps``) and the finger wait of ``set_gripper``. A backend supplies the engine calls as a
handful of hooks (``_physics_step``, ``_teleport_gripper``, ``_track``, ``_collides``, ...).
"""

from __future__ import annotations

import math
from abc import abstractmethod
from collections.abc import Iterator, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from msmem_core.interfaces import Simulator
from msmem_core.sim.arm import ArmDriver
from msmem_core.world.geometry import matrix_to_quat, pose_matrix, quat_angle, quat_to_matrix, rotation_vector, slerp
from msmem_core.world.scene import SceneSpec

FINGER_SPEED_MPS = 0.1
"""Top speed of each finger while opening or closing."""
ROTATION_LEVER_M = 0.1
"""Rotations are timed so that a point this far from the gripper origin moves at ``speed_mps``."""
PARK_POSITION_M = (0.0, 0.0, 3.0)
"""Where the gripper waits, out of every camera's range; moves from here start with a teleport."""
PARK_QUAT_XYZW = (1.0, 0.0, 0.0, 0.0)
"""Orientation of the parked gripper: a rotation by pi about x, so its approach axis points down."""
START_CLEARANCE_M = 0.02
"""Free space the gripper needs around the pose it teleports to when leaving the parking pose."""
START_BACKOFF_STEP_M = 0.02
START_BACKOFF_MAX_M = 0.50


class PathTarget(NamedTuple):
    """Where the gripper should be after one more time step of a move."""

    position: NDArray[np.float64]
    quat_xyzw: NDArray[np.float64]
    velocity: NDArray[np.float64]
    """Linear velocity of the current segment (m/s)."""
    spin: NDArray[np.float64]
    """Angular velocity of the current segment (rad/s, world axis times rate)."""


def path_targets(
    start: NDArray[np.float64], waypoints: Sequence[NDArray[np.float64]], speed_mps: float, dt: float
) -> Iterator[PathTarget]:
    """The per-time-step targets of a move from ``start`` through ``waypoints`` (4x4 poses).

    Each segment moves the position linearly and slerps the rotation over a whole number of steps,
    timed so that neither the gripper origin nor a point ``ROTATION_LEVER_M`` from it moves faster
    than ``speed_mps``; a segment's last target is its waypoint.
    """
    pos0, q0 = start[:3, 3], matrix_to_quat(start[:3, :3])
    for pose in waypoints:
        pos1, q1 = pose[:3, 3], matrix_to_quat(pose[:3, :3])
        dist = float(np.linalg.norm(pos1 - pos0))
        duration = max(dist, quat_angle(q0, q1) * ROTATION_LEVER_M) / speed_mps
        n = max(1, math.ceil(duration / dt))
        velocity = (pos1 - pos0) / (n * dt)
        spin = rotation_vector(quat_to_matrix(q1) @ quat_to_matrix(q0).T) / (n * dt)
        for i in range(1, n + 1):
            t = i / n
            yield PathTarget(pos0 + t * (pos1 - pos0), slerp(q0, q1, t), velocity, spin)
        pos0, q0 = pos1, q1


def start_candidates(first: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Poses to leave the parking pose to, nearest first: the first waypoint itself, then poses
    backed off from it in ``START_BACKOFF_STEP_M`` steps, alternately along its approach axis and
    towards the open front of the shelf (-y), up to ``START_BACKOFF_MAX_M``."""
    candidates = [first]
    for k in range(1, round(START_BACKOFF_MAX_M / START_BACKOFF_STEP_M) + 1):
        for direction in (-first[:3, 2], np.array([0.0, -1.0, 0.0])):
            pose = first.copy()
            pose[:3, 3] += k * START_BACKOFF_STEP_M * direction
            candidates.append(pose)
    return candidates


class FloatingGripperSimulator(Simulator):
    """A ``Simulator`` whose gripper floats: it is parked out of view, teleported next to the first
    waypoint when a move starts from there, and otherwise driven by physics along interpolated targets.

    Subclasses set ``_parked`` (True after ``reset``) and implement the hooks below.
    """

    _parked: bool
    _arm: ArmDriver | None = None
    """The attached robot's arm, when a backend drives one (it then replaces the floating gripper)."""

    # ------------------------------------------------------------------------------------------ hooks
    @property
    @abstractmethod
    def _time_step_s(self) -> float:
        """Length of one physics step."""

    @abstractmethod
    def _require_scene(self) -> SceneSpec:
        """The current scene; raises ``RuntimeError`` before ``reset``."""

    @abstractmethod
    def _physics_step(self) -> None:
        """Advance physics by one time step."""

    @abstractmethod
    def _opening(self) -> float:
        """Current distance between the fingers."""

    @abstractmethod
    def _finger_speed(self) -> float:
        """Sum of the fingers' absolute joint speeds (m/s)."""

    @abstractmethod
    def _teleport_gripper(self, pose: NDArray[np.float64]) -> None:
        """Put the gripper at ``pose`` at rest and make that its drive target."""

    @abstractmethod
    def _track(self, target: PathTarget) -> None:
        """Make ``target`` the gripper drive's target for the next step of a move."""

    def _end_path(self, position: NDArray[np.float64], quat_xyzw: NDArray[np.float64]) -> None:
        """Called once a move's targets are done, before the gripper catches up with its last waypoint
        (a backend whose drive follows a velocity target zeroes it here)."""

    @abstractmethod
    def _collides(self, pose: NDArray[np.float64], clearance: float, with_objects: bool) -> bool:
        """Whether the gripper at ``pose`` comes within ``clearance`` of a shelf board or, with
        ``with_objects``, of an object (a backend may move the gripper there to find out)."""

    # ------------------------------------------------------------------------------------------ shared
    def _wait_for_fingers(self, goal_m: float) -> float:
        """Step until the opening is within 0.5 mm of ``goal_m`` or the fingers are blocked (10 still
        steps after the first 0.05 s), at most 0.5 s; return the opening."""
        dt = self._time_step_s
        still = 0
        for i in range(max(1, round(0.5 / dt))):
            self._physics_step()
            if abs(self._opening() - goal_m) < 5e-4:
                break
            still = 0 if self._finger_speed() > 2e-3 else still + 1
            if still >= 10 and i * dt > 0.05:
                break
        return self._opening()

    def _start_is_clear(self, start: NDArray[np.float64], first: NDArray[np.float64]) -> bool:
        """Whether the gripper at ``start`` keeps START_CLEARANCE_M from everything and the straight
        path from there to ``first`` does not cross a shelf board (objects on it may be pushed)."""
        if self._collides(start, START_CLEARANCE_M, with_objects=True):
            return False
        dist = float(np.linalg.norm(first[:3, 3] - start[:3, 3]))
        n = math.ceil(dist / 0.01)
        for i in range(1, n):  # the end is the waypoint itself: it may touch what the skill aims at
            pose = start.copy()
            pose[:3, 3] += (i / n) * (first[:3, 3] - start[:3, 3])
            if self._collides(pose, 1e-3, with_objects=False):
                return False
        return True

    def _leave_park(self, first: NDArray[np.float64]) -> None:
        """Teleport out of the parking pose to the first clear pose of ``start_candidates(first)``
        (the waypoint itself if none is). The move then reaches the waypoint under physics. An arm is set
        at the waypoint by the robot's verified IK, or stays parked (and notes why)."""
        if self._arm is not None:
            reach = self._arm.place(first, self._require_scene().shelf, "the first waypoint")
            self._parked = not reach.reachable
            return
        start = next((c for c in start_candidates(first) if self._start_is_clear(c, first)), first)
        self._teleport_gripper(start)
        self._parked = False

    def move_gripper(
        self, waypoints: Sequence[NDArray[np.float64]], opening_m: float | None = None, speed_mps: float = 0.1
    ) -> NDArray[np.float64]:
        """Drive the gripper through the waypoints (linear position, slerped rotation) under physics.

        The opening is set first. From the parking pose the gripper first teleports next to the first
        waypoint (see ``_leave_park``). An arm that cannot reach the first waypoint from its parked or
        view configuration does not move (``robot_notes`` says why). Returns the reached pose.
        """
        self._require_scene()
        if speed_mps <= 0:
            raise ValueError("speed_mps must be positive")
        if opening_m is not None:
            self.set_gripper(opening_m)
        poses = [np.asarray(w, dtype=np.float64) for w in waypoints]
        if not poses:
            return self.gripper_pose()
        if self._parked:
            self._leave_park(poses[0])
            if self._parked:  # an arm that cannot get there
                return self.gripper_pose()
        dt = self._time_step_s
        for target in path_targets(self.gripper_pose(), poses, speed_mps, dt):
            self._track(target)
            self._physics_step()
        pos, quat = poses[-1][:3, 3], matrix_to_quat(poses[-1][:3, :3])
        self._end_path(pos, quat)
        # Let the gripper catch up with the final target (it lags slightly behind a moving target).
        rot = quat_to_matrix(quat)
        for _ in range(round(0.2 / dt)):
            now = self.gripper_pose()
            if np.linalg.norm(now[:3, 3] - pos) < 5e-4 and np.trace(now[:3, :3].T @ rot) > 3 - 1e-5:
                break
            self._physics_step()
        return self.gripper_pose()

    def park_gripper(self) -> None:
        """Teleport the gripper back to its parking pose out of view (an arm: to its home configuration,
        out of the shelf)."""
        self._require_scene()
        if self._arm is not None:
            self._arm.park()
        else:
            self._teleport_gripper(pose_matrix(PARK_POSITION_M, PARK_QUAT_XYZW))
        self._parked = True
