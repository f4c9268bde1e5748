"""A robot's arm in the SAPIEN world, driven by its joint drives (docs/explanation/robots.md, "Execution by the arm").

``SapienArm`` is the SAPIEN counterpart of ``msmem_pybullet.arm.ArmDrive``, with the same behaviour:
the robot's URDF is loaded (SAPIEN's URDF loader) at the robot's base pose with a fixed base, and it moves
the way a position-controlled arm moves: every physics step of a gripper move, the target gripper pose
of that step (``msmem_core.sim.motion.path_targets``) becomes joint targets by inverse kinematics
(SAPIEN's Pinocchio model, seeded with the arm's current joints), and PhysX joint drives pull the joints
there within the URDF's effort limits. Gravity is compensated (the arm's links ignore it, as a
controlled arm's would), every link collides with the objects and the shelf (not with each other), so
what the arm touches moves.

As with PyBullet, two things are set instead of simulated: the arm's configuration for a view (the
robot's verified ``reach_camera`` answer) and the start of a manipulation, its first waypoint; when the
robot cannot reach either, nothing is set and a note says why (``take_notes``).

SAPIEN's URDF loader builds the links' visual meshes, which needs its renderer: without a Vulkan device
(``make sapien`` sets up a CPU one) the arm cannot be loaded, and ``build`` says so in one line.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import UserError
from msmem_core.interfaces import Robot
from msmem_core.sim.arm import ArmDriver
from msmem_core.world.geometry import pose_matrix
from msmem_sapien.scene import _matrix, _sapien_pose

ARM_STIFFNESS = 2.0e4
"""N m/rad of an arm joint's drive (PhysX force mode): stiff enough to follow a 10 cm/s path."""
ARM_DAMPING = 2.0e3
TRACK_IK_ITERATIONS = 30
"""CLIK iterations per physics step while tracking (each starts from the current joints, a step away)."""


def urdf_efforts(urdf: str, names: Sequence[str]) -> dict[str, float]:
    """The effort limit of each named joint in the URDF (inf where it gives none)."""
    root = ET.parse(urdf).getroot()
    out = {n: float("inf") for n in names}
    for joint in root.iter("joint"):
        name, limit = joint.get("name"), joint.find("limit")
        if name in out and limit is not None and limit.get("effort") is not None:
            out[name] = float(limit.get("effort", "inf")) or float("inf")
    return out


class SapienArm(ArmDriver):
    """``robot`` built into a SAPIEN scene and driven by its joint drives (module docstring)."""

    def __init__(self, robot: Robot, finger_force_n: float) -> None:
        super().__init__(robot, "SAPIEN")
        model = self.model
        if model.finger_gearing:
            raise UserError(f"simulator 'sapien' does not drive linkage hands yet (robot {model.name!r}: "
                            f"{model.finger_joints[0]} and {len(model.finger_joints) - 1} geared joints); use the "
                            "pybullet simulator")
        self.finger_force_n = finger_force_n
        self.base_inv = np.linalg.inv(np.asarray(model.base_pose, dtype=np.float64))
        self.efforts = urdf_efforts(str(model.urdf), (*model.joint_names, *model.finger_joints))
        self.articulation: Any = None

    # ------------------------------------------------------------------------------------ building
    def build(self, scene: Any, groups: list[int], finger_material: Any, finger_stiffness: float,
              finger_damping: float) -> Any:
        """Load the arm into ``scene`` (a fresh ``sapien.Scene``) in its home configuration; its links'
        shapes get the collision ``groups`` (colliding with everything but each other), the fingers'
        ``finger_material``. Returns the articulation."""
        m = self.model
        loader = scene.create_urdf_loader()
        loader.fix_root_link = True
        try:
            art = loader.load(str(m.urdf))
        except RuntimeError as e:
            raise UserError(f"simulator 'sapien' cannot load robot {m.name!r} from {m.urdf}: {e} (SAPIEN's URDF "
                            "loader needs its renderer: run `make sapien` for a CPU Vulkan driver, or use the "
                            "pybullet simulator)") from e
        if art is None:
            raise UserError(f"simulator 'sapien' found no articulation in {m.urdf} (robot {m.name!r})")
        art.set_root_pose(_sapien_pose(np.asarray(m.base_pose, dtype=np.float64)))
        joints = {j.name: j for j in art.active_joints}
        missing = [n for n in (*m.joint_names, *m.finger_joints) if n not in joints]
        links = {lk.name: lk for lk in art.links}
        if missing or m.flange_link not in links:
            named = ", ".join(missing or [str(m.flange_link)])
            raise UserError(f"robot {m.name!r}: its URDF has no joint or link named {named}")
        order = [j.name for j in art.active_joints]
        self.arm_index = np.array([order.index(n) for n in m.joint_names])
        self.finger_index = np.array([order.index(n) for n in m.finger_joints])
        self.finger_joints = [joints[n] for n in m.finger_joints]
        self.finger_upper = [float(joints[n].get_limits()[0][1]) for n in m.finger_joints]
        for n in m.joint_names:
            joints[n].set_drive_property(ARM_STIFFNESS, ARM_DAMPING, self.efforts[n], "force")
        for j in self.finger_joints:
            j.set_drive_property(finger_stiffness, finger_damping, self.finger_force_n, "force")
        finger_links = {j.get_child_link().name for j in self.finger_joints}
        for lk in art.links:
            lk.disable_gravity = True
            for shape in lk.collision_shapes:
                shape.set_collision_groups(groups)
                if lk.name in finger_links:
                    shape.set_physical_material(finger_material)
        self.finger_entities = tuple(lk.entity.per_scene_id for lk in art.links if lk.name in finger_links)
        self.flange = links[str(m.flange_link)]
        self.pinocchio = art.create_pinocchio_model()
        self._mask = np.zeros(art.dof, dtype=np.int32)
        self._mask[self.arm_index] = 1
        self._lower = np.asarray(m.joint_lower, dtype=np.float64)
        self._upper = np.asarray(m.joint_upper, dtype=np.float64)
        self.articulation = art
        q = art.get_qpos().astype(np.float64)
        q[self.finger_index] = self.finger_upper
        art.set_qpos(q.astype(np.float32))
        self.set_joints(np.asarray(m.home, dtype=np.float64))
        return art

    # ------------------------------------------------------------------------------------ state
    def set_joints(self, q: NDArray[np.float64]) -> None:
        """Put the arm at ``q`` at rest (the fingers stay) and hold it there (the drives' target)."""
        art = self.articulation
        full = art.get_qpos().astype(np.float64)
        full[self.arm_index] = q
        art.set_qpos(full.astype(np.float32))
        art.set_qvel(np.zeros(art.dof, dtype=np.float32))
        self.drive(q)

    def drive(self, q: NDArray[np.float64]) -> None:
        """Make ``q`` the arm drives' target."""
        self._target = np.asarray(q, dtype=np.float64).copy()
        for i, v in zip(self.arm_index, self._target, strict=True):
            self.articulation.active_joints[i].set_drive_target(float(v))

    def joint_positions(self) -> NDArray[np.float64]:
        return self.articulation.get_qpos().astype(np.float64)[self.arm_index]

    def state(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Every joint's position and velocity (for snapshots)."""
        art = self.articulation
        return tuple(float(v) for v in art.get_qpos()), tuple(float(v) for v in art.get_qvel())

    def set_state(self, state: tuple[Sequence[float], Sequence[float]], arm_target: Sequence[float]) -> None:
        art = self.articulation
        art.set_qpos(np.asarray(state[0], dtype=np.float32))
        art.set_qvel(np.asarray(state[1], dtype=np.float32))
        self.drive(np.asarray(arm_target, dtype=np.float64))

    # ------------------------------------------------------------------------------------ hand
    def tool_pose(self) -> NDArray[np.float64]:
        """The gripper frame (``GripperSpec``'s) of the hand: the flange's pose times ``Robot.tool_mount``."""
        return _matrix(self.flange.entity_pose) @ self.tool

    def opening(self) -> float:
        return float(np.sum(self.articulation.get_qpos()[self.finger_index]))

    def finger_speed(self) -> float:
        return float(np.abs(self.articulation.get_qvel()[self.finger_index]).sum())

    def max_opening(self) -> float:
        return float(sum(self.finger_upper))

    def drive_fingers(self, opening_m: float, speed: float) -> None:
        """Each finger's drive to its share of ``opening_m``, moving at ``speed`` (m/s of the opening's half)."""
        for j, u in zip(self.finger_joints, self.finger_upper, strict=True):
            share = u / self.max_opening()
            j.set_drive_target(opening_m * share)
            j.set_drive_velocity_target(speed * 2 * share)

    # ------------------------------------------------------------------------------------ motion
    def track(self, position: NDArray[np.float64], quat_xyzw: NDArray[np.float64]) -> None:
        """Joint targets for the gripper frame at (``position``, ``quat_xyzw``): CLIK of the flange pose in
        the base frame from the arm's current joints, clipped to the limits."""
        target = self.base_inv @ pose_matrix(position, quat_xyzw) @ self.tool_inv
        q, _, _ = self.pinocchio.compute_inverse_kinematics(
            self.flange.index, _sapien_pose(target), initial_qpos=self.articulation.get_qpos().astype(np.float64),
            active_qmask=self._mask, max_iterations=TRACK_IK_ITERATIONS)
        self.drive(np.clip(np.asarray(q)[self.arm_index], self._lower, self._upper))
