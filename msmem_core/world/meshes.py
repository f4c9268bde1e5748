"""Triangle meshes of the catalogue's parts, objects and shelf boards (for raycasting and rendering).

Meshes are built once per class in the object frame (cached) and transformed to a pose on request.
A cylinder is a prism inscribed in the true cylinder (``CYLINDER_SECTIONS`` sides, sagitta below
0.1 mm for the catalogue's radii), so every mesh surface point lies in the analytic solid that
ground truth voxelises.
"""

from __future__ import annotations

from functools import cache
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from msmem_core.world.geometry import pose_matrix
from msmem_core.world.scene import ObjectClass, ObjectSpec, Part, ShelfSpec, object_class, parts_centroid

if TYPE_CHECKING:
    import trimesh  # imported on first use: it takes a third of a second (the CLI starts without it)

CYLINDER_SECTIONS = 48


def part_mesh_own_frame(part: Part) -> trimesh.Trimesh:
    """Watertight mesh of one part in its own frame (its ``position_m`` and ``quat_xyzw`` not applied)."""
    return part_mesh_local(part.model_copy(update={"position_m": (0.0, 0.0, 0.0), "quat_xyzw": (0.0, 0.0, 0.0, 1.0)}))


def part_mesh_local(part: Part) -> trimesh.Trimesh:
    """Watertight mesh of one part in the object frame."""
    import trimesh
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
    import trimesh
    mesh = trimesh.util.concatenate(list(_class_part_meshes(cls)))
    assert isinstance(mesh, trimesh.Trimesh)
    return mesh


@cache
def class_extents_m(cls: ObjectClass) -> tuple[float, float, float]:
    """The class's axis-aligned extents (x, y, z) in its object frame, over all its parts (metres)."""
    lo, hi = _class_mesh(cls).bounds
    x, y, z = (float(v) for v in hi - lo)
    return x, y, z


@cache
def upright_tip_ratio(cls: ObjectClass) -> float:
    """How easily the class tips standing as in its object frame (z up): the height of its mass centre
    (``parts_centroid``) above its lowest point over the distance from the centre's projection to the
    nearest edge of its support (the hull of its mesh's points within 5 mm of the lowest). A box of
    height h on a face of narrow width w: (h / 2) / (w / 2) = h / w; a bunny standing on its small feet
    more than its extents say."""
    from scipy.spatial import ConvexHull, QhullError

    v = np.asarray(_class_mesh(cls).vertices)
    com = parts_centroid(cls.parts)
    z0 = float(v[:, 2].min())
    base = v[v[:, 2] < z0 + 0.005, :2]
    try:
        edges = ConvexHull(base).equations  # n . p + c <= 0 inside
    except (QhullError, ValueError):  # a support of one point or a line: tips at once
        return float("inf")
    margin = float((-(edges[:, :2] @ com[:2] + edges[:, 2])).min())
    return float("inf") if margin <= 0 else (float(com[2]) - z0) / margin


def stance_ratio(cls: ObjectClass, height_m: float) -> float:
    """How thin and tall an object of class ``cls`` stands when its top is ``height_m`` above its
    support. The axis standing up is, of the class's three extents, the one closest to ``height_m``
    (z on a tie).
    Standing as in its object frame (z up): ``upright_tip_ratio``. On another axis (lying, or on an
    edge): that extent over the narrower of the other two. A book of 15 x 3.5 x 20 cm standing on its
    3.5 cm edge: 20 / 3.5 = 5.7; the same book lying flat: 3.5 / 15 = 0.23."""
    e = np.asarray(class_extents_m(cls))
    off = np.abs(e - height_m)
    up = 2 if off[2] <= off.min() + 1e-9 else int(np.argmin(off))  # a tie: upright, as the class stands
    if up == 2:
        return upright_tip_ratio(cls)
    return float(e[up] / np.delete(e, up).min())


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
    import trimesh
    out = []
    for centre, half in shelf.boards():
        t = np.eye(4)
        t[:3, 3] = centre
        out.append(trimesh.creation.box(extents=2 * half, transform=t))
    return out
