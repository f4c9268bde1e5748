"""Triangle meshes of the catalogue's parts, objects and shelf boards (for raycasting and rendering).

Meshes are built once per class in the object frame (cached) and transformed to a pose on request.
A cylinder is a prism inscribed in the true cylinder (``CYLINDER_SECTIONS`` sides, sagitta below
0.1 mm for the catalogue's radii), so every mesh surface point lies in the analytic solid that
ground truth voxelises.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import trimesh
from numpy.typing import NDArray

from msmem_core.world.geometry import pose_matrix
from msmem_core.world.scene import ObjectClass, ObjectSpec, Part, ShelfSpec, object_class

CYLINDER_SECTIONS = 48


def part_mesh_own_frame(part: Part) -> trimesh.Trimesh:
    """Watertight mesh of one part in its own frame (its ``position_m`` and ``quat_xyzw`` not applied)."""
    return part_mesh_local(part.model_copy(update={"position_m": (0.0, 0.0, 0.0), "quat_xyzw": (0.0, 0.0, 0.0, 1.0)}))


def part_mesh_local(part: Part) -> trimesh.Trimesh:
    """Watertight mesh of one part in the object frame."""
    transform = pose_matrix(part.position_m, part.quat_xyzw)
    if part.kind == "box":
        return trimesh.creation.box(extents=part.size_m, transform=transform)
    if part.kind == "convex":
        hull = trimesh.convex.convex_hull(np.asarray(part.vertices_m, dtype=np.float64))
        return hull.apply_transform(transform)
    radius, height = part.size_m
    return trimesh.creation.cylinder(radius=radius, height=height, sections=CYLINDER_SECTIONS, transform=transform)


@cache
def _class_part_meshes(cls: ObjectClass) -> tuple[trimesh.Trimesh, ...]:
    return tuple(part_mesh_local(p) for p in cls.parts)


@cache
def _class_mesh(cls: ObjectClass) -> trimesh.Trimesh:
    mesh = trimesh.util.concatenate(list(_class_part_meshes(cls)))
    assert isinstance(mesh, trimesh.Trimesh)
    return mesh


def class_mesh(cls: str | ObjectClass) -> trimesh.Trimesh:
    """The class's mesh in its object frame (a concatenation of watertight part meshes; a copy); a
    name is a built-in class."""
    return _class_mesh(object_class(cls) if isinstance(cls, str) else cls).copy()


def part_meshes(obj: ObjectSpec, pose: NDArray[np.float64] | None = None) -> list[trimesh.Trimesh]:
    """One watertight mesh per part, at ``pose`` (default: the spec's pose)."""
    t = obj.pose() if pose is None else np.asarray(pose, dtype=np.float64)
    return [m.copy().apply_transform(t) for m in _class_part_meshes(obj.object_class)]


def object_mesh(obj: ObjectSpec, pose: NDArray[np.float64] | None = None) -> trimesh.Trimesh:
    """The object's parts concatenated into one mesh at ``pose`` (default: the spec's pose).

    Not a boolean union: overlapping parts keep their inner faces, which raycasting never sees
    from outside and which ground truth does not use.
    """
    t = obj.pose() if pose is None else np.asarray(pose, dtype=np.float64)
    return _class_mesh(obj.object_class).copy().apply_transform(t)


def shelf_meshes(shelf: ShelfSpec) -> list[trimesh.Trimesh]:
    """The shelf's boards (bottom, top, left, right, back) as boxes in the world frame."""
    out = []
    for centre, half in shelf.boards():
        t = np.eye(4)
        t[:3, 3] = centre
        out.append(trimesh.creation.box(extents=2 * half, transform=t))
    return out
