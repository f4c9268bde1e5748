"""Frontier point projection (paper eq. frontier_projection): pcd = FPP(E[Phi^O]).

Camera rays of the visited views (or of virtual front cameras) are cast into the expected occupancy
p of a belief. Per ray, the exact DDA traversal (:func:`msmem_core.raycast.first_hit`) finds the
first voxel with p > threshold; the crossing is then located continuously: p is sampled trilinearly
(voxel centres as samples) at sub-voxel steps from one voxel before that voxel to its exit, and the
first upward crossing of the threshold is interpolated linearly between two samples.

The analytic observation update marks as occupied the voxel that *contains* a depth return, after
free voxels, so the 0.5-isosurface of the trilinear field lies on the voxel boundary in front of
the true surface, while the surface itself is anywhere inside the hit voxel. ``surface_offset_voxels``
moves each point that far along its ray: 0.5 (the default) halves the mean distance to the true
surface (measured in docs/grasp-learning.md).

Per point, the outward normal is the negative gradient of p (Gaussian-derivative filtered, sampled
trilinearly), turned to face the camera; points seen by several rays are deduplicated on a grid
of ``dedup_m`` (first ray wins), and up to ``num_points`` are drawn without replacement, seeded.
Everything runs as array operations or numba kernels; no Python loop touches rays or points.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from msmem_core import raycast
from msmem_core.belief import EvidentialMap
from msmem_core.camera import CameraConfig
from msmem_core.grid import GridSpec
from msmem_core.scene import ShelfSpec
from msmem_core.viewpoints import ViewpointConfig, generate_viewpoints

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
    """Camera-to-world poses [G, 4, 4] of one virtual camera per viewpoint grid (the grid's centre
    view), used when no view has been visited (e.g. right after a manipulation)."""
    cfg = viewpoints or ViewpointConfig()
    poses = generate_viewpoints(cfg)
    g = cfg.grid
    centre = (g // 2) * g + g // 2
    return poses[[k * g * g + centre for k in range(len(cfg.targets_x_m))]]


def _trilinear(field: NDArray[np.floating], grid: GridSpec, points: NDArray[np.float64]) -> NDArray[np.float64]:
    """Trilinear interpolation of a voxel field [X, Y, Z] (values at voxel centres) at world points
    [..., 3]; outside the outermost centres the border value is held."""
    coords = (points - grid.origin) / grid.voxel_m - 0.5
    flat = coords.reshape(-1, 3).T
    out = ndimage.map_coordinates(np.asarray(field, dtype=np.float64), flat, order=1, mode="nearest")
    return out.reshape(points.shape[:-1])


def occupancy_normals(p: NDArray[np.floating], sigma_voxels: float) -> NDArray[np.float64]:
    """Negative Gaussian-derivative gradient of p, [3, X, Y, Z] (per voxel, unnormalised, in 1/voxel)."""
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
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    p = np.asarray(p, dtype=np.float32)
    occ = np.ascontiguousarray((p > cfg.threshold).ravel().astype(np.uint8))
    if len(poses) == 0 or not occ.any():
        return SurfaceCloud.empty()
    origins, dirs, view = camera_rays(poses, cfg.camera, cfg.ray_stride_px)
    g0, s, n = raycast.grid_params(grid)
    t_in, t_out, idx = raycast.first_hit(occ, origins, dirs, g0, s, n, cfg.camera.near_m, cfg.camera.far_m)
    hit = idx >= 0
    if not hit.any():
        return SurfaceCloud.empty()
    o, d, t_in, t_out, idx, view = origins[hit], dirs[hit], t_in[hit], t_out[hit], idx[hit], view[hit]
    dn = np.linalg.norm(d, axis=1)
    t_voxel = s / dn  # ray parameter per voxel length

    # Continuous crossing: trilinear p sampled from one voxel before the hit voxel to its exit.
    k = 2 * cfg.samples_per_voxel + 1
    t_start = np.maximum(t_in - t_voxel, cfg.camera.near_m)
    frac = np.linspace(0.0, 1.0, k)
    ts = t_start[:, None] + frac[None] * (t_out - t_start)[:, None]  # [M, K]
    vals = _trilinear(p, grid, o[:, None, :] + ts[..., None] * d[:, None, :])
    above = vals > cfg.threshold
    first = np.argmax(above, axis=1)
    found = above[np.arange(len(first)), first]
    prev = np.maximum(first - 1, 0)
    rows = np.arange(len(first))
    v0, v1 = vals[rows, prev], vals[rows, first]
    w = np.where(v1 > v0, (cfg.threshold - v0) / np.where(v1 > v0, v1 - v0, 1.0), 0.0)
    t_cross = ts[rows, prev] + np.clip(w, 0.0, 1.0) * (ts[rows, first] - ts[rows, prev])
    t_cross = np.where(first == 0, ts[:, 0], t_cross)
    t_cross = np.where(found, t_cross, t_in)  # no trilinear crossing (grazing ray): the DDA entry
    if bounds is not None:
        at = o + t_cross[:, None] * d
        tol = 0.5 * s
        inside = np.all((at >= np.asarray(bounds[0]) - tol) & (at <= np.asarray(bounds[1]) + tol), axis=1)
        if not inside.any():
            return SurfaceCloud.empty()
        o, d, dn, t_voxel, t_cross, idx, view = (a[inside] for a in (o, d, dn, t_voxel, t_cross, idx, view))
    t_surf = t_cross + cfg.surface_offset_voxels * t_voxel
    pts = o + t_surf[:, None] * d

    # Deduplicate on a grid of dedup_m (first ray in camera order wins: deterministic).
    cell_m = cfg.dedup_m or 0.5 * s
    cells = np.floor((pts - grid.origin) / cell_m).astype(np.int64)
    cells -= cells.min(axis=0)
    key = np.ravel_multi_index(cells.T, tuple(int(v) + 1 for v in cells.max(axis=0)))  # 1-D: a fast unique
    _, keep = np.unique(key, return_index=True)
    keep = np.sort(keep)
    pts, d, dn, idx, view = pts[keep], d[keep], dn[keep], idx[keep], view[keep]

    grad = occupancy_normals(p, cfg.normal_sigma_voxels)
    nrm = np.stack([_trilinear(grad[a], grid, pts) for a in range(3)], axis=1)
    length = np.linalg.norm(nrm, axis=1, keepdims=True)
    unit_d = d / dn[:, None]
    nrm = np.where(length > 1e-6, nrm / np.maximum(length, 1e-12), -unit_d)
    facing = np.einsum("ij,ij->i", nrm, unit_d)
    nrm = np.where(facing[:, None] > 0.0, -nrm, nrm)  # a seen surface faces its camera
    return SurfaceCloud(
        points=pts.astype(np.float32),
        normals=nrm.astype(np.float32),
        occupancy=p.ravel()[idx].astype(np.float32),
        voxel=idx.astype(np.int64),
        view=view.astype(np.int64),
    )


def shelf_bounds(shelf: ShelfSpec) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The region whose bounding surfaces FPP keeps: the shelf interior, open towards the front (-y)."""
    lo = shelf.interior_lower.copy()
    lo[1] = -np.inf
    return lo, shelf.interior_upper


def sample_cloud(cloud: SurfaceCloud, num_points: int, seed: int | np.random.Generator | None = 0) -> SurfaceCloud:
    """Up to ``num_points`` points drawn without replacement (all of them, in order, if fewer)."""
    if len(cloud) <= num_points:
        return cloud
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    return cloud.subset(np.sort(rng.choice(len(cloud), num_points, replace=False)))


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
    cloud = project_surface(belief.expected_occupancy(), belief.grid, poses, cfg, bounds)
    return sample_cloud(cloud, cfg.num_points, cfg.seed if seed is None else seed)
