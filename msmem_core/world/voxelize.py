"""Ground-truth voxelisation: occupancy, classes and object ids per voxel, from object specs and poses.

Occupancy rule (shared with the observation update): a voxel is occupied iff the solid touches it,
i.e. the voxel and one of the object's convex parts overlap with positive volume (equivalently: the
voxel contains a point of the surface, or its centre lies inside a part). It is computed exactly
by a separating-axis test of every part against the candidate voxels; a cylinder is the
``CYLINDER_SECTIONS``-sided prism of its mesh (inscribed, < 0.1 mm from the true surface), so
every point a ray can hit lies in an occupied voxel.
Overlaps thinner than ``TOUCH_TOLERANCE_M`` do not count, so an object resting on a voxel
boundary (z = 0 on the default grid) does not mark the layer below it.

What the views can see of that ground truth (visible objects, observable voxels) is in
``msmem_core.world.visibility``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from functools import cache

import numpy as np
from numpy.typing import NDArray

from msmem_core.world.geometry import pose_matrix
from msmem_core.world.grid import GridSpec
from msmem_core.world.meshes import CYLINDER_SECTIONS, part_mesh_own_frame
from msmem_core.world.scene import ObjectSpec, Part, ShelfSpec

TOUCH_TOLERANCE_M = 1e-4
"""Minimum overlap depth (metres) for a part to touch a voxel. A tenth of a millimetre: simulated objects
settle ~10 um into the floor or a neighbour, which must not count as touching the next voxel layer
(otherwise metrics would depend on the physics backend)."""

Poses = Mapping[int, NDArray[np.float64]]
"""Object id -> 4x4 world pose, for objects that moved away from their spec's pose."""


def current_pose(obj: ObjectSpec, poses: Poses | None) -> NDArray[np.float64]:
    """The object's world pose: ``poses[obj.id]`` when given (it moved), else its spec's pose."""
    if poses is not None and obj.id in poses:
        return np.asarray(poses[obj.id], dtype=np.float64)
    return obj.pose()


def _part_world_pose(part: Part, object_pose: NDArray[np.float64]) -> NDArray[np.float64]:
    return object_pose @ pose_matrix(part.position_m, part.quat_xyzw)


def _candidates(
    centre: NDArray[np.float64], half: NDArray[np.float64], grid: GridSpec
) -> tuple[NDArray[np.int64], NDArray[np.float64]] | None:
    """Flat indices and centres (N, 3) of the grid voxels that meet the box centre +- half."""
    s = grid.voxel_m
    lo = np.maximum(np.floor((centre - half - grid.origin) / s).astype(np.int64), 0)
    hi = np.minimum(np.floor((centre + half - grid.origin) / s).astype(np.int64), np.asarray(grid.shape) - 1)
    if np.any(hi < lo):
        return None
    axes = [np.arange(lo[a], hi[a] + 1) for a in range(3)]
    ijk = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    flat = np.ravel_multi_index(ijk.T, grid.shape)
    return flat, grid.origin + (ijk + 0.5) * s


def _unique_directions(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit directions of the rows of ``v``, each line once (v and -v are one axis)."""
    u = v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)
    first = np.argmax(np.abs(u) > 1e-9, axis=1)  # the first clearly non-zero component is made positive
    u[u[np.arange(len(u)), first] < 0] *= -1
    return np.unique(np.round(u, 9), axis=0)


@cache
def _polytope(part: Part) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Vertices, face normals and edge directions of a part in its own frame.

    A cylinder is the prism its mesh uses (``CYLINDER_SECTIONS`` sides, vertices at angles
    2 pi k / n), so ground truth voxelises exactly the geometry that rays hit.
    """
    mesh = part_mesh_own_frame(part)
    verts = np.asarray(mesh.vertices)
    if part.kind == "box":
        return verts, np.eye(3), np.eye(3)
    if part.kind == "convex":  # the hull's face normals and edge directions, each direction once
        hull = mesh
        normals = _unique_directions(np.asarray(hull.face_normals))
        edges = np.asarray(hull.vertices)[hull.edges_unique]
        return verts, normals, _unique_directions(edges[:, 1] - edges[:, 0])
    n = CYLINDER_SECTIONS
    a = 2 * np.pi * (np.arange((n + 1) // 2) + 0.5) / n  # opposite sides are parallel for even n
    side = np.stack([np.cos(a), np.sin(a), np.zeros_like(a)], axis=-1)
    along = np.stack([-np.sin(a), np.cos(a), np.zeros_like(a)], axis=-1)
    z = np.array([[0.0, 0.0, 1.0]])
    return verts, np.concatenate([side, z]), np.concatenate([along, z])


def _convex_touches(
    centres: NDArray[np.float64],
    verts: NDArray[np.float64],
    normals: NDArray[np.float64],
    edges: NDArray[np.float64],
    s: float,
) -> NDArray[np.bool_]:
    """Separating-axis test of a convex polytope (world frame) against axis-aligned voxels.

    Candidate axes: the polytope's face normals, the grid axes and the cross products of the
    polytope's edge directions with the grid axes; the voxel (centre c, edge s) and the polytope
    overlap iff their projections overlap by more than ``TOUCH_TOLERANCE_M`` on every axis.
    """
    eye = np.eye(3)
    axes = np.concatenate([normals, eye, np.cross(edges[:, None, :], eye[None]).reshape(-1, 3)])
    norm = np.linalg.norm(axes, axis=1)
    axes = axes[norm > 1e-9] / norm[norm > 1e-9, None]  # drop degenerate (parallel) cross products
    proj = verts @ axes.T
    lo, hi = proj.min(axis=0), proj.max(axis=0)
    reach = s / 2 * np.abs(axes).sum(axis=1)
    c = centres @ axes.T
    return np.all((c + reach > lo + TOUCH_TOLERANCE_M) & (c - reach < hi - TOUCH_TOLERANCE_M), axis=1)


def _part_voxels(part: Part, object_pose: NDArray[np.float64], grid: GridSpec) -> NDArray[np.int64]:
    """Flat indices of the grid voxels the part touches."""
    pose = _part_world_pose(part, object_pose)
    rot, t = pose[:3, :3], pose[:3, 3]
    verts, normals, edges = _polytope(part)
    verts_w = verts @ rot.T + t
    lo, hi = verts_w.min(axis=0), verts_w.max(axis=0)
    cand = _candidates((lo + hi) / 2, (hi - lo) / 2, grid)
    if cand is None:
        return np.zeros(0, dtype=np.int64)
    flat, centres = cand
    return flat[_convex_touches(centres, verts_w, normals @ rot.T, edges @ rot.T, grid.voxel_m)]


def object_voxels(obj: ObjectSpec, grid: GridSpec, pose: NDArray[np.float64] | None = None) -> NDArray[np.int64]:
    """Sorted flat indices (into ``grid.shape``) of the voxels the object touches at ``pose``."""
    t = obj.pose() if pose is None else np.asarray(pose, dtype=np.float64)
    parts = [_part_voxels(p, t, grid) for p in obj.object_class.parts]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)


def voxelize_instances(objects: Sequence[ObjectSpec], grid: GridSpec, poses: Poses | None = None) -> NDArray[np.int32]:
    """Object id per voxel ``[X, Y, Z]`` (-1 = free); where objects share a voxel the later one wins."""
    ids = np.full(grid.size, -1, dtype=np.int32)
    for obj in objects:
        ids[object_voxels(obj, grid, current_pose(obj, poses))] = obj.id
    return ids.reshape(grid.shape)


def voxelize(
    objects: Sequence[ObjectSpec], grid: GridSpec, poses: Poses | None = None
) -> tuple[NDArray[np.bool_], NDArray[np.int16]]:
    """Ground-truth occupancy (bool) and class id (int16, 0 = free) per voxel, both ``[X, Y, Z]``.

    ``poses`` (object id -> 4x4 world pose) overrides the specs' poses, for objects that moved;
    objects absent from ``objects`` (removed) are simply not passed. The shelf is not included.
    """
    occ = np.zeros(grid.size, dtype=bool)
    cls = np.zeros(grid.size, dtype=np.int16)
    for obj in objects:
        idx = object_voxels(obj, grid, current_pose(obj, poses))
        occ[idx] = True
        cls[idx] = obj.class_id
    return occ.reshape(grid.shape), cls.reshape(grid.shape)


def interior_mask(shelf: ShelfSpec, grid: GridSpec) -> NDArray[np.bool_]:
    """Voxels whose centre lies inside the shelf interior (excludes the boards and the outside)."""
    c = grid.centers()
    return np.all((c > shelf.interior_lower) & (c < shelf.interior_upper), axis=-1)
