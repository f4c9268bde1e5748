"""SAPIEN 3 implementation of ``Simulator``: PhysX (CPU) rigid-body shelf scenes, a floating parallel-jaw
gripper and a depth + semantic camera, with the same semantics as the PyBullet reference backend.

The backend is three modules: ``scene`` builds the shelf, objects and gripper (``SceneBuilder``),
``camera`` renders observations (``CameraView``), and this one runs the simulation (``SapienSimulator``).

Design notes:
- Each instance owns its own ``sapien.Scene`` with a ``PhysxCpuSystem`` (single-threaded, enhanced
  determinism). SAPIEN poses are (position, quaternion **wxyz**); core uses xyzw and 4x4 matrices,
  converted at this boundary only.
- Objects, friction and the gripper articulation: see ``msmem_sapien.scene``.
- Camera: see ``msmem_sapien.camera``.
- ``snapshot`` records the full state in plain data; ``restore`` rebuilds the scene from it, which brings
  back removed objects and discards solver caches, so restoring and repeating the same calls
  reproduces the same result bit for bit.
"""

from __future__ import annotations

import itertools
import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

with warnings.catch_warnings():  # "Failed to find system libvulkan": SAPIEN then uses its bundled loader
    warnings.simplefilter("ignore", UserWarning)
    import sapien

from msmem_core.errors import UserError
from msmem_core.interfaces import GRIPPER_ID, Capabilities, Contact, Observation, Robot
from msmem_core.sim.motion import (
    FINGER_SPEED_MPS,
    PARK_POSITION_M,
    PARK_QUAT_XYZW,
    FloatingGripperSimulator,
    PathTarget,
)
from msmem_core.world.geometry import boxes_overlap, matrix_to_quat, pose_matrix
from msmem_core.world.scene import SceneSpec, ShelfSpec
from msmem_sapien.arm import SapienArm
from msmem_sapien.camera import CameraView
from msmem_sapien.config import SapienConfig
from msmem_sapien.scene import SceneBuilder, _BodyState, _matrix, _Object, _sapien_pose

CONTACT_DISTANCE_M = 1e-3
"""Contact points farther apart than this are not reported as contacts."""


# ------------------------------------------------------------------------------------ state records
_ContactPoint = tuple[int, int, int, int, tuple[float, float, float], float]
"""(entity a, entity b, id a, id b, position, normal force) of one touching contact point."""


@dataclass(frozen=True)
class _Snapshot:
    """Everything ``restore`` needs to rebuild the world exactly."""

    owner: int
    scene: SceneSpec
    objects: tuple[tuple[int, _BodyState], ...]
    """Objects present at snapshot time, in scene order."""
    palm: _BodyState
    finger_positions: tuple[float, float]
    finger_velocities: tuple[float, float]
    finger_goal_m: float
    finger_command_m: float
    gripper_target: tuple[tuple[float, ...], tuple[float, ...]]
    parked: bool
    contacts: tuple[_ContactPoint, ...]
    """The touching points of the last step (PhysX reports them only after a step)."""
    arm: tuple[tuple[float, ...], tuple[float, ...]] = ((), ())
    """With an arm: every joint's position and velocity (the fields above then hold no finger state)."""
    arm_target: tuple[float, ...] = ()



_OWNER_IDS = itertools.count()


class SapienSimulator(SceneBuilder, CameraView, FloatingGripperSimulator):
    """Shelf scenes in SAPIEN 3 (PhysX on the CPU; one scene per instance)."""

    def __init__(self, config: SapienConfig | None = None, **kwargs: Any) -> None:
        if config is not None and kwargs:
            raise UserError("pass either a SapienConfig or keyword options, not both")
        self.config = config if config is not None else SapienConfig(**kwargs)
        self._owner = next(_OWNER_IDS)
        self._rng = np.random.default_rng(self.config.seed)
        g = self.config.gripper
        self._palm_centre = np.array([0.0, 0.0, -g.finger_length_m - g.palm_depth_m / 2])
        self._native = self._choose_camera()
        self._scene: SceneSpec | None = None
        self._sapien: sapien.Scene | None = None
        self._objects: dict[int, _Object] = {}
        self._ids: dict[int, int] = {}
        """Entity ``per_scene_id`` -> object id, ``GRIPPER_ID`` or ``SHELF_ID``."""
        self._fingers: tuple[int, int] = (-1, -1)
        """``per_scene_id`` of the left and right finger links."""
        self._gripper_target: tuple[tuple[float, ...], tuple[float, ...]] = (PARK_POSITION_M, PARK_QUAT_XYZW)
        self._finger_goal_m = g.max_opening_m
        self._finger_command_m = g.max_opening_m
        self._finger_velocity = 0.0
        self._parked = True
        self._camera: Any = None
        self._shelf_boxes = (np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 3)))
        self._shelf_mesh_cache: tuple[ShelfSpec, list[Any]] | None = None
        self._pixel_rays: NDArray[np.float32] | None = None
        self._contact_cache: list[_ContactPoint] | None = None
        self._arm: SapienArm | None = None

    def attach_robot(self, robot: Robot) -> None:
        """From the next ``reset`` on, the robot's arm (its URDF, at its base pose) replaces the floating
        gripper and is driven by its joint drives (``msmem_sapien.arm``). A robot without an arm changes
        nothing. The arm needs SAPIEN's renderer (its URDF loader builds visuals): refused in one line
        without it."""
        if not robot.arm:
            return
        if not self._native:
            raise UserError(f"simulator 'sapien' cannot load robot {robot.model().name!r}: SAPIEN's URDF loader needs "
                            "its renderer, which has no Vulkan device here (run `make sapien` for a CPU one), or use "
                            "the pybullet simulator")
        self._arm = SapienArm(robot, self.config.gripper.finger_force_n)

    def robot_notes(self) -> list[str]:
        return self._arm.take_notes() if self._arm is not None else []

    # ------------------------------------------------------------------------------------- lifecycle
    def reset(self, scene: SceneSpec) -> None:
        """Build the shelf and objects at their poses, park the gripper open, settle for ``settle_s``."""
        g = self.config.gripper
        self._scene = scene
        self._finger_goal_m = self._finger_command_m = g.max_opening_m
        self._gripper_target = (PARK_POSITION_M, PARK_QUAT_XYZW)
        self._parked = True
        self._build_world(scene, [(o, None) for o in scene.objects])
        if self._arm is None:
            q = g.max_opening_m / 2
            self._articulation.set_qpos(np.array([q, q], dtype=np.float32))
        else:
            self._finger_goal_m = self._finger_command_m = self._arm.max_opening()
        self._drive_fingers(0.0)
        self.step(self.config.settle_s)

    def close(self) -> None:
        """Drop the scene (idempotent)."""
        self._camera = None
        self._objects = {}
        self._contact_cache = None
        for name in ("_articulation", "_drive", "_links", "_joints"):
            self.__dict__.pop(name, None)
        self._sapien = None

    def observe(self, camera_to_world: NDArray[np.float64]) -> Observation:
        """``CameraView.observe``; with an arm, the wrist camera takes the view: the arm is set there first
        (and is in the image), or a note says why it could not be."""
        if self._arm is not None:
            self._arm.place_camera(np.asarray(camera_to_world, dtype=np.float64), self._require_scene().shelf)
            self._parked = True  # the next move starts at its first waypoint, as from the parking pose
        return super().observe(camera_to_world)

    def capabilities(self) -> Capabilities:
        camera = "SAPIEN renderer (Vulkan) depth and labels" if self._native else "open3d ray-cast depth and labels"
        return Capabilities(name="sapien", notes=f"{camera}; PhysX (CPU) rigid bodies")

    # ------------------------------------------------------------------------------------- state
    def _require_scene(self) -> SceneSpec:
        if self._scene is None or self._sapien is None:
            raise RuntimeError("call reset(scene) first")
        return self._scene

    @staticmethod
    def _body_state(pose: sapien.Pose, lin: Any, ang: Any) -> _BodyState:
        return _BodyState(
            tuple(float(v) for v in pose.p),  # type: ignore[arg-type]
            tuple(float(v) for v in pose.q),  # type: ignore[arg-type]
            tuple(float(v) for v in lin),  # type: ignore[arg-type]
            tuple(float(v) for v in ang),  # type: ignore[arg-type]
        )

    def object_poses(self) -> dict[int, NDArray[np.float64]]:
        """Object-frame poses (``ObjectSpec`` convention) of every object still in the workspace."""
        return {oid: _matrix(obj.entity.pose) for oid, obj in self._objects.items()}

    @property
    def _time_step_s(self) -> float:
        return self.config.time_step_s

    def _physics_step(self) -> None:
        """One time step: finger drive targets move towards the goal at ``FINGER_SPEED_MPS``."""
        assert self._sapien is not None
        dt = self.config.time_step_s
        diff = self._finger_goal_m - self._finger_command_m
        max_step = 2 * FINGER_SPEED_MPS * dt  # both fingers move: the opening changes twice as fast
        if diff != 0.0:
            if abs(diff) <= max_step:
                self._finger_command_m = self._finger_goal_m
                self._drive_fingers(0.0)
            else:
                self._finger_command_m += math.copysign(max_step, diff)
                self._drive_fingers(math.copysign(FINGER_SPEED_MPS, diff))
        self._sapien.step()
        self._contact_cache = None

    def _drive_fingers(self, speed: float) -> None:
        """Send the commanded half-opening (and its rate) to both finger drives."""
        self._finger_velocity = speed
        if self._arm is not None:
            self._arm.drive_fingers(self._finger_command_m, speed)
            return
        for joint in self._joints:
            joint.set_drive_target(self._finger_command_m / 2)
            joint.set_drive_velocity_target(speed)

    def step(self, seconds: float) -> None:
        """Advance physics by ``seconds`` rounded to whole time steps."""
        self._require_scene()
        for _ in range(max(0, round(seconds / self.config.time_step_s))):
            self._physics_step()

    def remove_object(self, object_id: int) -> None:
        """Take the object's actor out of the scene; a snapshot taken before brings it back."""
        obj = self._objects.pop(object_id, None)
        if obj is None:
            raise KeyError(f"object {object_id} is not in the workspace")
        assert self._sapien is not None
        # PhysX keeps the last step's contacts, which would then point at a deleted body: keep the others.
        sid = obj.entity.per_scene_id
        self._contact_cache = [c for c in self._contact_points() if sid not in (c[0], c[1])]
        self._ids.pop(sid, None)
        self._sapien.remove_entity(obj.entity)

    def snapshot(self) -> _Snapshot:
        scene = self._require_scene()
        art = self._articulation
        qpos, qvel = (np.zeros(2), np.zeros(2)) if self._arm is not None else (art.get_qpos(), art.get_qvel())
        return _Snapshot(
            owner=self._owner,
            scene=scene,
            objects=tuple(
                (o.id, self._body_state(self._objects[o.id].entity.pose, self._objects[o.id].body.linear_velocity,
                                        self._objects[o.id].body.angular_velocity))
                for o in scene.objects
                if o.id in self._objects
            ),
            palm=self._body_state(art.root_pose, art.root_linear_velocity, art.root_angular_velocity),
            finger_positions=(float(qpos[0]), float(qpos[1])),
            finger_velocities=(float(qvel[0]), float(qvel[1])),
            finger_goal_m=self._finger_goal_m,
            finger_command_m=self._finger_command_m,
            gripper_target=self._gripper_target,
            parked=self._parked,
            contacts=tuple(self._contact_points()),
            arm=self._arm.state() if self._arm is not None else ((), ()),
            arm_target=self._arm.targets() if self._arm is not None else (),
        )

    def restore(self, token: Any) -> None:
        """Rebuild the world in the snapshot's state (objects removed since come back)."""
        if not isinstance(token, _Snapshot) or token.owner != self._owner:
            raise ValueError("not a snapshot of this simulator")
        specs = {o.id: o for o in token.scene.objects}
        self._scene = token.scene
        self._gripper_target = token.gripper_target
        self._finger_goal_m = token.finger_goal_m
        self._finger_command_m = token.finger_command_m
        self._parked = token.parked
        contacts = list(token.contacts)
        self._build_world(token.scene, [(specs[oid], s) for oid, s in token.objects])
        if self._arm is not None:
            self._arm.set_state(token.arm, token.arm_target)
            self._drive_fingers(0.0 if token.finger_goal_m == token.finger_command_m else
                                math.copysign(FINGER_SPEED_MPS, token.finger_goal_m - token.finger_command_m))
            self._contact_cache = contacts
            return
        art = self._articulation
        art.set_root_pose(sapien.Pose(np.array(token.palm.p, np.float32), np.array(token.palm.q, np.float32)))
        art.set_root_linear_velocity(np.array(token.palm.linear_velocity, np.float32))
        art.set_root_angular_velocity(np.array(token.palm.angular_velocity, np.float32))
        art.set_qpos(np.array(token.finger_positions, np.float32))
        art.set_qvel(np.array(token.finger_velocities, np.float32))
        self._drive_fingers(0.0 if token.finger_goal_m == token.finger_command_m else
                            math.copysign(FINGER_SPEED_MPS, token.finger_goal_m - token.finger_command_m))
        self._set_target(np.asarray(token.gripper_target[0]), np.asarray(token.gripper_target[1]))
        self._contact_cache = contacts

    # ------------------------------------------------------------------------------------- gripper
    def gripper_pose(self) -> NDArray[np.float64]:
        """Pose of the gripper frame (origin between the fingertip pads, z = approach)."""
        self._require_scene()
        if self._arm is not None:
            return self._arm.tool_pose()
        return _matrix(self._articulation.root_pose)

    def _opening(self) -> float:
        if self._arm is not None:
            return self._arm.opening()
        return float(np.sum(self._articulation.get_qpos()))

    def _finger_speed(self) -> float:
        if self._arm is not None:
            return self._arm.finger_speed()
        return float(np.abs(self._articulation.get_qvel()).sum())

    def set_gripper(self, opening_m: float) -> float:
        """Drive both fingers to ``opening_m`` (clamped); stop when reached or blocked (<= 0.5 s)."""
        self._require_scene()
        g = self.config.gripper
        top = g.max_opening_m if self._arm is None else min(g.max_opening_m, self._arm.max_opening())
        self._finger_goal_m = float(np.clip(opening_m, 0.0, top))
        return self._wait_for_fingers(self._finger_goal_m)

    def _set_target(self, pos: NDArray[np.float64], quat: NDArray[np.float64],
                    velocity: NDArray[np.float64] | None = None, spin: NDArray[np.float64] | None = None) -> None:
        self._gripper_target = (tuple(float(v) for v in pos), tuple(float(v) for v in quat))
        t = pose_matrix(pos, quat)
        self._drive.set_drive_target(_sapien_pose(t))
        zero = np.zeros(3, dtype=np.float32)
        self._drive.set_drive_velocity_target(
            zero if velocity is None else velocity.astype(np.float32), zero if spin is None else spin.astype(np.float32)
        )

    def _teleport_gripper(self, pose: NDArray[np.float64]) -> None:
        if self._arm is not None:
            self._arm.place(pose, self._require_scene().shelf, "the gripper pose")
            return
        art = self._articulation
        art.set_root_pose(_sapien_pose(pose))
        art.set_root_linear_velocity(np.zeros(3, dtype=np.float32))
        art.set_root_angular_velocity(np.zeros(3, dtype=np.float32))
        self._set_target(pose[:3, 3], matrix_to_quat(pose[:3, :3]))

    def _track(self, target: PathTarget) -> None:
        if self._arm is not None:
            self._arm.track(target.position, target.quat_xyzw)
            return
        self._set_target(target.position, target.quat_xyzw, target.velocity, target.spin)

    def _end_path(self, position: NDArray[np.float64], quat_xyzw: NDArray[np.float64]) -> None:
        if self._arm is not None:
            self._arm.track(position, quat_xyzw)
            return
        self._set_target(position, quat_xyzw)  # hold still there: zero velocity target

    def _gripper_boxes(self, pose: NDArray[np.float64], inflate: float) -> list[tuple[Any, Any, Any]]:
        """World (centre, rotation, half extents + inflate) of palm and fingers at ``pose``."""
        return [
            (pose[:3, 3] + pose[:3, :3] @ c, pose[:3, :3], h + inflate)
            for c, h in self.config.gripper.boxes(self._opening())
        ]

    def _obstacles(self, with_objects: bool) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """World bounding boxes of the shelf boards and (optionally) every object part."""
        cs, rs, hs = [self._shelf_boxes[0]], [self._shelf_boxes[1]], [self._shelf_boxes[2]]
        if with_objects:
            for obj in self._objects.values():
                t = _matrix(obj.entity.pose)
                c, r, h = obj.boxes
                cs.append(c @ t[:3, :3].T + t[:3, 3])
                rs.append(np.einsum("ij,njk->nik", t[:3, :3], r))
                hs.append(h)
        return np.concatenate(cs), np.concatenate(rs), np.concatenate(hs)

    def _collides(self, pose: NDArray[np.float64], clearance: float, with_objects: bool) -> bool:
        """Whether the gripper at ``pose``, grown by ``clearance``, overlaps an obstacle (bounding boxes). With
        an arm: also whether the robot cannot reach ``pose`` without touching the shelf (its own check)."""
        if self._arm is not None:
            reach = self._arm.robot.ik(pose @ self._arm.tool_inv, self._require_scene().shelf)
            if not reach.reachable:
                return True
        cb, rb, hb = self._obstacles(with_objects)
        return any(bool(np.any(boxes_overlap(cb, rb, hb, c, r, h, margin=1e-9)))
                   for c, r, h in self._gripper_boxes(pose, clearance))

    # ------------------------------------------------------------------------------------- contacts
    def _contact_points(self) -> list[_ContactPoint]:
        """The last step's touching points between known bodies (read from PhysX once per step)."""
        assert self._sapien is not None
        if self._contact_cache is not None:
            return self._contact_cache
        dt = self.config.time_step_s
        out: list[_ContactPoint] = []
        for c in self._sapien.physx_system.get_contacts():
            ea, eb = c.bodies[0].entity.per_scene_id, c.bodies[1].entity.per_scene_id
            a, b = self._ids.get(ea), self._ids.get(eb)
            if a is None or b is None:
                continue
            for pt in c.points:
                if pt.separation > CONTACT_DISTANCE_M:
                    continue
                force = abs(float(np.dot(pt.impulse, pt.normal))) / dt
                x, y, z = (float(v) for v in pt.position)
                out.append((ea, eb, a, b, (x, y, z), force))
        self._contact_cache = out
        return out

    def contacts(self) -> list[Contact]:
        """Contacts of the last physics step between the gripper, objects and the shelf."""
        self._require_scene()
        out = []
        for _, _, a, b, pos, force in self._contact_points():
            if a == b == GRIPPER_ID:
                continue
            out.append(Contact(body_a=a, body_b=b, position_m=pos, normal_force_n=force))
        return out

    def held_object(self) -> int | None:
        """The object touching both fingers (the most firmly gripped one if several do)."""
        self._require_scene()
        touching: list[dict[int, float]] = [{}, {}]
        for ea, eb, a, b, _, force in self._contact_points():
            for finger_entity, other_entity, other in ((ea, eb, b), (eb, ea, a)):
                if finger_entity in self._fingers and other >= 0 and other_entity not in self._fingers:
                    side = self._fingers.index(finger_entity)
                    touching[side][other] = touching[side].get(other, 0.0) + force
        both = [(min(touching[0][oid], touching[1][oid]), oid) for oid in touching[0].keys() & touching[1].keys()]
        return max(both)[1] if both else None


