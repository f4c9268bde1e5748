"""Building a shelf scene in SAPIEN 3: shelf boards, objects and the floating gripper (``SceneBuilder``).

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
- SAPIEN poses are (position, quaternion **wxyz**); core uses xyzw and 4x4 matrices, converted at this
  boundary only (``_sapien_pose``, ``_matrix``).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from numpy.typing import NDArray

with warnings.catch_warnings():  # "Failed to find system libvulkan": SAPIEN then uses its bundled loader
    warnings.simplefilter("ignore", UserWarning)
    import sapien

from msmem_core.interfaces import GRIPPER_ID, SHELF_ID
from msmem_core.world.geometry import matrix_to_quat, pose_matrix, quat_to_matrix
from msmem_core.world.meshes import part_mesh_local, shelf_meshes
from msmem_core.world.scene import ObjectClass, ObjectSpec, Part, SceneSpec, ShelfSpec, parts_centroid

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
_GRIPPER_GROUPS = [1, 1, 1, 0]
"""Collision groups of gripper shapes: they collide with everything but each other (shared word 2)."""
_CYLINDER_TO_Z = quat_to_matrix((0.0, -math.sqrt(0.5), 0.0, math.sqrt(0.5)))
"""Rotation taking PhysX's cylinder axis (x) to the part's z axis (a quarter turn about y)."""

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
    if part.kind == "convex":  # the vertices' bounds in the part frame
        v = np.asarray(part.vertices_m, dtype=np.float64)
        lo, hi = v.min(axis=0), v.max(axis=0)
        return np.asarray(part.position_m, dtype=np.float64) + rot @ ((lo + hi) / 2), rot, (hi - lo) / 2
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



@dataclass(frozen=True)
class _BodyState:
    """Entity-frame pose (position, wxyz quaternion; float32 as PhysX holds it) and velocity of a body."""

    p: tuple[float, float, float]
    q: tuple[float, float, float, float]
    linear_velocity: tuple[float, float, float]
    angular_velocity: tuple[float, float, float]



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



class SceneBuilder:
    """The scene-building half of ``SapienSimulator``: a fresh ``sapien.Scene`` with shelf, gripper and objects.

    A mixin: it reads the simulator's ``config``, ``_native``, ``_gripper_target`` and ``_palm_centre`` and
    sets ``_sapien``, ``_materials``, ``_ids``, ``_objects``, ``_shelf_boxes``, ``_camera`` and the gripper's
    ``_links``, ``_articulation``, ``_fingers``, ``_joints`` and ``_drive``.
    """

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
            if part.kind == "convex":
                shape: Any = sapien.physx.PhysxCollisionShapeConvexMesh(
                    np.asarray(part.vertices_m, dtype=np.float32), np.ones(3, np.float32), self._materials["object"]
                )
            elif part.kind == "box":
                shape = sapien.physx.PhysxCollisionShapeBox(
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
        boxes = [_part_box(q) for q in cls.parts]
        return _Object(
            spec,
            entity,
            body,
            cls.class_id,
            cls.confusable_id,
            (np.array([b[0] for b in boxes]), np.array([b[1] for b in boxes]), np.array([b[2] for b in boxes])),
        )

    def _build_gripper(self) -> None:
        """Palm link (its frame is the gripper frame) with two prismatic fingers along gripper x; with an
        attached robot, its arm instead (``msmem_sapien.arm``)."""
        assert self._sapien is not None
        arm = getattr(self, "_arm", None)
        if arm is not None:
            art = arm.build(self._sapien, _GRIPPER_GROUPS, self._materials["finger"], FINGER_STIFFNESS, FINGER_DAMPING)
            art.solver_position_iterations = self.config.solver_position_iterations
            for link in art.links:
                self._ids[link.entity.per_scene_id] = GRIPPER_ID
            self._links, self._articulation = list(art.links), art
            self._fingers = arm.finger_entities
            self._joints = arm.finger_joints
            return
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
