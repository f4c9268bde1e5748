"""Visibility on the ground truth: which objects the views see, and which voxels any view can observe.

All by ray casting (open3d) from the candidate viewpoints through every ``stride``-th pixel; the
shelf boards occlude.

A camera ray's hit should mark the voxel that contains ``hit + 1e-4 * voxel * ray_direction``
(a point just past the surface, inside the solid): that voxel is occupied under the occupancy rule
of ``msmem_core.world.voxelize`` even when the surface lies exactly on a voxel boundary (top faces
of objects resting at z = 0).
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from msmem_core.world.camera import CameraConfig
from msmem_core.world.grid import GridSpec
from msmem_core.world.meshes import object_mesh, shelf_meshes
from msmem_core.world.scene import ObjectSpec, ShelfSpec
from msmem_core.world.voxelize import Poses, current_pose, voxelize

if TYPE_CHECKING:
    import open3d as o3d
    import trimesh


def _tensor(a: NDArray[Any]) -> o3d.core.Tensor:
    """``a`` as an open3d tensor. open3d is imported on first use: importing it takes about 0.7 s, which
    every command that never casts a ray (``--help``, a refused input) would otherwise pay."""
    import open3d

    return open3d.core.Tensor.from_numpy(np.ascontiguousarray(a))

HIT_NUDGE_VOXELS = 1e-4
"""Hits are pushed this fraction of a voxel along the ray before picking their voxel (see module doc)."""

MIN_VISIBLE_PIXELS = 10
"""An object seen by fewer strided pixels (stride 4) summed over all views counts as hidden: 10 is
under 160 full-resolution pixels over all 300 views, at most a sliver of about 1.5 x 1.5 cm."""


def camera_rays(
    viewpoints: NDArray[np.float64], camera: CameraConfig, stride: int
) -> tuple[NDArray[np.float32], NDArray[np.float64]]:
    """Rays ``[V, P, 6]`` (origin on the near plane, direction with unit optical-axis component).

    With this parametrisation a hit's ``t_hit + near`` is the z-depth, and geometry nearer than
    the near plane is clipped as a renderer would. Also returns the pixel-grid directions (P, 3).
    """
    d_cam = camera.pixel_rays(stride).reshape(-1, 3)
    d_world = d_cam.astype(np.float32)[None] @ viewpoints[:, :3, :3].transpose(0, 2, 1).astype(np.float32)
    origins = viewpoints[:, None, :3, 3].astype(np.float32) + np.float32(camera.near_m) * d_world
    rays = np.concatenate([origins, d_world], axis=-1)
    return rays, d_cam


def _rays_at(
    flat_ids: NDArray[np.int64], viewpoints: NDArray[np.float64], camera: CameraConfig, stride: int
) -> NDArray[np.float32]:
    """Rows of ``camera_rays(viewpoints, camera, stride)[0].reshape(-1, 6)`` at ``flat_ids``."""
    d_cam = camera.pixel_rays(stride).reshape(-1, 3).astype(np.float32)
    views, pix = np.divmod(flat_ids, len(d_cam))
    rot = viewpoints[:, :3, :3].astype(np.float32)
    d = np.einsum("nij,nj->ni", rot[views], d_cam[pix])
    return np.concatenate([viewpoints[views, :3, 3].astype(np.float32) + np.float32(camera.near_m) * d, d], axis=1)


def _raycasting_scene(meshes: Sequence[trimesh.Trimesh]) -> tuple[o3d.t.geometry.RaycastingScene, list[int]]:
    import open3d

    scene = open3d.t.geometry.RaycastingScene()
    ids = [
        scene.add_triangles(_tensor(m.vertices.astype(np.float32)), _tensor(m.faces.astype(np.uint32)))
        for m in meshes
    ]
    return scene, ids


def _cast(
    scene: o3d.t.geometry.RaycastingScene, rays: NDArray[np.float32], max_t: float
) -> tuple[NDArray[np.float32], NDArray[np.int64]]:
    """t_hit and geometry id (-1 for no hit within max_t) of rays (N, 6)."""
    ans = scene.cast_rays(_tensor(rays))
    t = ans["t_hit"].numpy()
    gid = ans["geometry_ids"].numpy().astype(np.int64)
    gid[~(t <= max_t)] = -1  # inf (miss) and beyond far
    return t, gid


@dataclass(frozen=True)
class Visibility:
    """How many (strided) pixels of each view see each object first: ``pixel_counts[v, n]``."""

    object_ids: tuple[int, ...]
    pixel_counts: NDArray[np.int64]
    stride: int

    def visible(self, min_pixels: int = 1) -> NDArray[np.bool_]:
        """``[V, N]`` mask: object n counts as visible in view v."""
        return self.pixel_counts >= min_pixels

    def per_view(self, min_pixels: int = 1) -> list[set[int]]:
        """Ids of the objects visible in each view."""
        vis = self.visible(min_pixels)
        return [{self.object_ids[n] for n in np.nonzero(row)[0]} for row in vis]

    def hidden(self, min_pixels: int = MIN_VISIBLE_PIXELS) -> list[int]:
        """Ids of the objects with fewer than ``min_pixels`` pixels summed over all views."""
        total = self.pixel_counts.sum(axis=0)
        return [oid for oid, c in zip(self.object_ids, total, strict=True) if c < min_pixels]


def visible_objects(
    objects: Sequence[ObjectSpec],
    shelf: ShelfSpec,
    viewpoints: NDArray[np.float64],
    camera: CameraConfig,
    stride: int = 4,
    poses: Poses | None = None,
    views_per_batch: int = 50,
) -> Visibility:
    """Count, per view, the pixels (every ``stride``-th) whose first hit is each object.

    The shelf boards occlude. Rays of ``views_per_batch`` views are cast in one open3d call.
    """
    meshes = [object_mesh(o, current_pose(o, poses)) for o in objects] + shelf_meshes(shelf)
    scene, _ = _raycasting_scene(meshes)
    n_obj, n_views = len(objects), len(viewpoints)
    counts = np.zeros((n_views, n_obj), dtype=np.int64)
    max_t = camera.far_m - camera.near_m
    for v0 in range(0, n_views, views_per_batch):
        rays, _ = camera_rays(viewpoints[v0 : v0 + views_per_batch], camera, stride)
        nv, n_pix = rays.shape[:2]
        _, gid = _cast(scene, rays.reshape(-1, 6), max_t)
        gid = gid.reshape(nv, n_pix)
        key = (np.arange(nv)[:, None] * (n_obj + 1) + np.where((gid >= 0) & (gid < n_obj), gid, n_obj)).ravel()
        counts[v0 : v0 + nv] = np.bincount(key, minlength=nv * (n_obj + 1)).reshape(nv, n_obj + 1)[:, :n_obj]
    return Visibility(tuple(o.id for o in objects), counts, stride)


def hidden_objects(
    objects: Sequence[ObjectSpec],
    shelf: ShelfSpec,
    viewpoints: NDArray[np.float64],
    camera: CameraConfig,
    stride: int = 4,
    min_pixels: int = MIN_VISIBLE_PIXELS,
    poses: Poses | None = None,
) -> list[int]:
    """Ids of the objects seen by no viewpoint: fewer than ``min_pixels`` strided pixels over all views."""
    return visible_objects(objects, shelf, viewpoints, camera, stride, poses).hidden(min_pixels)


def _box_ray_indices(
    bounds: NDArray[np.float64], viewpoints: NDArray[np.float64], camera: CameraConfig, stride: int
) -> NDArray[np.int64]:
    """Sorted flat indices into ``camera_rays(...).reshape(-1, 6)`` of the rays that may hit a box.

    ``bounds`` is the box's (lower, upper) corner pair; per view, the strided pixels inside its
    projected bounding rectangle (one pixel of slack).
    """
    lo, hi = bounds[0], bounds[1]
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    rot, eye = viewpoints[:, :3, :3], viewpoints[:, :3, 3]
    pc = np.matmul(corners[None] - eye[:, None], rot)  # [V, 8, 3] camera-frame corners
    k = camera.intrinsics
    n_u, n_v = len(np.arange(stride / 2, camera.width_px, stride)), len(np.arange(stride / 2, camera.height_px, stride))
    z = pc[..., 2]
    behind = np.any(z <= 1e-6, axis=1)  # box reaches behind the camera: take the whole image
    zs = np.where(z > 1e-6, z, 1.0)
    u, v = k[0, 0] * pc[..., 0] / zs + k[0, 2], k[1, 1] * pc[..., 1] / zs + k[1, 2]
    # Strided pixel c has its centre at stride / 2 + c * stride.
    c0 = np.where(behind, 0, np.ceil((u.min(1) - 1 - stride / 2) / stride)).clip(0, n_u).astype(np.int64)
    c1 = np.where(behind, n_u - 1, np.floor((u.max(1) + 1 - stride / 2) / stride)).clip(-1, n_u - 1).astype(np.int64)
    r0 = np.where(behind, 0, np.ceil((v.min(1) - 1 - stride / 2) / stride)).clip(0, n_v).astype(np.int64)
    r1 = np.where(behind, n_v - 1, np.floor((v.max(1) + 1 - stride / 2) / stride)).clip(-1, n_v - 1).astype(np.int64)
    out = []
    for view in np.nonzero((c1 >= c0) & (r1 >= r0))[0]:
        rows = np.arange(r0[view], r1[view] + 1)
        cols = np.arange(c0[view], c1[view] + 1)
        out.append((view * n_u * n_v + rows[:, None] * n_u + cols[None, :]).ravel())
    return np.concatenate(out) if out else np.zeros(0, dtype=np.int64)


def object_pixel_counts(
    objects: Sequence[ObjectSpec],
    target_ids: Sequence[int],
    shelf: ShelfSpec,
    viewpoints: NDArray[np.float64],
    camera: CameraConfig,
    stride: int = 4,
    poses: Poses | None = None,
) -> dict[int, int]:
    """Strided pixels over all views whose first hit is each target object (as ``visible_objects``).

    Casts only the rays inside the targets' projected bounding boxes, so checking a few small
    objects costs a fraction of a full ``visible_objects``.
    """
    meshes = [object_mesh(o, current_pose(o, poses)) for o in objects]
    scene, _ = _raycasting_scene(meshes + shelf_meshes(shelf))
    index = {o.id: n for n, o in enumerate(objects)}
    n_rays = len(viewpoints) * camera.pixel_rays(stride).shape[0] * camera.pixel_rays(stride).shape[1]
    selected = np.zeros(n_rays, dtype=bool)
    for t in target_ids:
        selected[_box_ray_indices(meshes[index[t]].bounds, viewpoints, camera, stride)] = True
    counts = {int(t): 0 for t in target_ids}
    if not selected.any():
        return counts
    rays = _rays_at(np.flatnonzero(selected), viewpoints, camera, stride)
    _, gid = _cast(scene, rays, camera.far_m - camera.near_m)
    hits = np.bincount(gid[gid >= 0], minlength=len(objects) + 1)
    return {int(t): int(hits[index[t]]) for t in target_ids}


class InsertionProbe:
    """Pixels an object would get if it were added to a fixed scene, for many trial poses.

    Builds the scene (objects and shelf boards) once; each probe casts the rays in the new object's
    projected bounding boxes at the object alone, then tests the rays that hit it for occlusion
    by the scene before the hit. Equal to ``object_pixel_counts([*objects, obj], [obj.id])``.
    """

    def __init__(
        self,
        objects: Sequence[ObjectSpec],
        shelf: ShelfSpec,
        viewpoints: NDArray[np.float64],
        camera: CameraConfig,
        stride: int = 4,
        poses: Poses | None = None,
    ) -> None:
        meshes = [object_mesh(o, current_pose(o, poses)) for o in objects] + shelf_meshes(shelf)
        self._scene, _ = _raycasting_scene(meshes)
        self._views, self._camera, self._stride = viewpoints, camera, stride

    def pixel_count(self, obj: ObjectSpec, pose: NDArray[np.float64] | None = None) -> int:
        """Strided pixels over all views whose first hit would be ``obj`` (at ``pose`` or its own)."""
        mesh = object_mesh(obj, pose)
        idx = _box_ray_indices(mesh.bounds, self._views, self._camera, self._stride)
        if len(idx) == 0:
            return 0
        rays = _rays_at(idx, self._views, self._camera, self._stride)
        alone, _ = _raycasting_scene([mesh])
        t_obj, g_obj = _cast(alone, rays, self._camera.far_m - self._camera.near_m)
        hit = rays[g_obj >= 0]
        hit[:, 3:] *= t_obj[g_obj >= 0, None]  # the object's surface point is now at t = 1
        occluded = self._scene.test_occlusions(_tensor(hit), tnear=0.0, tfar=1.0).numpy()
        return int(np.count_nonzero(~occluded))


def observable_mask(
    objects: Sequence[ObjectSpec],
    poses: Poses | None,
    shelf: ShelfSpec,
    viewpoints: NDArray[np.float64],
    camera: CameraConfig,
    grid: GridSpec,
    stride: int = 4,
) -> NDArray[np.bool_]:
    """Voxels ``[X, Y, Z]`` that count for ``observable_iou``: all except self-occluded object interiors.

    A ground-truth-occupied voxel is observable iff some ray (every ``stride``-th pixel of every
    viewpoint) hits it while its object stands alone in the empty shelf (boards still occlude);
    free voxels are always observable. Only rays whose pixel lies in the projection of the
    object's bounding box are cast. The mask is the same for every method on a scene.
    """
    occ, _ = voxelize(objects, grid, poses)
    seen = np.zeros(grid.size, dtype=bool)
    boards = shelf_meshes(shelf)
    max_t = camera.far_m - camera.near_m
    nudge = HIT_NUDGE_VOXELS * grid.voxel_m
    table = ray_table(viewpoints, camera, stride)
    for obj in objects:
        mesh = object_mesh(obj, current_pose(obj, poses))
        scene, ids = _raycasting_scene([mesh, *boards])
        rays = table[_box_ray_indices(mesh.bounds, viewpoints, camera, stride)]
        if len(rays) == 0:
            continue
        t, gid = _cast(scene, rays, max_t)
        _mark_hits(rays, t, gid == ids[0], grid.origin, grid.voxel_m, np.asarray(grid.shape, dtype=np.int64), nudge,
                   seen)
    return (~occ) | seen.reshape(grid.shape)


def ray_table(viewpoints: NDArray[np.float64], camera: CameraConfig, stride: int) -> NDArray[np.float32]:
    """All rays ``_rays_at(arange(V * P), ...)`` [V * P, 6], each row equal to the bit to what
    ``_rays_at`` gives for it in any subset (read-only; the last two tables are kept: an episode asks
    for the same one at every refresh of its observable mask)."""
    vp = np.ascontiguousarray(viewpoints, dtype=np.float64)
    key = (vp.shape, hashlib.sha1(vp.tobytes()).hexdigest(), camera.model_dump_json(), int(stride))
    table = _RAY_TABLES.get(key)
    if table is None:
        n = len(vp) * camera.pixel_rays(stride).reshape(-1, 3).shape[0]
        table = _rays_at(np.arange(n, dtype=np.int64), vp, camera, stride)
        table.flags.writeable = False
        while len(_RAY_TABLES) >= 2:
            _RAY_TABLES.pop(next(iter(_RAY_TABLES)))
        _RAY_TABLES[key] = table
    return table


_RAY_TABLES: dict[tuple[object, ...], NDArray[np.float32]] = {}


@njit(cache=True)
def _mark_hits(rays, t, hit, origin, voxel, shape, nudge, seen):
    """Mark in ``seen`` (flat) the voxel of each hit ray's point just past the surface: in float64,
    in numpy's order of operations (``r[:3] + (t + nudge / |d|) * d``, ``|d|`` summed left to right
    as ``np.linalg.norm`` does along a row of three), so the voxels are those numpy would pick."""
    nx, ny, nz = shape[0], shape[1], shape[2]
    for i in range(rays.shape[0]):
        if not hit[i]:
            continue
        dx, dy, dz = np.float64(rays[i, 3]), np.float64(rays[i, 4]), np.float64(rays[i, 5])
        s = np.float64(t[i]) + nudge / math.sqrt((dx * dx + dy * dy) + dz * dz)
        ix = math.floor(((np.float64(rays[i, 0]) + s * dx) - origin[0]) / voxel)
        iy = math.floor(((np.float64(rays[i, 1]) + s * dy) - origin[1]) / voxel)
        iz = math.floor(((np.float64(rays[i, 2]) + s * dz) - origin[2]) / voxel)
        if 0 <= ix < nx and 0 <= iy < ny and 0 <= iz < nz:
            seen[(ix * ny + iy) * nz + iz] = True


def count_views_seeing(
    points: NDArray[np.float64],
    objects: Sequence[ObjectSpec],
    shelf: ShelfSpec,
    viewpoints: NDArray[np.float64],
    camera: CameraConfig,
    poses: Poses | None = None,
    views_per_batch: int = 50,
) -> NDArray[np.int64]:
    """Number of viewpoints that see each world point (N, 3): in the image, within near..far, unoccluded.

    Occlusion is tested on the segment from the point to the camera (objects and shelf boards);
    a point inside an object counts as occluded.
    """
    meshes = [object_mesh(o, current_pose(o, poses)) for o in objects] + shelf_meshes(shelf)
    scene, _ = _raycasting_scene(meshes)
    pts = np.asarray(points, dtype=np.float64)
    counts = np.zeros(len(pts), dtype=np.int64)
    half_w, half_h = camera.width_px / 2 / camera.fy, camera.height_px / 2 / camera.fy
    for v0 in range(0, len(viewpoints), views_per_batch):
        vp = viewpoints[v0 : v0 + views_per_batch]
        eye = vp[:, :3, 3]
        rel = pts[None] - eye[:, None]  # [V, N, 3]
        pc = np.matmul(rel, vp[:, :3, :3])  # camera-frame coordinates
        z = pc[..., 2]
        in_view = (z >= camera.near_m) & (z <= camera.far_m)
        in_view &= (np.abs(pc[..., 0]) <= half_w * z) & (np.abs(pc[..., 1]) <= half_h * z)
        if not in_view.any():
            continue
        vi, pi = np.nonzero(in_view)
        rays = np.concatenate([pts[pi], -rel[vi, pi]], axis=1).astype(np.float32)
        occluded = scene.test_occlusions(_tensor(rays), tnear=1e-6, tfar=1.0).numpy()
        counts += np.bincount(pi[~occluded], minlength=len(pts))
    return counts


def occluders(
    objects: Sequence[ObjectSpec],
    target_ids: Sequence[int],
    shelf: ShelfSpec,
    viewpoints: NDArray[np.float64],
    camera: CameraConfig,
    stride: int = 4,
    poses: Poses | None = None,
) -> dict[int, dict[int, int]]:
    """Per target object, the objects that hide it: ``{target: {occluder: pixels}}``.

    A strided pixel counts for occluder ``o`` when the target alone (in the empty shelf) would be hit
    by its ray and ``o`` is what the ray hits first in the full scene. Pixels the shelf boards take
    are nobody's. Rays are cast only inside each target's projected bounding box.
    """
    meshes = [object_mesh(o, current_pose(o, poses)) for o in objects]
    scene, _ = _raycasting_scene(meshes + shelf_meshes(shelf))
    index = {o.id: n for n, o in enumerate(objects)}
    max_t = camera.far_m - camera.near_m
    out: dict[int, dict[int, int]] = {}
    for t in target_ids:
        n = index[t]
        rays = _rays_at(_box_ray_indices(meshes[n].bounds, viewpoints, camera, stride), viewpoints, camera, stride)
        out[int(t)] = {}
        if len(rays) == 0:
            continue
        alone, _ = _raycasting_scene([meshes[n]])
        _, g_alone = _cast(alone, rays, max_t)
        rays = rays[g_alone >= 0]
        if len(rays) == 0:
            continue
        _, gid = _cast(scene, rays, max_t)
        counts = np.bincount(gid[(gid >= 0) & (gid < len(objects)) & (gid != n)], minlength=len(objects))
        out[int(t)] = {objects[k].id: int(c) for k, c in enumerate(counts) if c > 0}
    return out
