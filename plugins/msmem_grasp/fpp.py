"""Frontier point projection (paper eq. frontier_projection): pcd = FPP(E[Phi^O]).

Camera rays of the visited views (or of virtual front cameras) are cast into the expected occupancy
p of a belief. Per ray, the exact DDA traversal of :mod:`msmem_core.map.raycast` (as in
``raycast.first_hit``) finds the first voxel with p > threshold; the crossing is then located
continuously: p is sampled trilinearly (voxel centres as samples) at sub-voxel steps from one voxel
before that voxel to its exit, and the first upward crossing of the threshold is interpolated
linearly between two samples. One numba kernel (:func:`_ray_crossings`) does both per ray, from the
camera poses and pixel directions (no per-ray arrays are built first).

The analytic observation update marks as occupied the voxel that *contains* a depth return, after
free voxels, so the 0.5-isosurface of the trilinear field lies on the voxel boundary in front of
the true surface, while the surface itself is anywhere inside the hit voxel. ``surface_offset_voxels``
moves each point that far along its ray: 0.5 (the default) puts it at the middle of the hit voxel,
which halves the expected distance to a surface lying anywhere inside that voxel.

Points seen by several rays are deduplicated on a grid of ``dedup_m`` (first ray wins), and up to
``num_points`` are drawn without replacement, seeded. Per drawn point, the outward normal is the
negative gradient of p (Gaussian-derivative filtered, sampled trilinearly), turned to face the
camera. The filter runs only over the box of voxels the drawn points' interpolation reads, widened
by the filter's radius (clipped to the grid): inside that margin every filtered value is the one
the whole-grid filter gives, bit for bit, since each 1-D pass reads only voxels within its radius
and the grid's own borders are extended the same way. The trilinear sampling
(:func:`_trilinear_at`) does scipy's ``map_coordinates(order=1, mode="nearest")`` arithmetic in
the same order, so its values are those of :func:`_trilinear`, bit for bit.
Everything runs as array operations or numba kernels; no Python loop touches rays or points.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.map import raycast
from msmem_core.map.belief import EvidentialMap
from msmem_core.world.camera import CameraConfig
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ShelfSpec
from msmem_core.world.viewpoints import ViewpointConfig, front_views, generate_viewpoints

F32 = NDArray[np.float32]
FEATURES = ("nx", "ny", "nz", "occupancy")
"""Per-point input features of FE-vMF built from a :class:`SurfaceCloud` (``SurfaceCloud.features``)."""


class FPPConfig(BaseModel):
    """Frontier point projection: rays, surface refinement, normals and sampling."""

    model_config = ConfigDict(extra="forbid")

    num_points: int = Field(4096, ge=1)
    """Points sampled from the projected surface (the paper uses 1e4 on a GPU)."""
    threshold: float = Field(0.5, gt=0.0, lt=1.0)
    """Surface = first crossing of expected occupancy above this along a ray."""
    ray_stride_px: int = Field(4, ge=1)
    """Cast every n-th pixel in u and v of each camera (4: 160 x 120 rays per 640 x 480 view)."""
    samples_per_voxel: int = Field(4, ge=1)
    """Trilinear samples per voxel length when locating the crossing."""
    surface_offset_voxels: float = Field(0.5, ge=0.0, le=1.0)
    """Move each point this many voxels further along its ray (see the module docstring)."""
    normal_sigma_voxels: float = Field(1.0, gt=0.0)
    """Gaussian-derivative scale of the occupancy gradient the normals come from."""
    dedup_m: float | None = Field(None, gt=0.0)
    """Keep one point per cell of this size (None: half a voxel)."""
    camera: CameraConfig = CameraConfig()
    seed: int = 0


@dataclass(frozen=True)
class SurfaceCloud:
    """FPP output, all float32: points [N, 3] (world), outward unit normals [N, 3], expected occupancy
    of the hit voxel [N]; ``voxel`` [N] flat index of the hit voxel (int64); ``view`` [N] index of
    the camera whose ray produced the point (int64)."""

    points: F32
    normals: F32
    occupancy: F32
    voxel: NDArray[np.int64]
    view: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.points)

    @classmethod
    def empty(cls) -> SurfaceCloud:
        z3 = np.zeros((0, 3), np.float32)
        return cls(z3, z3.copy(), np.zeros(0, np.float32), np.zeros(0, np.int64), np.zeros(0, np.int64))

    def subset(self, keep: NDArray[np.intp] | NDArray[np.bool_]) -> SurfaceCloud:
        return SurfaceCloud(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})

    def features(self) -> F32:
        """FE-vMF input features [N, 4]: the normal and the hit voxel's expected occupancy (``FEATURES``)."""
        return np.concatenate([self.normals, self.occupancy[:, None]], axis=1).astype(np.float32)


def virtual_front_views(viewpoints: ViewpointConfig | None = None) -> NDArray[np.float64]:
    """Camera-to-world poses [G, 4, 4] of the virtual front cameras (``viewpoints.front_views``: each
    grid's centre view), used when no view has been visited (e.g. right after a manipulation)."""
    cfg = viewpoints or ViewpointConfig()
    if cfg.poses_file is not None:  # read from a file each time: the file may change
        return generate_viewpoints(cfg)[front_views(cfg)]
    return _generated_front_views(cfg).copy()


@functools.lru_cache(maxsize=8)
def _generated_front_views(cfg: ViewpointConfig) -> NDArray[np.float64]:
    """:func:`virtual_front_views` of a generated viewpoint set: the grasp skill asks at every step before
    the first manipulation, and generating the whole set takes about 15 ms."""
    return generate_viewpoints(cfg)[front_views(cfg)]


def _trilinear(field: NDArray[np.floating], grid: GridSpec, points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Trilinear interpolation of a voxel field [X, Y, Z] (values at voxel centres) at world points
    [..., 3]; outside the outermost centres the border value is held."""
    from scipy import ndimage
    coords = (points - grid.origin) / grid.voxel_m - 0.5
    flat = coords.reshape(-1, 3).T
    out = ndimage.map_coordinates(np.asarray(field, dtype=np.float64), flat, order=1, mode="nearest")
    return out.reshape(points.shape[:-1])


def occupancy_normals(p: NDArray[np.floating], sigma_voxels: float) -> NDArray[np.float64]:
    """Negative Gaussian-derivative gradient of p, [3, X, Y, Z] (per voxel, unnormalised, in 1/voxel)."""
    from scipy import ndimage
    p64 = np.asarray(p, dtype=np.float64)
    grads = [
        -ndimage.gaussian_filter(p64, sigma_voxels, order=tuple(int(a == b) for b in range(3)), mode="nearest")
        for a in range(3)
    ]
    return np.stack(grads)


def camera_rays(poses: NDArray[np.float64], camera: CameraConfig, stride: int) -> tuple[NDArray[np.float64], ...]:
    """(origins [M, 3], dirs [M, 3] with unit optical-axis component, view index [M]) of every
    stride-th pixel of every camera pose [V, 4, 4]."""
    d_cam = camera.pixel_rays(stride).reshape(-1, 3)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    dirs = np.einsum("vij,rj->vri", poses[:, :3, :3], d_cam).reshape(-1, 3)
    view = np.repeat(np.arange(len(poses)), len(d_cam))
    origins = poses[view, :3, 3]
    return np.ascontiguousarray(origins), np.ascontiguousarray(dirs), view


@njit(cache=True, fastmath=False, inline="always")
def _trilinear_at(f, lo0, lo1, lo2, n0, n1, n2, c0, c1, c2):
    """Trilinear value at voxel coordinates (c0, c1, c2) (voxel centres at integers) of a field of
    grid shape (n0, n1, n2) given on the box starting at voxel (lo0, lo1, lo2) (``f`` holds that box;
    it must hold every voxel read). Indices are clamped to the grid (scipy's ``mode="nearest"``);
    weights, products and sum in the order of scipy's ``map_coordinates(order=1)``, so the value is
    the same to the bit."""
    f0, f1, f2 = math.floor(c0), math.floor(c1), math.floor(c2)
    a0, a1, a2 = 1.0 - (c0 - f0), 1.0 - (c1 - f1), 1.0 - (c2 - f2)
    i, j, k = int(f0), int(f1), int(f2)
    acc = 0.0
    for di in range(2):
        ii = min(max(i + di, 0), n0 - 1) - lo0
        wi = a0 if di == 0 else 1.0 - a0
        for dj in range(2):
            jj = min(max(j + dj, 0), n1 - 1) - lo1
            wj = a1 if dj == 0 else 1.0 - a1
            for dk in range(2):
                kk = min(max(k + dk, 0), n2 - 1) - lo2
                wk = a2 if dk == 0 else 1.0 - a2
                acc += float(f[ii, jj, kk]) * wi * wj * wk
    return acc


@njit(cache=True, fastmath=False, parallel=True)
def _ray_crossings(p, occ, rot, pos, d_cam, g0, s, n, t_min, t_max, frac, threshold, lo, hi, tol, offset):
    """Per camera ray (pose v's rotation ``rot[v]`` [3, 3] times pixel direction ``d_cam[r]``, from
    ``pos[v]``; ray number ``v * R + r``): the first voxel with ``occ != 0`` (``raycast`` DDA,
    ``t`` in [t_min, t_max]), the continuous crossing of ``threshold`` by the trilinear p (float32
    [X, Y, Z]) sampled at ``t_start + frac * (t_out - t_start)``, ``t_start`` one voxel length before
    the hit voxel's entry (the DDA entry when no sample pair crosses), kept if the crossing lies in
    the box [lo - tol, hi + tol], moved ``offset`` voxel lengths along the ray.

    Returns the hit voxel (int64 [M], -1: no hit or dropped), the surface point [M, 3] and the unit
    ray direction [M, 3] (both meaningless where the voxel is -1)."""
    nv, nr = rot.shape[0], d_cam.shape[0]
    m_rays = nv * nr
    k = frac.shape[0]
    voxel = np.full(m_rays, -1, dtype=np.int64)
    point = np.empty((m_rays, 3), dtype=np.float64)
    unit = np.empty((m_rays, 3), dtype=np.float64)
    nbuf = n[0] + n[1] + n[2]
    n0, n1, n2 = n[0], n[1], n[2]
    chunk = 64
    for c in prange((m_rays + chunk - 1) // chunk):
        vox = np.empty(nbuf, dtype=np.int64)
        tin = np.empty(nbuf, dtype=np.float64)
        tout = np.empty(nbuf, dtype=np.float64)
        ts = np.empty(k, dtype=np.float64)
        vals = np.empty(k, dtype=np.float64)
        for q in range(c * chunk, min(m_rays, (c + 1) * chunk)):
            v, r = q // nr, q % nr
            ox, oy, oz = pos[v, 0], pos[v, 1], pos[v, 2]
            # rot[v] @ d_cam[r], summed as numpy's einsum sums it in camera_rays (the same rays, bit for bit)
            dx = (rot[v, 0, 0] * d_cam[r, 0] + rot[v, 0, 2] * d_cam[r, 2]) + rot[v, 0, 1] * d_cam[r, 1]
            dy = (rot[v, 1, 0] * d_cam[r, 0] + rot[v, 1, 2] * d_cam[r, 2]) + rot[v, 1, 1] * d_cam[r, 1]
            dz = (rot[v, 2, 0] * d_cam[r, 0] + rot[v, 2, 2] * d_cam[r, 2]) + rot[v, 2, 1] * d_cam[r, 1]
            m = raycast.traverse(ox, oy, oz, dx, dy, dz, g0, s, n, t_min, t_max, occ, vox, tin, tout)
            if m == 0 or occ[vox[m - 1]] == 0:
                continue
            t_in, t_out = tin[m - 1], tout[m - 1]
            dn = math.sqrt(dx * dx + dy * dy + dz * dz)
            t_voxel = s / dn
            t_start = max(t_in - t_voxel, t_min)
            first = -1
            for j in range(k):
                t = t_start + frac[j] * (t_out - t_start)
                ts[j] = t
                vals[j] = _trilinear_at(p, 0, 0, 0, n0, n1, n2, (ox + t * dx - g0[0]) / s - 0.5,
                                        (oy + t * dy - g0[1]) / s - 0.5, (oz + t * dz - g0[2]) / s - 0.5)
                if vals[j] > threshold:
                    first = j
                    break
            if first < 0:
                t_cross = t_in  # no trilinear crossing (grazing ray): the DDA entry
            elif first == 0:
                t_cross = ts[0]
            else:
                v0, v1 = vals[first - 1], vals[first]
                w = (threshold - v0) / (v1 - v0) if v1 > v0 else 0.0
                w = min(max(w, 0.0), 1.0)
                t_cross = ts[first - 1] + w * (ts[first] - ts[first - 1])
            ax, ay, az = ox + t_cross * dx, oy + t_cross * dy, oz + t_cross * dz
            if not (lo[0] - tol <= ax <= hi[0] + tol and lo[1] - tol <= ay <= hi[1] + tol
                    and lo[2] - tol <= az <= hi[2] + tol):
                continue
            t_surf = t_cross + offset * t_voxel
            voxel[q] = vox[m - 1]
            point[q, 0], point[q, 1], point[q, 2] = ox + t_surf * dx, oy + t_surf * dy, oz + t_surf * dz
            unit[q, 0], unit[q, 1], unit[q, 2] = dx / dn, dy / dn, dz / dn
    return voxel, point, unit


@njit(cache=True, fastmath=False)
def _trilinear_points(f, lo, n, g0, s, points):
    """:func:`_trilinear_at` of the field box ``f`` (from voxel ``lo`` of a grid of shape ``n``) at
    world points [N, 3]: the values of :func:`_trilinear` on the whole field."""
    out = np.empty(points.shape[0], dtype=np.float64)
    for i in range(points.shape[0]):
        out[i] = _trilinear_at(f, lo[0], lo[1], lo[2], n[0], n[1], n[2], (points[i, 0] - g0[0]) / s - 0.5,
                               (points[i, 1] - g0[1]) / s - 0.5, (points[i, 2] - g0[2]) / s - 0.5)
    return out


@dataclass(frozen=True)
class _Surface:
    """Deduplicated first crossings before the normals: points [N, 3], unit ray directions [N, 3],
    hit voxel [N], view [N]."""

    points: NDArray[np.float64]
    unit: NDArray[np.float64]
    voxel: NDArray[np.int64]
    view: NDArray[np.int64]


def _surface(p: F32, grid: GridSpec, poses: NDArray[np.float64], cfg: FPPConfig,
             bounds: tuple[NDArray[np.float64], NDArray[np.float64]] | None) -> _Surface | None:
    """The deduplicated first crossings of :func:`project_surface` (None if there are none)."""
    occ = np.ascontiguousarray((p > cfg.threshold).ravel().astype(np.uint8))
    if len(poses) == 0 or not occ.any():
        return None
    d_cam = np.ascontiguousarray(cfg.camera.pixel_rays(cfg.ray_stride_px).reshape(-1, 3))
    g0, s, n = raycast.grid_params(grid)
    lo, hi = (np.full(3, -np.inf), np.full(3, np.inf)) if bounds is None else bounds
    frac = np.linspace(0.0, 1.0, 2 * cfg.samples_per_voxel + 1)
    voxel, pts, unit = _ray_crossings(
        p, occ, np.ascontiguousarray(poses[:, :3, :3]), np.ascontiguousarray(poses[:, :3, 3]), d_cam, g0, s, n,
        cfg.camera.near_m, cfg.camera.far_m, frac, cfg.threshold, np.asarray(lo, np.float64),
        np.asarray(hi, np.float64), 0.5 * s, cfg.surface_offset_voxels,
    )
    kept = np.flatnonzero(voxel >= 0)
    if not len(kept):
        return None
    pts, unit, voxel, view = pts[kept], unit[kept], voxel[kept], kept // len(d_cam)

    # Deduplicate on a grid of dedup_m (first ray in camera order wins: deterministic).
    cell_m = cfg.dedup_m or 0.5 * s
    cells = np.floor((pts - grid.origin) / cell_m).astype(np.int64)
    cells -= cells.min(axis=0)
    key = np.ravel_multi_index(cells.T, tuple(int(v) + 1 for v in cells.max(axis=0)))  # 1-D: a fast unique
    _, keep = np.unique(key, return_index=True)
    keep = np.sort(keep)
    return _Surface(pts[keep], unit[keep], voxel[keep], view[keep])


def point_normals(p: NDArray[np.floating], grid: GridSpec, points: NDArray[np.float64],
                  sigma_voxels: float) -> NDArray[np.float64]:
    """:func:`occupancy_normals` sampled trilinearly at world points [N, 3] ([N, 3], unnormalised),
    equal to the whole-grid filter's to the bit but filtered only over the box the points read
    (see the module docstring)."""
    if not len(points):
        return np.zeros((0, 3))
    g0, s, n = raycast.grid_params(grid)
    base = np.floor((points - g0) / s - 0.5).astype(np.int64)  # lower interpolation corner per point
    radius = int(4.0 * float(sigma_voxels) + 0.5)  # gaussian_filter's (truncate=4)
    lo = np.maximum(np.minimum(base.min(axis=0), n - 1) - radius, 0)
    hi = np.minimum(np.maximum(base.max(axis=0) + 1, 0) + radius, n - 1) + 1
    box = np.asarray(p, dtype=np.float64)[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    grad = occupancy_normals(box, sigma_voxels)
    return np.stack([_trilinear_points(grad[a], lo, n, g0, s, points) for a in range(3)], axis=1)


def _cloud(p: F32, grid: GridSpec, surf: _Surface, sigma_voxels: float) -> SurfaceCloud:
    """The :class:`SurfaceCloud` of crossings: normals facing the camera, occupancy of the hit voxel."""
    nrm = point_normals(p, grid, surf.points, sigma_voxels)
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    unit_d = surf.unit
    nrm = np.where(length > 1e-6, nrm / np.maximum(length, 1e-12), -unit_d)
    facing = np.einsum("ij,ij->i", nrm, unit_d)
    nrm = np.where(facing[:, None] > 0.0, -nrm, nrm)  # a seen surface faces its camera
    return SurfaceCloud(
        points=surf.points.astype(np.float32),
        normals=nrm.astype(np.float32),
        occupancy=p.ravel()[surf.voxel].astype(np.float32),
        voxel=surf.voxel.astype(np.int64),
        view=surf.view.astype(np.int64),
    )


def project_surface(
    p: NDArray[np.floating],
    grid: GridSpec,
    poses: NDArray[np.float64],
    config: FPPConfig | None = None,
    bounds: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
) -> SurfaceCloud:
    """All first-crossing points of the rays of ``poses`` into the occupancy field p [X, Y, Z],
    deduplicated but not subsampled. With ``bounds`` (lower, upper corners), crossings farther than
    half a voxel outside that box are dropped (e.g. the top of the shelf's top board, seen from above
    through the grid margin)."""
    cfg = config or FPPConfig()
    p = np.ascontiguousarray(p, dtype=np.float32)
    surf = _surface(p, grid, np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4), cfg, bounds)
    return SurfaceCloud.empty() if surf is None else _cloud(p, grid, surf, cfg.normal_sigma_voxels)


def shelf_bounds(shelf: ShelfSpec) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The region whose bounding surfaces FPP keeps: the shelf interior, open towards the front (-y)."""
    lo = shelf.interior_lower.copy()
    lo[1] = -np.inf
    return lo, shelf.interior_upper


def _sample_index(size: int, num_points: int, seed: int | np.random.Generator | None) -> NDArray[np.intp] | None:
    """Sorted indices of ``num_points`` of ``size`` items drawn without replacement (None: keep all)."""
    if size <= num_points:
        return None
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    return np.sort(rng.choice(size, num_points, replace=False))


def sample_cloud(cloud: SurfaceCloud, num_points: int, seed: int | np.random.Generator | None = 0) -> SurfaceCloud:
    """Up to ``num_points`` points drawn without replacement (all of them, in order, if fewer)."""
    keep = _sample_index(len(cloud), num_points, seed)
    return cloud if keep is None else cloud.subset(keep)


def frontier_points(
    belief: EvidentialMap,
    poses: NDArray[np.float64] | None = None,
    config: FPPConfig | None = None,
    seed: int | np.random.Generator | None = None,
    shelf: ShelfSpec | None = None,
) -> SurfaceCloud:
    """FPP(E[Phi^O]): the surface cloud of ``belief`` seen from camera ``poses`` [V, 4, 4] (the
    visited views; None: :func:`virtual_front_views`), sampled to ``config.num_points``. ``seed``
    overrides ``config.seed``. With ``shelf``, only surfaces bounding the shelf's interior (and the
    space in front of it) are kept. An empty or all-unknown belief gives an empty cloud."""
    cfg = config or FPPConfig()
    poses = virtual_front_views() if poses is None else poses
    bounds = shelf_bounds(shelf) if shelf is not None else None
    p = np.ascontiguousarray(belief.expected_occupancy(), dtype=np.float32)
    surf = _surface(p, belief.grid, np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4), cfg, bounds)
    if surf is None:
        return SurfaceCloud.empty()
    # the draw of sample_cloud, before the normals: they are computed for the drawn points only
    keep = _sample_index(len(surf.points), cfg.num_points, cfg.seed if seed is None else seed)
    if keep is not None:
        surf = _Surface(surf.points[keep], surf.unit[keep], surf.voxel[keep], surf.view[keep])
    return _cloud(p, belief.grid, surf, cfg.normal_sigma_voxels)
