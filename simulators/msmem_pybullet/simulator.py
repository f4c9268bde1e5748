"""PyBullet implementation of ``Simulator``: rigid-body shelf scenes, a floating parallel-jaw gripper and a
depth + semantic camera rendered with TinyRenderer (CPU, headless).

Design notes:
- Each instance owns its own ``p.DIRECT`` client and passes ``physicsClientId`` on every call, so
  several simulators in one process do not interfere.
- Every object is one multibody with a compound collision shape made from its class's parts; its
  inertial frame sits at the parts' volume centroid and poses are converted back to the object frame
  of ``ObjectSpec`` at the boundary. TinyRenderer draws collision shapes, so no visual shapes are made.
- The gripper is a palm base with two prismatic fingers; a fixed constraint to the world drives the
  base (objects push back), position-controlled motors with ``finger_force_n`` drive the fingers.
- ``snapshot`` records the full state in plain data; ``restore`` rebuilds the world from it. Rebuilding
  brings back removed objects and discards solver caches, so restoring a snapshot and repeating the
  same calls reproduces the same result bit for bit.
"""

from __future__ import annotations

import contextlib
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pybullet as p
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.errors import UserError
from msmem_core.interfaces import GRIPPER_ID, SHELF_ID, Capabilities, Contact, Robot
from msmem_core.sim.motion import (
    FINGER_SPEED_MPS,
    PARK_POSITION_M,
    PARK_QUAT_XYZW,
    FloatingGripperSimulator,
    PathTarget,
)
from msmem_core.util.artifacts import atomic_text
from msmem_core.world.camera import CameraConfig, Observation
from msmem_core.world.geometry import matrix_to_quat, pose_matrix
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.meshes import part_mesh_own_frame
from msmem_core.world.meshparts import cache_dir
from msmem_core.world.scene import ObjectClass, ObjectSpec, Part, SceneSpec, ShelfSpec, parts_centroid
from msmem_pybullet.arm import ArmDrive

OBJECT_FRICTION = 0.6
"""Lateral friction of objects (Bullet multiplies the coefficients of the two bodies in contact)."""
GRIPPER_MAX_FORCE_N = 200.0
"""Force (and torque, N m) limit of the constraint that drives the gripper base."""
FINGER_MASS_KG = 0.05
SOLVER_ITERATIONS = 200
"""More than PyBullet's default 50: two 40 N fingers squeezing a light object otherwise sink ~3 mm in."""
CONTACT_DISTANCE_M = 1e-3
"""Manifold points farther apart than this are not reported as contacts."""


class PyBulletConfig(BaseModel):
    """Configuration of the PyBullet backend."""

    model_config = ConfigDict(extra="forbid")

    camera: CameraConfig = CameraConfig()
    gripper: GripperSpec = GripperSpec()
    label_noise: float = Field(0.05, ge=0.0, le=1.0)
    """Probability that, in one view, a visible object is labelled entirely as its confusable class."""
    time_step_s: float = Field(1.0 / 240.0, gt=0.0, le=0.05)
    settle_s: float = Field(1.0, ge=0.0)
    """Simulated time objects settle for after ``reset``."""
    seed: int = 0
    """Seed of every random choice of the backend (segmentation noise)."""


@dataclass(frozen=True)
class _BodyState:
    """Inertial-frame pose and velocity of one body (what PyBullet reports and resets)."""

    position: tuple[float, float, float]
    orientation: tuple[float, float, float, float]
    linear_velocity: tuple[float, float, float]
    angular_velocity: tuple[float, float, float]


@dataclass(frozen=True)
class _Snapshot:
    """Everything ``restore`` needs to rebuild the world exactly."""

    client: int
    scene: SceneSpec
    objects: tuple[tuple[int, _BodyState], ...]
    """Objects present at snapshot time, in scene order."""
    gripper: _BodyState
    finger_positions: tuple[float, float]
    finger_velocities: tuple[float, float]
    finger_target_m: float
    gripper_target: tuple[tuple[float, float, float], tuple[float, float, float, float]]
    parked: bool
    arm: tuple[tuple[float, float], ...] = ()
    """With an attached robot: position and velocity of each of its movable joints."""
    arm_target: tuple[float, ...] = ()
    """With an attached robot: its arm motors' targets."""


def convex_obj(part: Part) -> Path:
    """An OBJ file of a convex part's vertices (PyBullet builds a convex hull from a GEOM_MESH file),
    written once per vertex set into the mesh cache (``msmem_core.world.meshparts.cache_dir``)."""
    v = np.asarray(part.vertices_m, dtype=np.float64)
    key = hashlib.sha256(v.tobytes()).hexdigest()[:16]
    path = cache_dir() / "pybullet" / f"convex-{key}.obj"
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        hull = part_mesh_own_frame(part)
        atomic_text("".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in hull.vertices)
                    + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in hull.faces), path)
    return path


@dataclass(frozen=True)
class _Object:
    uid: int
    class_id: int
    confusable_id: int | None
    """Class the structured segmentation noise reports instead of ``class_id``."""
    com_m: NDArray[np.float64]
    """Inertial frame origin (parts' volume centroid) in the object frame."""


def _tiny_renderer_projection(cam: CameraConfig) -> list[float]:
    """OpenGL projection (column-major) that makes TinyRenderer's pixels follow ``Observation``'s convention.

    TinyRenderer samples pixel (i, j) at pixel-corner coordinates (u, v) = (i, j + 1) of the projected
    image, where ``Observation.points_world`` assumes pixel centres (i + 0.5, j + 0.5). Moving the
    principal point by (-0.5, +0.5) px removes that half-pixel shift (measured with box edges).
    """
    k = cam.intrinsics
    w, h, n, f = cam.width_px, cam.height_px, cam.near_m, cam.far_m
    cx, cy = k[0, 2] - 0.5, k[1, 2] + 0.5
    proj = np.array(
        [
            [2 * k[0, 0] / w, 0.0, 1 - 2 * cx / w, 0.0],
            [0.0, 2 * k[1, 1] / h, 2 * cy / h - 1, 0.0],
            [0.0, 0.0, -(f + n) / (f - n), -2 * f * n / (f - n)],
            [0.0, 0.0, -1.0, 0.0],
        ]
    )
    return proj.T.reshape(-1).tolist()


class PyBulletSimulator(FloatingGripperSimulator):
    """Shelf scenes in PyBullet (``p.DIRECT``; one physics client per instance)."""

    def __init__(self, config: PyBulletConfig | None = None, **kwargs: Any) -> None:
        if config is not None and kwargs:
            raise UserError("pass either a PyBulletConfig or keyword options, not both")
        self.config = config if config is not None else PyBulletConfig(**kwargs)
        self._client = p.connect(p.DIRECT)
        if self._client < 0:
            raise RuntimeError("pybullet could not open a DIRECT physics client")
        self._rng = np.random.default_rng(self.config.seed)
        cam = self.config.camera
        self._projection = _tiny_renderer_projection(cam)
        g = self.config.gripper
        self._palm_centre = np.array([0.0, 0.0, -g.finger_length_m - g.palm_depth_m / 2])
        self._scene: SceneSpec | None = None
        self._objects: dict[int, _Object] = {}
        self._shelf_uids: set[int] = set()
        self._gripper_uid = -1
        self._constraint = -1
        self._gripper_target: tuple[tuple[float, float, float], tuple[float, float, float, float]] = (
            PARK_POSITION_M,
            PARK_QUAT_XYZW,
        )
        self._finger_target_m = g.max_opening_m
        self._parked = True
        self._arm: ArmDrive | None = None

    def attach_robot(self, robot: Robot) -> None:
        """From the next ``reset`` on, the robot's arm (its URDF, at its base pose) replaces the floating
        gripper and is driven by joint control (``msmem_pybullet.arm``). A robot without an arm changes
        nothing."""
        if robot.arm:
            g = self.config.gripper
            self._arm = ArmDrive(robot, self._client, g.finger_force_n, g.finger_friction)

    def robot_notes(self) -> list[str]:
        return self._arm.take_notes() if self._arm is not None else []

    # ------------------------------------------------------------------------------------- lifecycle
    def reset(self, scene: SceneSpec) -> None:
        """Build the shelf and objects at their poses, park the gripper open, settle for ``settle_s``."""
        self._scene = scene
        self._finger_target_m = self.config.gripper.max_opening_m
        self._gripper_target = (PARK_POSITION_M, PARK_QUAT_XYZW)
        self._parked = True
        self._build_world(scene, [(o, None) for o in scene.objects])
        if self._arm is None:
            q = self._finger_target_m / 2
            for j in (0, 1):
                p.resetJointState(self._gripper_uid, j, q, 0.0, physicsClientId=self._client)
        self._drive_fingers()
        self.step(self.config.settle_s)

    def close(self) -> None:
        """Disconnect the physics client (idempotent)."""
        if self._client >= 0:
            with contextlib.suppress(p.error):
                p.disconnect(physicsClientId=self._client)
            self._client = -1

    def __del__(self) -> None:
        with contextlib.suppress(Exception):  # the interpreter may be shutting down
            self.close()

    def capabilities(self) -> Capabilities:
        return Capabilities(name="pybullet", notes="TinyRenderer (CPU) depth and labels; Bullet rigid bodies")

    # ------------------------------------------------------------------------------------- building
    def _build_world(self, scene: SceneSpec, objects: Sequence[tuple[ObjectSpec, _BodyState | None]]) -> None:
        """Reset the physics world and create shelf, gripper and objects (``None`` state: the spec pose)."""
        c = self._client
        p.resetSimulation(physicsClientId=c)
        p.setPhysicsEngineParameter(
            fixedTimeStep=self.config.time_step_s,
            numSolverIterations=SOLVER_ITERATIONS,
            deterministicOverlappingPairs=1,
            physicsClientId=c,
        )
        p.setGravity(0.0, 0.0, -9.81, physicsClientId=c)
        self._shelf_uids = self._build_shelf(scene.shelf)
        if self._arm is not None:
            self._gripper_uid = self._arm.build()
        else:
            self._build_gripper()
        self._objects = {}
        for spec, state in objects:
            self._objects[spec.id] = self._build_object(spec, state)

    def _build_shelf(self, shelf: ShelfSpec) -> set[int]:
        uids = set()
        for centre, half in shelf.boards():
            shape = p.createCollisionShape(p.GEOM_BOX, halfExtents=half.tolist(), physicsClientId=self._client)
            uid = p.createMultiBody(0.0, shape, -1, basePosition=centre.tolist(), physicsClientId=self._client)
            p.changeDynamics(uid, -1, lateralFriction=shelf.friction, physicsClientId=self._client)
            uids.add(uid)
        return uids

    def _build_object(self, spec: ObjectSpec, state: _BodyState | None) -> _Object:
        cls: ObjectClass = spec.object_class
        c = self._client
        kinds = [q.kind for q in cls.parts]
        geom = {"box": p.GEOM_BOX, "cylinder": p.GEOM_CYLINDER, "convex": p.GEOM_MESH}
        shape = p.createCollisionShapeArray(
            shapeTypes=[geom[k] for k in kinds],
            halfExtents=[[s / 2 for s in q.size_m] if q.kind == "box" else [0.0, 0.0, 0.0] for q in cls.parts],
            radii=[q.size_m[0] if q.kind == "cylinder" else 0.0 for q in cls.parts],
            lengths=[q.size_m[1] if q.kind == "cylinder" else 0.0 for q in cls.parts],
            fileNames=[str(convex_obj(q)) if q.kind == "convex" else "" for q in cls.parts],
            meshScales=[[1.0, 1.0, 1.0] for _ in cls.parts],
            collisionFramePositions=[list(q.position_m) for q in cls.parts],
            collisionFrameOrientations=[list(q.quat_xyzw) for q in cls.parts],
            physicsClientId=c,
        )
        com = parts_centroid(cls.parts)
        uid = p.createMultiBody(
            cls.mass_kg,
            shape,
            -1,
            basePosition=list(spec.position_m),
            baseOrientation=list(spec.quat_xyzw),
            baseInertialFramePosition=com.tolist(),
            physicsClientId=c,
        )
        p.changeDynamics(
            uid, -1, lateralFriction=OBJECT_FRICTION, spinningFriction=1e-3, rollingFriction=1e-4, physicsClientId=c
        )
        if state is not None:
            self._set_body_state(uid, state)
        return _Object(uid, cls.class_id, cls.confusable_id, com)

    def _build_gripper(self) -> None:
        """Palm base (its frame is the gripper frame) with two prismatic fingers along gripper x."""
        g = self.config.gripper
        c = self._client
        _, finger_half = g.boxes(0.0)[0]
        _, palm_half = g.boxes(0.0)[2]
        palm = p.createCollisionShape(
            p.GEOM_BOX,
            halfExtents=palm_half.tolist(),
            collisionFramePosition=self._palm_centre.tolist(),
            physicsClientId=c,
        )
        finger = p.createCollisionShape(p.GEOM_BOX, halfExtents=finger_half.tolist(), physicsClientId=c)
        pos, orn = self._gripper_target
        fz = -g.finger_length_m / 2
        # A finger's joint position q is half the opening: its centre sits at x = -+(q + thickness/2).
        self._gripper_uid = p.createMultiBody(
            g.mass_kg,
            palm,
            -1,
            basePosition=list(pos),
            baseOrientation=list(orn),
            baseInertialFramePosition=self._palm_centre.tolist(),
            linkMasses=[FINGER_MASS_KG, FINGER_MASS_KG],
            linkCollisionShapeIndices=[finger, finger],
            linkVisualShapeIndices=[-1, -1],
            linkPositions=[[-g.finger_thickness_m / 2, 0.0, fz], [g.finger_thickness_m / 2, 0.0, fz]],
            linkOrientations=[[0.0, 0.0, 0.0, 1.0]] * 2,
            linkInertialFramePositions=[[0.0, 0.0, 0.0]] * 2,
            linkInertialFrameOrientations=[[0.0, 0.0, 0.0, 1.0]] * 2,
            linkParentIndices=[0, 0],
            linkJointTypes=[p.JOINT_PRISMATIC, p.JOINT_PRISMATIC],
            linkJointAxis=[[-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
            physicsClientId=c,
        )
        uid = self._gripper_uid
        for link in (-1, 0, 1):
            p.changeDynamics(uid, link, lateralFriction=g.finger_friction, physicsClientId=c)
        for j in (0, 1):
            p.changeDynamics(uid, j, jointLowerLimit=0.0, jointUpperLimit=g.max_opening_m / 2, physicsClientId=c)
        self._constraint = p.createConstraint(
            uid,
            -1,
            -1,
            -1,
            p.JOINT_FIXED,
            [0.0, 0.0, 0.0],
            parentFramePosition=(-self._palm_centre).tolist(),
            childFramePosition=list(pos),
            childFrameOrientation=list(orn),
            physicsClientId=c,
        )
        p.changeConstraint(self._constraint, maxForce=GRIPPER_MAX_FORCE_N, physicsClientId=c)

    # ------------------------------------------------------------------------------------- state
    def _body_state(self, uid: int) -> _BodyState:
        pos, orn = p.getBasePositionAndOrientation(uid, physicsClientId=self._client)
        lin, ang = p.getBaseVelocity(uid, physicsClientId=self._client)
        return _BodyState(tuple(pos), tuple(orn), tuple(lin), tuple(ang))

    def _set_body_state(self, uid: int, s: _BodyState) -> None:
        p.resetBasePositionAndOrientation(uid, s.position, s.orientation, physicsClientId=self._client)
        p.resetBaseVelocity(uid, s.linear_velocity, s.angular_velocity, physicsClientId=self._client)

    def _require_scene(self) -> SceneSpec:
        if self._scene is None:
            raise RuntimeError("call reset(scene) first")
        return self._scene

    def object_poses(self) -> dict[int, NDArray[np.float64]]:
        """Object-frame poses (``ObjectSpec`` convention) of every object still in the workspace."""
        out = {}
        for oid, obj in self._objects.items():
            pos, orn = p.getBasePositionAndOrientation(obj.uid, physicsClientId=self._client)
            t = pose_matrix(pos, orn)
            t[:3, 3] -= t[:3, :3] @ obj.com_m
            out[oid] = t
        return out

    @property
    def _time_step_s(self) -> float:
        return self.config.time_step_s

    def _physics_step(self) -> None:
        p.stepSimulation(physicsClientId=self._client)

    def step(self, seconds: float) -> None:
        """Advance physics by ``seconds`` rounded to whole time steps."""
        for _ in range(max(0, round(seconds / self.config.time_step_s))):
            self._physics_step()

    def remove_object(self, object_id: int) -> None:
        """Delete the object's body; a snapshot taken before brings it back."""
        obj = self._objects.pop(object_id, None)
        if obj is None:
            raise KeyError(f"object {object_id} is not in the workspace")
        p.removeBody(obj.uid, physicsClientId=self._client)

    def snapshot(self) -> _Snapshot:
        scene = self._require_scene()
        c, g = self._client, self._gripper_uid
        joints = p.getJointStates(g, self._finger_joints(), physicsClientId=c)
        return _Snapshot(
            client=c,
            scene=scene,
            objects=tuple(
                (o.id, self._body_state(self._objects[o.id].uid)) for o in scene.objects if o.id in self._objects
            ),
            gripper=self._body_state(g),
            finger_positions=(joints[0][0], joints[1][0]),
            finger_velocities=(joints[0][1], joints[1][1]),
            finger_target_m=self._finger_target_m,
            gripper_target=self._gripper_target,
            parked=self._parked,
            arm=self._arm.state() if self._arm is not None else (),
            arm_target=self._arm.targets() if self._arm is not None else (),
        )

    def restore(self, token: Any) -> None:
        """Rebuild the world in the snapshot's state (objects removed since come back)."""
        if not isinstance(token, _Snapshot) or token.client != self._client:
            raise ValueError("not a snapshot of this simulator")
        specs = {o.id: o for o in token.scene.objects}
        self._scene = token.scene
        self._gripper_target = token.gripper_target
        self._finger_target_m = token.finger_target_m
        self._parked = token.parked
        self._build_world(token.scene, [(specs[oid], s) for oid, s in token.objects])
        if self._arm is not None:
            self._arm.set_state(token.arm, token.arm_target, token.finger_target_m)
            p.performCollisionDetection(physicsClientId=self._client)
            return
        self._set_body_state(self._gripper_uid, token.gripper)
        for j in (0, 1):
            p.resetJointState(
                self._gripper_uid,
                j,
                token.finger_positions[j],
                token.finger_velocities[j],
                physicsClientId=self._client,
            )
        self._drive_fingers()
        p.performCollisionDetection(physicsClientId=self._client)

    # ------------------------------------------------------------------------------------- camera
    def observe(self, camera_to_world: NDArray[np.float64]) -> Observation:
        """Render z-depth, labels and object ids from an OpenCV camera-to-world pose."""
        scene = self._require_scene()
        cam = self.config.camera
        c2w = np.asarray(camera_to_world, dtype=np.float64)
        if self._arm is not None:  # the wrist camera takes the view: the arm goes there (and is in the image)
            self._arm.place_camera(c2w, scene.shelf)
            self._parked = True  # the next move starts at its first waypoint, as from the parking pose
        # OpenGL camera axes are OpenCV's with y and z flipped; PyBullet wants column-major matrices.
        view = np.linalg.inv(c2w @ np.diag([1.0, -1.0, -1.0, 1.0]))
        _, _, _, zbuf, seg = p.getCameraImage(
            cam.width_px,
            cam.height_px,
            viewMatrix=view.T.reshape(-1).tolist(),
            projectionMatrix=self._projection,
            renderer=p.ER_TINY_RENDERER,
            physicsClientId=self._client,
        )
        n, f = cam.near_m, cam.far_m
        zbuf = np.asarray(zbuf, dtype=np.float64).reshape(cam.height_px, cam.width_px)
        seg = np.asarray(seg, dtype=np.int64).reshape(cam.height_px, cam.width_px)
        depth = f * n / (f - (f - n) * zbuf)
        depth[depth >= 0.999 * f] = 0.0

        # Lookup tables indexed by body uid + 1 (uid -1 = nothing hit); shelf and gripper stay -1 / 0.
        size = max([self._gripper_uid, *self._shelf_uids, *(o.uid for o in self._objects.values())]) + 2
        id_lut = np.full(size, -1, dtype=np.int32)
        label_lut = np.zeros(size, dtype=np.int16)
        for oid, obj in self._objects.items():
            id_lut[obj.uid + 1] = oid
            label_lut[obj.uid + 1] = obj.class_id
        if self.config.label_noise > 0.0:
            # Structured noise: a visible object is relabelled as a whole for this view, never per pixel.
            hit = set(np.unique(seg).tolist())
            visible = sorted(oid for oid, obj in self._objects.items() if obj.uid in hit)
            flips = self._rng.random(len(visible)) < self.config.label_noise
            for oid, flip in zip(visible, flips, strict=True):
                obj = self._objects[oid]
                if flip and obj.confusable_id is not None:
                    label_lut[obj.uid + 1] = obj.confusable_id
        object_ids = id_lut[seg + 1]
        labels = label_lut[seg + 1]
        return Observation(
            depth=depth.astype(np.float32),
            labels=labels,
            intrinsics=cam.intrinsics,
            camera_to_world=c2w.copy(),
            object_ids=object_ids,
        )

    # ------------------------------------------------------------------------------------- gripper
    def gripper_pose(self) -> NDArray[np.float64]:
        """Pose of the gripper frame (origin between the fingertip pads, z = approach)."""
        if self._arm is not None:
            return self._arm.tool_pose()
        pos, orn = p.getBasePositionAndOrientation(self._gripper_uid, physicsClientId=self._client)
        t = pose_matrix(pos, orn)
        t[:3, 3] -= t[:3, :3] @ self._palm_centre
        return t

    def _finger_joints(self) -> list[int]:
        return self._arm.finger_links() if self._arm is not None else [0, 1]

    def _opening(self) -> float:
        if self._arm is not None:
            return self._arm.opening()
        joints = p.getJointStates(self._gripper_uid, [0, 1], physicsClientId=self._client)
        return float(joints[0][0] + joints[1][0])

    def _finger_speed(self) -> float:
        if self._arm is not None:
            return self._arm.finger_speed()
        joints = p.getJointStates(self._gripper_uid, [0, 1], physicsClientId=self._client)
        return abs(joints[0][1]) + abs(joints[1][1])

    def _drive_fingers(self) -> None:
        if self._arm is not None:
            self._arm.set_fingers(self._finger_target_m)
            return
        g = self.config.gripper
        for j in (0, 1):
            p.setJointMotorControl2(
                self._gripper_uid,
                j,
                p.POSITION_CONTROL,
                targetPosition=self._finger_target_m / 2,
                force=g.finger_force_n,
                maxVelocity=FINGER_SPEED_MPS,
                physicsClientId=self._client,
            )

    def set_gripper(self, opening_m: float) -> float:
        """Drive both fingers to ``opening_m`` (clamped); stop when reached or blocked (<= 0.5 s)."""
        self._require_scene()
        g = self.config.gripper
        top = g.max_opening_m if self._arm is None else min(g.max_opening_m, self._arm.max_opening())
        self._finger_target_m = float(np.clip(opening_m, 0.0, top))
        self._drive_fingers()
        return self._wait_for_fingers(self._finger_target_m)

    def _set_target(self, pos: NDArray[np.float64], quat: NDArray[np.float64]) -> None:
        self._gripper_target = (tuple(pos.tolist()), tuple(quat.tolist()))
        p.changeConstraint(
            self._constraint,
            jointChildPivot=pos.tolist(),
            jointChildFrameOrientation=quat.tolist(),
            maxForce=GRIPPER_MAX_FORCE_N,
            physicsClientId=self._client,
        )

    def _teleport_gripper(self, pose: NDArray[np.float64]) -> None:
        if self._arm is not None:
            self._arm.place(pose, self._require_scene().shelf, "the gripper pose")
            return
        pos = pose[:3, 3] + pose[:3, :3] @ self._palm_centre
        quat = matrix_to_quat(pose[:3, :3])
        p.resetBasePositionAndOrientation(self._gripper_uid, pos.tolist(), quat.tolist(), physicsClientId=self._client)
        p.resetBaseVelocity(self._gripper_uid, [0.0] * 3, [0.0] * 3, physicsClientId=self._client)
        self._set_target(pose[:3, 3], quat)

    def _track(self, target: PathTarget) -> None:
        if self._arm is not None:
            self._arm.track(target.position, target.quat_xyzw)
            return
        self._set_target(target.position, target.quat_xyzw)

    def _clearance(self, uids: Sequence[int], cap: float) -> float:
        """Distance from the gripper to the nearest of ``uids``, capped at ``cap``."""
        best = cap
        for uid in uids:
            for pt in p.getClosestPoints(self._gripper_uid, uid, cap, physicsClientId=self._client):
                best = min(best, pt[8])
        return best

    def _collides(self, pose: NDArray[np.float64], clearance: float, with_objects: bool) -> bool:
        """Whether the gripper, teleported to ``pose``, is within ``clearance`` of the shelf (or anything)."""
        uids = [*self._shelf_uids, *(o.uid for o in self._objects.values())] if with_objects else list(self._shelf_uids)
        if self._arm is not None:
            reach = self._arm.robot.ik(pose @ self._arm.tool_inv, self._require_scene().shelf)
            if not reach.reachable or reach.joints is None:
                return True
            self._arm.set_joints(np.asarray(reach.joints))
            return self._arm.touching(uids, clearance)
        self._teleport_gripper(pose)
        return self._clearance(uids, clearance) < clearance

    # ------------------------------------------------------------------------------------- contacts
    def _ids_by_uid(self) -> dict[int, int]:
        """Body uid -> object id, ``GRIPPER_ID`` or ``SHELF_ID``."""
        ids = {obj.uid: oid for oid, obj in self._objects.items()}
        ids.update({uid: SHELF_ID for uid in self._shelf_uids})
        ids[self._gripper_uid] = GRIPPER_ID
        return ids

    def contacts(self) -> list[Contact]:
        """Contacts of the last physics step between the gripper, objects and the shelf."""
        ids = self._ids_by_uid()
        out = []
        for pt in p.getContactPoints(physicsClientId=self._client):
            a, b = ids.get(pt[1]), ids.get(pt[2])
            if pt[8] > CONTACT_DISTANCE_M or a is None or b is None:
                continue
            x, y, z = (0.5 * (np.asarray(pt[5]) + np.asarray(pt[6]))).tolist()
            out.append(Contact(body_a=a, body_b=b, position_m=(x, y, z), normal_force_n=float(pt[9])))
        return out

    def held_object(self) -> int | None:
        """The object touching both fingers (the most firmly gripped one if several do)."""
        ids = {obj.uid: oid for oid, obj in self._objects.items()}
        touching: list[dict[int, float]] = [{}, {}]
        for k, finger in enumerate(self._finger_joints()):
            for pt in p.getContactPoints(bodyA=self._gripper_uid, linkIndexA=finger, physicsClientId=self._client):
                oid = ids.get(pt[2])
                if pt[8] <= CONTACT_DISTANCE_M and oid is not None:
                    touching[k][oid] = touching[k].get(oid, 0.0) + pt[9]
        both = [(min(touching[0][oid], touching[1][oid]), oid) for oid in touching[0].keys() & touching[1].keys()]
        return max(both)[1] if both else None
