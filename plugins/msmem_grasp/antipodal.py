"""Antipodal ground-truth grasps (paper sec. "Data generation": per object model in isolation, then
transformed into each scene and filtered for collisions with the shelf and the neighbours).

Per class: sample surface points with outward normals, shoot a ray into the solid along -n (tilted
uniformly inside the friction cone), take the first point where it leaves the solid as the opposite
contact, keep pairs narrower than the gripper's maximal opening whose baseline lies in the friction
cone (half-angle atan(mu)) of both contact normals, and try ``n_approach`` approach directions
orthogonal to the baseline; a grasp is kept if the finger and palm boxes of ``GripperSpec`` (opening
= width + margin, posed by ``executable_grasp``) do not intersect the object. Every grasp is stored
from both contacts (b flipped, same physical grasp), so each contact carries its directed baseline.

Collision tests are solid-vs-solid on the parts (box-box: exact separating-axis test in numpy;
box-cylinder and box-convex hull, a mesh class's pieces: python-fcl on the pairs whose bounding boxes
overlap); a triangle-mesh BVH test would miss a finger lying entirely inside a part.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING

import fcl
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.util.artifacts import cache_root
from msmem_core.world.geometry import F64, boxes_overlap, pose_matrix
from msmem_core.world.gripper import GripperSpec
from msmem_core.world.meshes import class_mesh
from msmem_core.world.scene import ObjectClass, Part, SceneSpec, object_class
from msmem_grasp.fevmf import executable_grasp

if TYPE_CHECKING:
    import trimesh

CACHE_VERSION = 1
"""Bump when the generator changes so stale cache files are not reused."""


class AntipodalConfig(BaseModel):
    """Sampling and filtering of antipodal grasps for one object class."""

    model_config = ConfigDict(extra="forbid")

    samples_per_m2: float = Field(100_000.0, gt=0.0)
    """Surface points sampled per m^2 of the class mesh (10 per cm^2). It sets how densely GT contacts
    cover the graspable surface, i.e. how many cloud points become positives: at this density 55-85 %
    of the surface within 2 cm of a contact lies within 5 mm (half a CPU voxel) of one. The paper
    uses 1e5 candidates per object."""
    min_samples: int = Field(500, ge=1)
    max_samples: int = Field(50_000, ge=1)
    n_approach: int = Field(12, ge=1)
    """Approach directions tried around each baseline (random phase per pair)."""
    friction: float = Field(0.5, gt=0.0)
    """Coulomb coefficient mu: friction-cone half-angle atan(mu)."""
    width_margin_m: float = Field(0.01, ge=0.0)
    """Opening used for the collision test = min(width + margin, max opening)."""
    min_width_m: float = Field(0.002, ge=0.0)
    symmetric: bool = True
    """Store each grasp from both of its contacts."""
    seed: int = 0


# ------------------------------------------------------------------------------------ grasp sets
@dataclass(frozen=True)
class GraspSet:
    """Antipodal grasps: contacts [G, 3], opposite contacts [G, 3], approach a [G, 3], baseline b [G, 3]
    (unit, directed from contact to opposite), width [G] (m). Frame: the object's, or the world's."""

    contacts: F64
    opposite: F64
    approach: F64
    baseline: F64
    width: F64

    def __len__(self) -> int:
        return len(self.width)

    @classmethod
    def empty(cls) -> GraspSet:
        z = np.zeros((0, 3))
        return cls(z, z.copy(), z.copy(), z.copy(), np.zeros(0))

    def subset(self, keep: NDArray[np.bool_] | NDArray[np.intp]) -> GraspSet:
        return GraspSet(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})

    def transformed(self, pose: F64) -> GraspSet:
        """The same grasps after a rigid transform (4x4)."""
        r, t = pose[:3, :3], pose[:3, 3]
        return GraspSet(self.contacts @ r.T + t, self.opposite @ r.T + t, self.approach @ r.T,
                        self.baseline @ r.T, self.width.copy())

    def poses(self) -> F64:
        """Gripper poses [G, 4, 4] (``executable_grasp``)."""
        out: F64 = executable_grasp(self.contacts, self.approach, self.baseline, self.width)  # type: ignore[assignment]
        return out

    def save(self, path: str | Path) -> None:
        """Write an .npz atomically (a concurrent reader never sees half a file)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        with open(tmp, "wb") as fh:
            np.savez(fh, **{f.name: getattr(self, f.name) for f in fields(self)})
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | Path) -> GraspSet:
        with np.load(path) as z:
            return cls(**{f.name: np.asarray(z[f.name], dtype=np.float64) for f in fields(cls)})


# ------------------------------------------------------------------------------------------ solids
@dataclass(frozen=True)
class Solids:
    """Convex primitives (boxes, z-axis cylinders and convex hulls) with world poses, for inside and
    overlap tests.

    ``half`` is the half-extent of each solid's bounding box in its own frame: (r, r, h/2) for a
    cylinder, whose radius is ``half[0]``. A convex hull (a mesh class's piece) has its world
    bounding box as (identity ``rot``, ``centre``, ``half``) and its world vertices, face normals and
    offsets in ``hull`` (None for the primitives).
    """

    is_cylinder: NDArray[np.bool_]
    rot: F64
    centre: F64
    half: F64
    hull: NDArray[np.object_]

    @classmethod
    def from_parts(cls, parts: tuple[Part, ...] | list[Part], pose: F64 | None = None) -> Solids:
        import trimesh
        pose = np.eye(4) if pose is None else pose
        rots, cens, halves, cyl, hulls = [], [], [], [], []
        for p in parts:
            t = pose @ pose_matrix(p.position_m, p.quat_xyzw)
            if p.kind == "convex":
                mesh = trimesh.convex.convex_hull(np.asarray(p.vertices_m) @ t[:3, :3].T + t[:3, 3])
                verts = np.asarray(mesh.vertices)
                planes = np.hstack([mesh.face_normals, np.einsum("fk,fk->f", mesh.face_normals,
                                                                   verts[mesh.faces[:, 0]])[:, None]])
                planes = np.unique(np.round(planes, 9), axis=0)  # a facet's triangles share one plane
                normals, offsets = planes[:, :3], planes[:, 3]
                lo, hi = verts.min(axis=0), verts.max(axis=0)
                rots.append(np.eye(3))
                cens.append((lo + hi) / 2)
                halves.append((hi - lo) / 2)
                cyl.append(False)
                hulls.append((verts, np.asarray(mesh.faces), normals, offsets))
                continue
            rots.append(t[:3, :3])
            cens.append(t[:3, 3])
            hulls.append(None)
            if p.kind == "box":
                halves.append(np.asarray(p.size_m) / 2)
                cyl.append(False)
            else:
                r, h = p.size_m
                halves.append(np.array([r, r, h / 2]))
                cyl.append(True)
        hull = np.empty(len(hulls), dtype=object)
        hull[:] = hulls
        return cls(np.array(cyl, dtype=bool), np.array(rots).reshape(-1, 3, 3), np.array(cens).reshape(-1, 3),
                   np.array(halves).reshape(-1, 3), hull)

    @classmethod
    def from_boxes(cls, boxes: list[tuple[F64, F64]]) -> Solids:
        """Axis-aligned boxes given as (centre, half-extents), e.g. ``ShelfSpec.boards()``."""
        n = len(boxes)
        return cls(np.zeros(n, dtype=bool), np.tile(np.eye(3), (n, 1, 1)),
                   np.array([c for c, _ in boxes]).reshape(-1, 3), np.array([h for _, h in boxes]).reshape(-1, 3),
                   np.full(n, None, dtype=object))

    @classmethod
    def concat(cls, items: list[Solids]) -> Solids:
        if not items:
            return cls(np.zeros(0, dtype=bool), np.zeros((0, 3, 3)), np.zeros((0, 3)), np.zeros((0, 3)),
                       np.zeros(0, dtype=object))
        return cls(*(np.concatenate([getattr(s, f.name) for s in items]) for f in fields(cls)))

    def __len__(self) -> int:
        return len(self.half)

    def contains(self, points: F64, tol: float = 0.0) -> NDArray[np.bool_]:
        """Points [N, 3] strictly inside the union (shrunk by ``tol``)."""
        inside = np.zeros(len(points), dtype=bool)
        for i in range(len(self)):
            if self.hull[i] is not None:  # the points in its bounding box, against its face planes
                _, _, normals, offsets = self.hull[i]
                near = np.flatnonzero(np.all(np.abs(points - self.centre[i]) < self.half[i] - tol, axis=1))
                inside[near] |= np.all(points[near] @ normals.T - offsets < -tol, axis=1)
                continue
            local = (points - self.centre[i]) @ self.rot[i]
            h = self.half[i] - tol
            if self.is_cylinder[i]:
                inside |= (np.hypot(local[:, 0], local[:, 1]) < h[0]) & (np.abs(local[:, 2]) < h[2])
            else:
                inside |= np.all(np.abs(local) < h, axis=1)
        return inside

    def _fcl(self, i: int) -> fcl.CollisionObject:
        if self.hull[i] is not None:
            verts, faces, _, _ = self.hull[i]
            flat = np.hstack([np.full((len(faces), 1), 3), faces]).ravel()
            return fcl.CollisionObject(fcl.Convex(verts, len(faces), flat), fcl.Transform())
        h = self.half[i]
        geom = fcl.Cylinder(h[0], 2 * h[2]) if self.is_cylinder[i] else fcl.Box(*(2 * h))
        return fcl.CollisionObject(geom, fcl.Transform(self.rot[i], self.centre[i]))

    def overlaps_boxes(self, centre: F64, rot: F64, half: F64, chunk: int = 4096) -> NDArray[np.bool_]:
        """For oriented boxes [M] (centre [M, 3], rot [M, 3, 3], half [M, 3]): intersects any solid?"""
        hit = np.zeros(len(centre), dtype=bool)
        if not len(self) or not len(centre):
            return hit
        fcl_objs: dict[int, fcl.CollisionObject] = {}
        request = fcl.CollisionRequest()
        reach = np.linalg.norm(half, axis=1)
        for s in range(len(self)):
            # broad phase: bounding spheres; then the exact separating-axis test on the boxes
            near = np.flatnonzero(~hit & (np.linalg.norm(centre - self.centre[s], axis=1)
                                          <= reach + np.linalg.norm(self.half[s])))
            for lo in range(0, len(near), chunk):
                idx = near[lo:lo + chunk]
                cand = idx[boxes_overlap(centre[idx], rot[idx], half[idx], self.centre[s], self.rot[s], self.half[s])]
                if not self.is_cylinder[s] and self.hull[s] is None:  # a box: the test was exact
                    hit[cand] = True
                    continue
                obj = fcl_objs.setdefault(s, self._fcl(s))
                for m in cand:
                    box = fcl.CollisionObject(fcl.Box(*(2 * half[m])), fcl.Transform(rot[m], centre[m]))
                    result = fcl.CollisionResult()
                    fcl.collide(box, obj, request, result)
                    hit[m] = result.is_collision
        return hit


def gripper_boxes(poses: F64, openings: F64, gripper: GripperSpec) -> tuple[F64, F64, F64]:
    """World (centre [3G, 3], rot [3G, 3, 3], half [3G, 3]) of the left finger, right finger and
    palm of G grasps (grasp-major order)."""
    c0 = np.array([c for c, _ in gripper.boxes(0.0)])
    c1 = np.array([c for c, _ in gripper.boxes(1.0)])
    # GripperSpec.boxes is affine in the opening: interpolate instead of one call per grasp
    local_c = c0[None] + np.asarray(openings, dtype=np.float64)[:, None, None] * (c1 - c0)[None]
    half = np.array([h for _, h in gripper.boxes(0.0)])
    rot = poses[:, :3, :3]
    centre = np.einsum("gij,gkj->gki", rot, local_c) + poses[:, None, :3, 3]
    return (centre.reshape(-1, 3), np.repeat(rot, 3, axis=0), np.tile(half, (len(poses), 1)))


def grasp_collides(grasps: GraspSet, solids: Solids, gripper: GripperSpec, margin_m: float) -> NDArray[np.bool_]:
    """[G]: does the gripper of each grasp (opening = min(width + margin, max)) hit the solids?"""
    if not len(grasps):
        return np.zeros(0, dtype=bool)
    openings = np.minimum(grasps.width + margin_m, gripper.max_opening_m)
    centre, rot, half = gripper_boxes(grasps.poses(), openings, gripper)
    return np.asarray(solids.overlaps_boxes(centre, rot, half).reshape(-1, 3).any(axis=1), dtype=bool)


# --------------------------------------------------------------------------------------- sampling
def _perp_basis(v: F64) -> tuple[F64, F64]:
    helper = np.where(np.abs(v[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    u = np.cross(v, helper)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(v, u)


def _first_exit(
    origins: F64, dirs: F64, mesh: trimesh.Trimesh, solids: Solids, eps: float, chunk: int = 256
) -> tuple[F64, F64]:
    """Distance to and outward normal at the first point where each ray leaves the solid union.

    All ray-triangle hits (Moller-Trumbore, vectorised); a hit counts as the exit if the triangle
    faces along the ray and the point ``eps`` beyond is outside every part, which skips the inner
    faces of overlapping parts. Misses get distance inf.
    """
    tri = mesh.triangles
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    normals = mesh.face_normals
    dist = np.full(len(origins), np.inf)
    normal = np.zeros((len(origins), 3))
    for lo in range(0, len(origins), chunk):
        o, d = origins[lo:lo + chunk], dirs[lo:lo + chunk]
        p = np.cross(d[:, None, :], e2[None])
        det = np.einsum("tk,rtk->rt", e1, p)
        inv = 1.0 / np.where(np.abs(det) > 1e-15, det, np.inf)
        s = o[:, None, :] - v0[None]
        u = np.einsum("rtk,rtk->rt", s, p) * inv
        q = np.cross(s, e1[None])
        v = np.einsum("rk,rtk->rt", d, q) * inv
        t = np.einsum("tk,rtk->rt", e2, q) * inv
        ok = (np.abs(det) > 1e-15) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        ok &= np.einsum("rk,tk->rt", d, normals) > 0
        r_idx, t_idx = np.nonzero(ok)
        th = t[r_idx, t_idx]
        beyond = o[r_idx] + (th + eps)[:, None] * d[r_idx]
        leave = ~solids.contains(beyond)
        r_idx, t_idx, th = r_idx[leave], t_idx[leave], th[leave]
        order = np.lexsort((th, r_idx))  # per ray, nearest first
        r_idx, t_idx, th = r_idx[order], t_idx[order], th[order]
        first = np.r_[True, r_idx[1:] != r_idx[:-1]]
        dist[lo + r_idx[first]] = th[first]
        normal[lo + r_idx[first]] = normals[t_idx[first]]
    return dist, normal


def sample_antipodal(cls: ObjectClass, config: AntipodalConfig, gripper: GripperSpec) -> GraspSet:
    """Antipodal, collision-free grasps of one class in its object frame (no cache)."""
    import trimesh
    rng = np.random.default_rng([config.seed, cls.class_id])
    mesh = class_mesh(cls)
    solids = Solids.from_parts(cls.parts)
    eps = 5e-4  # > the 0.11 mm sagitta of the prism meshes of the cylinders
    count = int(np.clip(round(config.samples_per_m2 * mesh.area), config.min_samples, config.max_samples))
    pts, face = trimesh.sample.sample_surface(mesh, count, seed=rng)
    n = mesh.face_normals[face]
    on_boundary = ~solids.contains(pts + eps * n) & solids.contains(pts - eps * n)
    pts, n = pts[on_boundary], n[on_boundary]

    # Ray directions: uniform in the friction cone around the inward normal.
    cos_cone = 1.0 / np.sqrt(1.0 + config.friction**2)  # cos(atan(mu))
    cos_t = rng.uniform(cos_cone, 1.0, len(pts))
    phi = rng.uniform(0.0, 2 * np.pi, len(pts))
    u, v = _perp_basis(-n)
    sin_t = np.sqrt(1.0 - cos_t**2)
    d = cos_t[:, None] * -n + sin_t[:, None] * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v)
    dist, n_opp = _first_exit(pts, d, mesh, solids, eps)

    keep = (dist >= config.min_width_m) & (dist <= gripper.max_opening_m)
    keep &= np.einsum("ij,ij->i", n_opp, d) >= cos_cone  # friction cone at the opposite contact
    keep &= np.einsum("ij,ij->i", -n, d) >= cos_cone - 1e-12
    pts, d, dist = pts[keep], d[keep], dist[keep]

    k = config.n_approach
    theta = rng.uniform(0.0, 2 * np.pi, (len(pts), 1)) + 2 * np.pi * np.arange(k) / k
    u, v = _perp_basis(d)
    approach = np.cos(theta)[..., None] * u[:, None] + np.sin(theta)[..., None] * v[:, None]
    rep = np.repeat(np.arange(len(pts)), k)
    cand = GraspSet(pts[rep], pts[rep] + dist[rep, None] * d[rep], approach.reshape(-1, 3), d[rep], dist[rep])
    grasps = cand.subset(~grasp_collides(cand, solids, gripper, config.width_margin_m))
    if config.symmetric:
        flipped = GraspSet(grasps.opposite, grasps.contacts, grasps.approach, -grasps.baseline, grasps.width)
        grasps = GraspSet(*(np.concatenate([getattr(grasps, f.name), getattr(flipped, f.name)])
                            for f in fields(GraspSet)))
    return grasps


# ------------------------------------------------------------------------------------------ cache
def cache_dir() -> Path:
    """``$MSMEM_CACHE_DIR/antipodal`` or ``~/.cache/msmem/antipodal``."""
    return cache_root("antipodal")


def cache_key(cls: ObjectClass, config: AntipodalConfig, gripper: GripperSpec) -> str:
    """Hash of everything the grasps depend on: class geometry, sampling config, gripper, version."""
    blob = json.dumps(
        {"v": CACHE_VERSION, "parts": [p.model_dump() for p in cls.parts],
         "config": config.model_dump(), "gripper": gripper.model_dump()},
        sort_keys=True,
    )
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def class_grasps(
    class_name: str | ObjectClass,
    config: AntipodalConfig | None = None,
    gripper: GripperSpec | None = None,
    directory: str | Path | None = None,
    use_cache: bool = True,
) -> GraspSet:
    """Grasps of a class in its object frame, from ``<cache>/<class>-<key>.npz`` or generated and cached."""
    config = config or AntipodalConfig()
    gripper = gripper or GripperSpec()
    cls = object_class(class_name) if isinstance(class_name, str) else class_name
    path = Path(directory or cache_dir()) / f"{cls.name}-{cache_key(cls, config, gripper)}.npz"
    if use_cache and path.exists():
        return GraspSet.load(path)
    grasps = sample_antipodal(cls, config, gripper)
    if use_cache:
        grasps.save(path)
    return grasps


# ------------------------------------------------------------------------------------------ scenes
def grasps_in_scene(
    scene: SceneSpec,
    poses: dict[int, F64] | None = None,
    config: AntipodalConfig | None = None,
    gripper: GripperSpec | None = None,
    directory: str | Path | None = None,
) -> dict[int, GraspSet]:
    """Per object id, its class grasps in the world frame minus those whose gripper hits the shelf
    boards or another object. ``poses`` (object id -> 4x4) override the spec's poses, e.g. settled
    poses read back from a simulator."""
    gripper = gripper or GripperSpec()
    margin = (config or AntipodalConfig()).width_margin_m
    poses = poses or {}
    world = {o.id: np.asarray(poses.get(o.id, o.pose()), dtype=np.float64) for o in scene.objects}
    solids = {o.id: Solids.from_parts(o.object_class.parts, world[o.id]) for o in scene.objects}
    boards = Solids.from_boxes(scene.shelf.boards())
    out: dict[int, GraspSet] = {}
    for o in scene.objects:
        grasps = class_grasps(o.object_class, config, gripper, directory).transformed(world[o.id])
        others = Solids.concat([boards, *(s for i, s in solids.items() if i != o.id)])
        out[o.id] = grasps.subset(~grasp_collides(grasps, others, gripper, margin))
    return out
