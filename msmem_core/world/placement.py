"""Plausibility of a scene's object placements: inside the shelf, resting on a support, not interpenetrating.

Objects are the convex parts ground truth voxelises (a cylinder is its ``CYLINDER_SECTIONS``-sided
prism), posed by the spec. Checks, each error naming the object's id and class:

- inside: every part lies in the shelf interior, give or take ``INSIDE_TOLERANCE_M``;
- support: the object's lowest point is on the floor board (z = 0) or on the top of another object
  below it, within ``SUPPORT_TOLERANCE_M``: nothing floats and nothing is sunk into the floor;
- interpenetration: two objects' parts overlap by at most ``PENETRATION_TOLERANCE_M`` (the depth of
  the overlap: the smallest overlap of their projections over the separating axes of the two convex parts).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import UserError
from msmem_core.world.scene import ClassSpec, ObjectSpec, SceneSpec
from msmem_core.world.voxelize import _part_world_pose, _polytope

INSIDE_TOLERANCE_M = 1e-3
"""How far a part may reach past the shelf interior (walls, top board, open front): 1 mm of rounding."""
SUPPORT_TOLERANCE_M = 5e-3
"""How far an object's lowest point may be from its support: a hand-written scene rounded to the
millimetre, or a drop of a few millimetres that physics settles in its first step."""
PENETRATION_TOLERANCE_M = 1e-3
"""Largest overlap depth between two objects: 1 mm, what a contact solver pushes apart in one step
(generated scenes keep a gap of ``min_gap_m`` on a 2.5 mm raster; the shipped suites overlap by 0)."""


@dataclass(frozen=True)
class _Solid:
    verts: NDArray[np.float64]
    normals: NDArray[np.float64]
    edges: NDArray[np.float64]
    lo: NDArray[np.float64]
    hi: NDArray[np.float64]


def _solids(obj: ObjectSpec) -> list[_Solid]:
    """The object's convex parts in the world: vertices, face normals, edge directions and bounds."""
    out = []
    pose = obj.pose()
    for part in obj.object_class.parts:
        p = _part_world_pose(part, pose)
        rot, t = p[:3, :3], p[:3, 3]
        verts, normals, edges = _polytope(part)
        w = verts @ rot.T + t
        out.append(_Solid(w, normals @ rot.T, edges @ rot.T, w.min(axis=0), w.max(axis=0)))
    return out


SAT_MAX_EDGES = 64
"""Solids with more edges than this (mesh pieces) are compared by ``inscribed_depth``: the separating
axis test's edge pairs grow as the product of the two edge counts."""


def inscribed_depth(a: _Solid, b: _Solid) -> float:
    """Twice the radius of the largest ball inside both convex solids (0 if they do not intersect): a
    linear program over the two solids' face half-planes. Never more than the least projection
    overlap ``penetration_depth`` measures, and equal to it for two boxes overlapping at a corner."""
    from scipy.optimize import linprog

    # each solid is the intersection of its supporting half-spaces along +-(its face normal directions)
    na, nb = np.concatenate([a.normals, -a.normals]), np.concatenate([b.normals, -b.normals])
    normals = np.concatenate([na, nb])
    offsets = np.concatenate([(a.verts @ na.T).max(axis=0), (b.verts @ nb.T).max(axis=0)])
    norm = np.linalg.norm(normals, axis=1)
    keep = norm > 1e-9
    rows = np.hstack([normals[keep], norm[keep, None]])  # n . x + |n| r <= offset
    res = linprog(c=[0.0, 0.0, 0.0, -1.0], A_ub=rows, b_ub=offsets[keep],
                  bounds=[(None, None)] * 3 + [(0.0, None)], method="highs")
    return 2.0 * float(res.x[3]) if res.status == 0 else 0.0


def penetration_depth(a: _Solid, b: _Solid) -> float:
    """Depth of the overlap of two convex solids (0 if they are apart): the least projection overlap
    over the candidate separating axes (both solids' face normals and their edges' cross products);
    for solids with many edges, ``inscribed_depth``."""
    if np.any(a.lo > b.hi) or np.any(b.lo > a.hi):
        return 0.0
    if max(len(a.edges), len(b.edges)) > SAT_MAX_EDGES:
        return inscribed_depth(a, b)
    axes = np.concatenate([a.normals, b.normals, np.cross(a.edges[:, None, :], b.edges[None]).reshape(-1, 3)])
    norm = np.linalg.norm(axes, axis=1)
    axes = axes[norm > 1e-9] / norm[norm > 1e-9, None]
    pa, pb = a.verts @ axes.T, b.verts @ axes.T
    overlap = np.minimum(pa.max(axis=0), pb.max(axis=0)) - np.maximum(pa.min(axis=0), pb.min(axis=0))
    return max(0.0, float(overlap.min()))


def _name(obj: ObjectSpec) -> str:
    return f"object {obj.id} ({obj.class_name})"


def placement_errors(scene: SceneSpec) -> list[str]:
    """One line per implausible placement (empty when the scene is plausible)."""
    errors: list[str] = []
    lower, upper = scene.shelf.interior_lower, scene.shelf.interior_upper
    solids = {o.id: _solids(o) for o in scene.objects}
    bounds = {i: (np.min([s.lo for s in ss], axis=0), np.max([s.hi for s in ss], axis=0)) for i, ss in solids.items()}
    for obj in scene.objects:
        lo, hi = bounds[obj.id]
        for axis, (name, low_side, high_side) in enumerate(
            [("x", "left wall", "right wall"), ("y", "open front", "back wall"), ("z", "floor", "top board")]
        ):
            if lo[axis] < lower[axis] - INSIDE_TOLERANCE_M:
                errors.append(f"{_name(obj)} is outside the shelf: it reaches {name} = {lo[axis]:.3f} m, past the "
                              f"{low_side} at {lower[axis]:.3f} m")
            if hi[axis] > upper[axis] + INSIDE_TOLERANCE_M:
                errors.append(f"{_name(obj)} is outside the shelf: it reaches {name} = {hi[axis]:.3f} m, past the "
                              f"{high_side} at {upper[axis]:.3f} m")
        bottom = lo[2]
        on_floor = abs(bottom - lower[2]) <= SUPPORT_TOLERANCE_M
        on_object = any(abs(bottom - bounds[o.id][1][2]) <= SUPPORT_TOLERANCE_M
                        and np.all(lo[:2] <= bounds[o.id][1][:2]) and np.all(bounds[o.id][0][:2] <= hi[:2])
                        for o in scene.objects if o.id != obj.id)
        if not (on_floor or on_object) and bottom > lower[2]:
            errors.append(f"{_name(obj)} floats: its lowest point is {bottom - lower[2]:.3f} m above the floor and "
                          f"on no other object (tolerance {SUPPORT_TOLERANCE_M * 1000:g} mm)")
    objs = list(scene.objects)
    for i, a in enumerate(objs):
        for b in objs[i + 1:]:
            (alo, ahi), (blo, bhi) = bounds[a.id], bounds[b.id]
            if np.any(alo > bhi) or np.any(blo > ahi):
                continue
            depth = max(penetration_depth(sa, sb) for sa in solids[a.id] for sb in solids[b.id])
            if depth > PENETRATION_TOLERANCE_M:
                errors.append(f"{_name(a)} and {_name(b)} interpenetrate by {depth * 1000:.1f} mm "
                              f"(tolerance {PENETRATION_TOLERANCE_M * 1000:g} mm)")
    return errors


def check_placement(scene: SceneSpec, source: str = "scene") -> SceneSpec:
    """The scene, or a ``UserError`` naming the first implausible placements (objects by id and class)."""
    errors = placement_errors(scene)
    if errors:
        more = f" (+{len(errors) - 3} more)" if len(errors) > 3 else ""
        raise UserError(f"implausible {source}: " + "; ".join(errors[:3]) + more)
    return scene


def load_scene(path: str, offered: Mapping[str, ClassSpec] | None = None) -> SceneSpec:
    """A scene file, validated field by field (``SceneSpec.from_json``, with the classes plugins
    ``offered``) and then for placement."""
    return check_placement(SceneSpec.from_json(path, offered), f"scene file {path}")
