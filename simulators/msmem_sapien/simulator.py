"""SAPIEN 3 implementation of ``Simulator``: PhysX (CPU) rigid-body shelf scenes, a floating parallel-jaw
gripper and a depth + semantic camera, with the same semantics as the PyBullet reference backend.

Design notes:
- Each instance owns its own ``sapien.Scene`` with a ``PhysxCpuSystem`` (single-threaded, enhanced
  determinism). SAPIEN poses are (position, quaternion **wxyz**); core uses xyzw and 4x4 matrices,
  converted at this boundary only.
- Every object is one dynamic actor whose entity frame *is* the ``ObjectSpec`` object frame; its
  shapes are the class's parts (PhysX cylinders lie along x, so cylinder parts get a quarter turn),
  its mass centre is the parts' volume centroid and its inertia that of the parts' bounding box
  (what Bullet computes for compound shapes), so both backends move objects alike.
- Friction: Bullet multiplies the coefficients of two bodies in contact, PhysX averages them. The
  materials are chosen so that every pair involving an object gets Bullet's product (see
  ``_physx_frictions``).
- The gripper is an articulation: a free palm link (its frame is the gripper frame) and two prismatic
  fingers driven by force-limited joint drives (``finger_force_n``) whose targets move at
  ``FINGER_SPEED_MPS``. A force-limited D6 drive to the world moves the palm, so objects push back
  (as Bullet's fixed constraint with ``maxForce``). The gripper ignores gravity (a floating gripper).
- Camera: SAPIEN's own renderer (``Position`` picture -> z-depth, per-actor ``Segmentation`` -> ids and
  classes) when a Vulkan device with SAPIEN's required features exists (on a CPU: Mesa >= 24 lavapipe,
  see ``setup_lavapipe.sh``); otherwise open3d ray casting over the same part meshes that ground truth
  voxelises. Both put pixel centres at (u + 0.5, v + 0.5) and clip at the near plane.
- ``snapshot`` records the full state in plain data; ``restore`` rebuilds the scene from it, which brings
  back removed objects and discards solver caches, so restoring and repeating the same calls
  reproduces the same result bit for bit.
"""

from __future__ import annotations

import functools
import itertools
import logging
import math
import os
import sys
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import open3d as o3d
import trimesh
from numpy.typing import NDArray

with warnings.catch_warnings():  # "Failed to find system libvulkan": SAPIEN then uses its bundled loader
    warnings.simplefilter("ignore", UserWarning)
    import sapien

from msmem_core.errors import UserError
from msmem_core.interfaces import GRIPPER_ID, SHELF_ID, Capabilities, Contact
from msmem_core.sim.motion import (
    FINGER_SPEED_MPS,
    PARK_POSITION_M,
    PARK_QUAT_XYZW,
    FloatingGripperSimulator,
    PathTarget,
)
from msmem_core.world.camera import Observation
from msmem_core.world.geometry import matrix_to_quat, pose_matrix, quat_to_matrix
from msmem_core.world.meshes import class_mesh, part_mesh_local, shelf_meshes
from msmem_core.world.scene import ObjectClass, ObjectSpec, Part, SceneSpec, ShelfSpec, object_class, parts_centroid
from msmem_sapien.config import SapienConfig

log = logging.getLogger(__name__)

OBJECT_FRICTION = 0.6
"""Friction coefficient of objects, as in the PyBullet backend (pairs get Bullet's products)."""
GRIPPER_MAX_FORCE_N = 200.0
"""Force (N, per axis) and torque (N m) limit of the drive that moves the palm (Bullet: constraint maxForce)."""
GRIPPER_STIFFNESS = 1e5
"""N/m of the palm drive (2 mm of deflection at the force limit)."""
GRIPPER_DAMPING = 2e3
GRIPPER_ROT_STIFFNESS = 1e3
"""N m/rad of the palm's orientation drive."""
GRIPPER_ROT_DAMPING = 20.0
FINGER_MASS_KG = 0.05
FINGER_STIFFNESS = 1e4
"""N/m of a finger drive; it saturates at ``finger_force_n`` once blocked 4 mm short of its target."""
FINGER_DAMPING = 50.0
CONTACT_DISTANCE_M = 1e-3
"""Contact points farther apart than this are not reported as contacts."""
_GRIPPER_GROUPS = [1, 1, 1, 0]
"""Collision groups of gripper shapes: they collide with everything but each other (shared word 2)."""
_CYLINDER_TO_Z = quat_to_matrix((0.0, -math.sqrt(0.5), 0.0, math.sqrt(0.5)))
"""Rotation taking PhysX's cylinder axis (x) to the part's z axis (a quarter turn about y)."""
LAVAPIPE_ENV = "MSMEM_LAVAPIPE_DIR"
"""Folder with ``lvp_icd.json`` made by ``setup_lavapipe.sh`` (default: ``<sys.prefix>/lavapipe``)."""


# ------------------------------------------------------------------------------------ conversions
def _sapien_pose(t: NDArray[np.float64]) -> sapien.Pose:
    """A 4x4 pose as ``sapien.Pose`` (wxyz quaternion)."""
    x, y, z, w = matrix_to_quat(t[:3, :3])
    return sapien.Pose(np.asarray(t[:3, 3], dtype=np.float32), np.array([w, x, y, z], dtype=np.float32))


def _matrix(pose: sapien.Pose) -> NDArray[np.float64]:
    """A ``sapien.Pose`` as a 4x4 matrix (float64)."""
    w, x, y, z = np.asarray(pose.q, dtype=np.float64)
    return pose_matrix(np.asarray(pose.p, dtype=np.float64), (x, y, z, w))


def _physx_frictions(obj: float, shelf: float, finger: float) -> tuple[float, float, float]:
    """Material coefficients under PhysX's average rule that give every pair involving an object
    Bullet's product rule: ``(m_o + m_o)/2 = o*o``, ``(m_o + m_s)/2 = o*s``, ``(m_o + m_f)/2 = o*f``
    (the finger-shelf pair, which the skills never rely on, is then approximate)."""
    m_o = obj * obj
    return m_o, max(0.0, 2 * obj * shelf - m_o), max(0.0, 2 * obj * finger - m_o)


def _part_box(part: Part) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(centre, rotation, half extents) in the object frame of a part's bounding box."""
    rot = quat_to_matrix(part.quat_xyzw)
    if part.kind == "box":
        half = np.asarray(part.size_m, dtype=np.float64) / 2
    else:
        half = np.array([part.size_m[0], part.size_m[0], part.size_m[1] / 2])
    return np.asarray(part.position_m, dtype=np.float64), rot, half


def _bounding_box_inertia(parts: Sequence[Part], mass: float) -> NDArray[np.float64]:
    """Principal moments of a solid box spanning the parts' axis-aligned bounds (Bullet's compound rule)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for part in parts:
        c, r, h = _part_box(part)
        ext = np.abs(r) @ h
        lo, hi = np.minimum(lo, c - ext), np.maximum(hi, c + ext)
    x, y, z = hi - lo
    return mass / 12.0 * np.array([y * y + z * z, x * x + z * z, x * x + y * y])


def _box_inertia(half: NDArray[np.float64], mass: float) -> NDArray[np.float64]:
    x, y, z = 2 * half
    return mass / 12.0 * np.array([y * y + z * z, x * x + z * z, x * x + y * y])


def _obb_overlap(
    ca: NDArray[np.float64], ra: NDArray[np.float64], ha: NDArray[np.float64],
    cb: NDArray[np.float64], rb: NDArray[np.float64], hb: NDArray[np.float64],
) -> NDArray[np.bool_]:
    """Separating-axis test of one oriented box A (centre, rotation columns = axes, half extents)
    against N boxes B (``cb`` (N, 3), ``rb`` (N, 3, 3), ``hb`` (N, 3)); True where they overlap."""
    a_axes = np.broadcast_to(ra.T, (len(cb), 3, 3))
    b_axes = rb.transpose(0, 2, 1)
    cross = np.cross(a_axes[:, :, None, :], b_axes[:, None, :, :]).reshape(len(cb), 9, 3)
    axes = np.concatenate([a_axes, b_axes, cross], axis=1)  # (N, 15, 3)
    dist = np.abs(np.einsum("nkj,nj->nk", axes, cb - ca))
    r_a = np.einsum("nkj,ji,i->nk", np.abs(axes @ ra), np.eye(3), ha)
    r_b = np.einsum("nki,ni->nk", np.abs(axes @ rb), hb)
    return ~np.any(dist > r_a + r_b + 1e-9, axis=1)


# ------------------------------------------------------------------------------------ native camera
_NATIVE: tuple[bool, str] | None = None
"""Whether SAPIEN's renderer works in this process, and why (probed once: a failed Vulkan start sticks)."""
_KEEPALIVE: list[Any] = []


def lavapipe_icd() -> Path | None:
    """The ICD file ``setup_lavapipe.sh`` wrote, if any (``$MSMEM_LAVAPIPE_DIR`` or ``<sys.prefix>/lavapipe``)."""
    folder = Path(os.environ.get(LAVAPIPE_ENV) or Path(sys.prefix) / "lavapipe")
    icd = folder / "lvp_icd.json"
    return icd if icd.is_file() else None


def native_renderer() -> tuple[bool, str]:
    """Probe SAPIEN's renderer once per process: (available, what was found or why it failed).

    When ``VK_ICD_FILENAMES`` is unset and ``setup_lavapipe.sh`` has installed its private lavapipe,
    point the Vulkan loader at it first (the loader reads the variable when SAPIEN starts Vulkan).
    """
    global _NATIVE
    if _NATIVE is None:
        icd = lavapipe_icd()
        if icd is not None and not os.environ.get("VK_ICD_FILENAMES"):
            os.environ["VK_ICD_FILENAMES"] = str(icd)
        try:
            system = sapien.render.RenderSystem()
            _NATIVE = (True, f"SAPIEN renderer on {system.device.name}")
            # SAPIEN drops its compiled shader pipelines when the last render system goes; compiling
            # them takes seconds on lavapipe, so one system lives as long as the process.
            _KEEPALIVE.append(system)
        except RuntimeError as e:
            _NATIVE = (False, f"SAPIEN renderer unavailable ({e})")
    return _NATIVE


@functools.cache
def _class_soup(class_name: str) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Vertices and faces of a class's part meshes in its object frame (what ground truth voxelises)."""
    mesh = class_mesh(class_name)
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)


_LOGGED_CAMERA: set[str] = set()


def _log_camera_once(path: str, detail: str) -> None:
    if path not in _LOGGED_CAMERA:
        _LOGGED_CAMERA.add(path)
        log.info("SAPIEN backend camera: %s (%s)", path, detail)


# ------------------------------------------------------------------------------------ state records
@dataclass(frozen=True)
class _BodyState:
    """Entity-frame pose (position, wxyz quaternion; float32 as PhysX holds it) and velocity of a body."""

    p: tuple[float, float, float]
    q: tuple[float, float, float, float]
    linear_velocity: tuple[float, float, float]
    angular_velocity: tuple[float, float, float]


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


@dataclass
class _Object:
    spec: ObjectSpec
    entity: sapien.Entity
    body: sapien.physx.PhysxRigidDynamicComponent
    class_id: int
    confusable_id: int | None
    """Class the structured segmentation noise reports instead of ``class_id``."""
    boxes: tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
    """Parts' bounding boxes in the object frame: centres (K, 3), rotations (K, 3, 3), halves (K, 3)."""


_OWNER_IDS = itertools.count()


class SapienSimulator(FloatingGripperSimulator):
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

    def _choose_camera(self) -> bool:
        mode = self.config.renderer
        if mode == "raycast":
            _log_camera_once("raycast", "renderer: raycast in config")
            return False
        ok, detail = native_renderer()
        if ok:
            _log_camera_once("native", detail)
            return True
        if mode == "native":
            raise UserError(
                f"simulator 'sapien': renderer 'native' needs a Vulkan device: {detail}. Run "
                "simulators/msmem_sapien/setup_lavapipe.sh (CPU lavapipe) or set renderer: auto / raycast"
            )
        _log_camera_once("raycast", f"{detail}; open3d ray casting over the collision geometry")
        return False

    # ------------------------------------------------------------------------------------- lifecycle
    def reset(self, scene: SceneSpec) -> None:
        """Build the shelf and objects at their poses, park the gripper open, settle for ``settle_s``."""
        g = self.config.gripper
        self._scene = scene
        self._finger_goal_m = self._finger_command_m = g.max_opening_m
        self._gripper_target = (PARK_POSITION_M, PARK_QUAT_XYZW)
        self._parked = True
        self._build_world(scene, [(o, None) for o in scene.objects])
        q = g.max_opening_m / 2
        self._articulation.set_qpos(np.array([q, q], dtype=np.float32))
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

    def capabilities(self) -> Capabilities:
        camera = "SAPIEN renderer (Vulkan) depth and labels" if self._native else "open3d ray-cast depth and labels"
        return Capabilities(name="sapien", notes=f"{camera}; PhysX (CPU) rigid bodies")

    @property
    def camera_path(self) -> str:
        """``native`` (SAPIEN's renderer) or ``raycast`` (open3d over the collision geometry)."""
        return "native" if self._native else "raycast"

    # ------------------------------------------------------------------------------------- building
    def _build_world(self, scene: SceneSpec, objects: Sequence[tuple[ObjectSpec, _BodyState | None]]) -> None:
        """A new scene with shelf, gripper and objects (``None`` state: the spec pose)."""
        cfg = self.config
        sapien.physx.set_scene_config(
            gravity=np.array([0.0, 0.0, -9.81], dtype=np.float32),
            bounce_threshold=2.0,
            enable_pcm=True,
            enable_tgs=True,
            enable_ccd=False,
            enable_enhanced_determinism=True,
            enable_friction_every_iteration=True,
            cpu_workers=0,
        )
        sapien.physx.set_body_config(
            solver_position_iterations=cfg.solver_position_iterations, solver_velocity_iterations=1
        )
        sapien.physx.set_shape_config(contact_offset=0.005, rest_offset=0.0)
        systems: list[Any] = [sapien.physx.PhysxCpuSystem()]
        if self._native:
            systems.append(sapien.render.RenderSystem())
        self._sapien = sapien.Scene(systems)
        self._sapien.set_timestep(cfg.time_step_s)
        m_obj, m_shelf, m_finger = _physx_frictions(OBJECT_FRICTION, scene.shelf.friction, cfg.gripper.finger_friction)
        self._materials = {
            "object": sapien.physx.PhysxMaterial(m_obj, m_obj, 0.0),
            "shelf": sapien.physx.PhysxMaterial(m_shelf, m_shelf, 0.0),
            "finger": sapien.physx.PhysxMaterial(m_finger, m_finger, 0.0),
        }
        if self._native:
            self._render_material = sapien.render.RenderMaterial(base_color=[0.6, 0.6, 0.6, 1.0])
        self._ids = {}
        self._contact_cache = None
        self._build_shelf(scene.shelf)
        self._build_gripper()
        self._objects = {}
        for spec, state in objects:
            self._objects[spec.id] = self._build_object(spec, state)
        self._camera = None
        if self._native:
            cam = self.config.camera
            self._camera = sapien.render.RenderCameraComponent(cam.width_px, cam.height_px)
            k = cam.intrinsics
            self._camera.set_perspective_parameters(cam.near_m, cam.far_m, k[0, 0], k[1, 1], k[0, 2], k[1, 2], 0.0)
            mount = sapien.Entity()
            mount.name = "camera"
            mount.add_component(self._camera)
            self._sapien.add_entity(mount)

    def _visual(self, meshes: Sequence[Any]) -> Any:
        """A render body of triangle meshes (entity frame), for the native camera."""
        body = sapien.render.RenderBodyComponent()
        for m in meshes:
            v = np.ascontiguousarray(m.vertices, dtype=np.float32)
            shape = sapien.render.RenderShapeTriangleMesh(
                v,
                np.ascontiguousarray(m.faces, dtype=np.uint32),
                np.ascontiguousarray(m.vertex_normals, dtype=np.float32),
                np.zeros((len(v), 2), dtype=np.float32),
                self._render_material,
            )
            body.attach(shape)
        return body

    def _build_shelf(self, shelf: ShelfSpec) -> None:
        assert self._sapien is not None
        body = sapien.physx.PhysxRigidStaticComponent()
        boards = shelf.boards()
        for centre, half in boards:
            shape = sapien.physx.PhysxCollisionShapeBox(
                half_size=np.asarray(half, dtype=np.float32), material=self._materials["shelf"]
            )
            shape.local_pose = sapien.Pose(np.asarray(centre, dtype=np.float32))
            body.attach(shape)
        entity = sapien.Entity()
        entity.name = "shelf"
        entity.add_component(body)
        if self._native:
            entity.add_component(self._visual(self._shelf_meshes(shelf)))
        self._sapien.add_entity(entity)
        self._ids[entity.per_scene_id] = SHELF_ID
        n = len(boards)
        self._shelf_boxes = (
            np.array([c for c, _ in boards]),
            np.broadcast_to(np.eye(3), (n, 3, 3)).copy(),
            np.array([h for _, h in boards]),
        )

    def _shelf_meshes(self, shelf: ShelfSpec) -> list[Any]:
        if self._shelf_mesh_cache is None or self._shelf_mesh_cache[0] != shelf:
            self._shelf_mesh_cache = (shelf, shelf_meshes(shelf))
        return self._shelf_mesh_cache[1]

    def _build_object(self, spec: ObjectSpec, state: _BodyState | None) -> _Object:
        assert self._sapien is not None
        cls: ObjectClass = spec.object_class
        body = sapien.physx.PhysxRigidDynamicComponent()
        for part in cls.parts:
            rot = quat_to_matrix(part.quat_xyzw)
            if part.kind == "box":
                shape: Any = sapien.physx.PhysxCollisionShapeBox(
                    half_size=np.asarray(part.size_m, dtype=np.float32) / 2, material=self._materials["object"]
                )
            else:
                radius, height = part.size_m
                shape = sapien.physx.PhysxCollisionShapeCylinder(
                    radius=radius, half_length=height / 2, material=self._materials["object"]
                )
                rot = rot @ _CYLINDER_TO_Z
            local = np.eye(4)
            local[:3, :3], local[:3, 3] = rot, part.position_m
            shape.local_pose = _sapien_pose(local)
            body.attach(shape)
        com = parts_centroid(cls.parts)
        body.mass = cls.mass_kg
        body.cmass_local_pose = sapien.Pose(np.asarray(com, dtype=np.float32))
        body.inertia = _bounding_box_inertia(cls.parts, cls.mass_kg).astype(np.float32)
        entity = sapien.Entity()
        entity.name = f"object:{spec.id}"
        entity.add_component(body)
        if self._native:
            entity.add_component(self._visual([part_mesh_local(q) for q in cls.parts]))
        if state is None:
            x, y, z, w = spec.quat_xyzw
            entity.pose = sapien.Pose(np.asarray(spec.position_m, dtype=np.float32), np.array([w, x, y, z], np.float32))
        else:
            entity.pose = sapien.Pose(np.array(state.p, np.float32), np.array(state.q, np.float32))
        self._sapien.add_entity(entity)
        if state is not None:
            body.set_linear_velocity(np.array(state.linear_velocity, np.float32))
            body.set_angular_velocity(np.array(state.angular_velocity, np.float32))
        self._ids[entity.per_scene_id] = spec.id
        other = cls.confusable_with
        boxes = [_part_box(q) for q in cls.parts]
        return _Object(
            spec,
            entity,
            body,
            cls.class_id,
            object_class(other).class_id if other else None,
            (np.array([b[0] for b in boxes]), np.array([b[1] for b in boxes]), np.array([b[2] for b in boxes])),
        )

    def _build_gripper(self) -> None:
        """Palm link (its frame is the gripper frame) with two prismatic fingers along gripper x."""
        assert self._sapien is not None
        g = self.config.gripper
        _, finger_half = g.boxes(0.0)[0]
        _, palm_half = g.boxes(0.0)[2]
        fz = -g.finger_length_m / 2
        links = []
        palm = sapien.physx.PhysxArticulationLinkComponent(None)
        palm_shape = sapien.physx.PhysxCollisionShapeBox(
            half_size=palm_half.astype(np.float32), material=self._materials["finger"]
        )
        palm_shape.local_pose = sapien.Pose(self._palm_centre.astype(np.float32))
        palm.attach(palm_shape)
        palm.mass = g.mass_kg
        palm.cmass_local_pose = sapien.Pose(self._palm_centre.astype(np.float32))
        palm.inertia = _box_inertia(palm_half, g.mass_kg).astype(np.float32)
        links.append(palm)
        # A finger's joint position q is half the opening: its centre sits at x = -+(q + thickness/2).
        flip = sapien.Pose(q=np.array([0.0, 0.0, 0.0, 1.0], dtype=np.float32))  # pi about z: joint x = -gripper x
        sides = ((-g.finger_thickness_m / 2, flip), (g.finger_thickness_m / 2, sapien.Pose()))
        for side, (x0, rot) in enumerate(sides):
            finger = sapien.physx.PhysxArticulationLinkComponent(palm)
            shape = sapien.physx.PhysxCollisionShapeBox(
                half_size=finger_half.astype(np.float32), material=self._materials["finger"]
            )
            finger.attach(shape)
            finger.mass = FINGER_MASS_KG
            finger.cmass_local_pose = sapien.Pose()
            finger.inertia = _box_inertia(finger_half, FINGER_MASS_KG).astype(np.float32)
            finger.joint.type = "prismatic"
            finger.joint.pose_in_parent = sapien.Pose(np.array([x0, 0.0, fz], np.float32), rot.q)
            finger.joint.pose_in_child = sapien.Pose()
            finger.joint.limit = np.array([[0.0, g.max_opening_m / 2]], dtype=np.float32)
            finger.joint.set_drive_properties(FINGER_STIFFNESS, FINGER_DAMPING, g.finger_force_n, "force")
            finger.joint.name = f"finger{side}"
            links.append(finger)
        pos, orn = self._gripper_target
        root = np.eye(4)
        root[:3, :3], root[:3, 3] = quat_to_matrix(orn), pos
        for i, link in enumerate(links):
            link.disable_gravity = True
            for shape in link.collision_shapes:
                shape.set_collision_groups(_GRIPPER_GROUPS)
            entity = sapien.Entity()
            entity.name = ("palm", "finger0", "finger1")[i]
            entity.add_component(link)
            if self._native:
                entity.add_component(self._visual(self._gripper_meshes()[i]))
            if i == 0:
                entity.pose = _sapien_pose(root)
            self._sapien.add_entity(entity)
            self._ids[entity.per_scene_id] = GRIPPER_ID
        self._links = links
        self._articulation = palm.articulation
        self._articulation.solver_position_iterations = self.config.solver_position_iterations
        self._fingers = (links[1].entity.per_scene_id, links[2].entity.per_scene_id)
        self._joints = self._articulation.active_joints
        drive = sapien.physx.PhysxDriveComponent(palm)
        drive.parent = None
        drive.pose_in_parent = sapien.Pose()
        drive.pose_in_child = sapien.Pose()
        for set_axis in (drive.set_drive_property_x, drive.set_drive_property_y, drive.set_drive_property_z):
            set_axis(GRIPPER_STIFFNESS, GRIPPER_DAMPING, GRIPPER_MAX_FORCE_N, "force")
        drive.set_drive_property_slerp(GRIPPER_ROT_STIFFNESS, GRIPPER_ROT_DAMPING, GRIPPER_MAX_FORCE_N, "force")
        palm.entity.add_component(drive)
        self._drive = drive
        self._drive.set_drive_target(_sapien_pose(root))

    def _gripper_meshes(self) -> list[list[Any]]:
        """Box meshes of palm and fingers in their link frames (native camera)."""
        g = self.config.gripper
        (_, finger_half), _, (_, palm_half) = g.boxes(0.0)
        palm = trimesh.creation.box(extents=2 * palm_half)
        palm.apply_translation(self._palm_centre)
        finger = trimesh.creation.box(extents=2 * finger_half)
        return [[palm], [finger], [finger]]

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
        qpos, qvel = art.get_qpos(), art.get_qvel()
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

    # ------------------------------------------------------------------------------------- camera
    def observe(self, camera_to_world: NDArray[np.float64]) -> Observation:
        """Render z-depth, labels and object ids from an OpenCV camera-to-world pose."""
        self._require_scene()
        cam = self.config.camera
        c2w = np.asarray(camera_to_world, dtype=np.float64)
        depth, object_ids = self._render_native(c2w) if self._native else self._render_raycast(c2w)
        oids = sorted(self._objects)
        id_lut = np.zeros(max(oids, default=0) + 2, dtype=np.int16)  # indexed by object id + 1
        for oid in oids:
            id_lut[oid + 1] = self._objects[oid].class_id
        if self.config.label_noise > 0.0:
            # Structured noise: a visible object is relabelled as a whole for this view, never per pixel.
            visible = sorted(int(i) for i in np.unique(object_ids) if i >= 0)
            flips = self._rng.random(len(visible)) < self.config.label_noise
            for oid, flip in zip(visible, flips, strict=True):
                obj = self._objects[oid]
                if flip and obj.confusable_id is not None:
                    id_lut[oid + 1] = obj.confusable_id
        labels = id_lut[object_ids + 1]
        return Observation(
            depth=depth.astype(np.float32),
            labels=labels.astype(np.int16),
            intrinsics=cam.intrinsics,
            camera_to_world=c2w.copy(),
            object_ids=object_ids.astype(np.int32),
            meta={"camera": self.camera_path},
        )

    def _render_native(self, c2w: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """SAPIEN's renderer: ``Position`` (OpenGL camera frame) -> z-depth, ``Segmentation`` -> ids."""
        assert self._sapien is not None
        assert self._camera is not None
        cam = self.config.camera
        # SAPIEN camera entity axes: x forward, y left, z up (OpenCV: z forward, x right, y down).
        mount = c2w.copy()
        mount[:3, :3] = c2w[:3, :3] @ np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
        self._camera.entity.pose = _sapien_pose(mount)
        self._sapien.update_render()
        self._camera.take_picture()
        position = self._camera.get_picture("Position")
        seg = self._camera.get_picture("Segmentation")[..., 1].astype(np.int64)
        depth = -position[..., 2].astype(np.float64)
        depth[(position[..., 3] >= 1.0) | (depth > cam.far_m) | (depth <= 0.0)] = 0.0
        lut = np.full(max(self._ids, default=0) + 2, -1, dtype=np.int64)
        for sid, oid in self._ids.items():
            if oid >= 0:
                lut[sid] = oid
        seg = np.where(seg < len(lut), seg, len(lut) - 1)
        ids = lut[seg]
        ids[depth == 0.0] = -1
        return depth, ids

    def _render_raycast(self, c2w: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """open3d ray casting over the part meshes at their current poses (and shelf and gripper boxes).

        One triangle soup; each triangle's owner (object id, or -1 for shelf and gripper) gives the ids.
        Rays start on the near plane with a unit optical-axis component, so ``near + t_hit`` is z-depth.
        """
        assert self._scene is not None
        cam = self.config.camera
        verts: list[NDArray[np.float64]] = []
        faces: list[NDArray[np.int64]] = []
        owners: list[NDArray[np.int64]] = []
        count = 0

        def add(v: NDArray[np.float64], f: NDArray[np.int64], owner: int) -> None:
            nonlocal count
            verts.append(v)
            faces.append(f + count)
            owners.append(np.full(len(f), owner, dtype=np.int64))
            count += len(v)

        for oid, obj in self._objects.items():
            v, f = _class_soup(obj.spec.class_name)
            t = _matrix(obj.entity.pose)
            add(v @ t[:3, :3].T + t[:3, 3], f, oid)
        for m in [*self._shelf_meshes(self._scene.shelf), self._gripper_world_mesh()]:
            add(np.asarray(m.vertices), np.asarray(m.faces, dtype=np.int64), -1)
        rc = o3d.t.geometry.RaycastingScene()
        rc.add_triangles(
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(np.concatenate(verts), dtype=np.float32)),
            o3d.core.Tensor.from_numpy(np.ascontiguousarray(np.concatenate(faces), dtype=np.uint32)),
        )
        if self._pixel_rays is None:
            self._pixel_rays = cam.pixel_rays(1).reshape(-1, 3).astype(np.float32)
        d_world = self._pixel_rays @ c2w[:3, :3].T.astype(np.float32)
        origin = (c2w[:3, 3] + cam.near_m * d_world).astype(np.float32)
        ans = rc.cast_rays(o3d.core.Tensor.from_numpy(np.concatenate([origin, d_world], axis=1)))
        t_hit = ans["t_hit"].numpy().astype(np.float64)
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        hit = np.isfinite(t_hit) & (t_hit <= cam.far_m - cam.near_m)
        owner = np.concatenate([*owners, np.array([-1], dtype=np.int64)])
        ids = owner[np.where(hit, prim, len(owner) - 1)]
        depth = np.where(hit, t_hit + cam.near_m, 0.0)
        shape = (cam.height_px, cam.width_px)
        return depth.reshape(shape), ids.reshape(shape)

    def _gripper_world_mesh(self) -> Any:
        pose = self.gripper_pose()
        parts = []
        for centre, half in self.config.gripper.boxes(self._opening()):
            t = pose.copy()
            t[:3, 3] = pose[:3, 3] + pose[:3, :3] @ centre
            parts.append(trimesh.creation.box(extents=2 * half, transform=t))
        return trimesh.util.concatenate(parts)

    # ------------------------------------------------------------------------------------- gripper
    def gripper_pose(self) -> NDArray[np.float64]:
        """Pose of the gripper frame (origin between the fingertip pads, z = approach)."""
        self._require_scene()
        return _matrix(self._articulation.root_pose)

    def _opening(self) -> float:
        return float(np.sum(self._articulation.get_qpos()))

    def _finger_speed(self) -> float:
        return float(np.abs(self._articulation.get_qvel()).sum())

    def set_gripper(self, opening_m: float) -> float:
        """Drive both fingers to ``opening_m`` (clamped); stop when reached or blocked (<= 0.5 s)."""
        self._require_scene()
        g = self.config.gripper
        self._finger_goal_m = float(np.clip(opening_m, 0.0, g.max_opening_m))
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
        art = self._articulation
        art.set_root_pose(_sapien_pose(pose))
        art.set_root_linear_velocity(np.zeros(3, dtype=np.float32))
        art.set_root_angular_velocity(np.zeros(3, dtype=np.float32))
        self._set_target(pose[:3, 3], matrix_to_quat(pose[:3, :3]))

    def _track(self, target: PathTarget) -> None:
        self._set_target(target.position, target.quat_xyzw, target.velocity, target.spin)

    def _end_path(self, position: NDArray[np.float64], quat_xyzw: NDArray[np.float64]) -> None:
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
        """Whether the gripper at ``pose``, grown by ``clearance``, overlaps an obstacle (bounding boxes)."""
        cb, rb, hb = self._obstacles(with_objects)
        return any(bool(np.any(_obb_overlap(c, r, h, cb, rb, hb))) for c, r, h in self._gripper_boxes(pose, clearance))

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


