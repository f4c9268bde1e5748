"""Brute-force float64 IG reference, for tests and ``msmem perf ig`` only (slow: a Python loop per ray).

Its traversal is independent of the DDA in :mod:`msmem_core.map.raycast`: Siddon's method. All
crossings of the ray with every grid plane inside the clipped ray interval are computed at once,
sorted, and each segment between consecutive crossings is assigned to the voxel holding its
midpoint; zero-length segments (edge/corner touches) are dropped.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from msmem_core.world.grid import GridSpec


def traverse(
    origin: NDArray[np.floating], direction: NDArray[np.floating], grid: GridSpec, t_min: float, t_max: float
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """Voxels of one ray in order: flat indices and their ``[t_in, t_out)`` intervals."""
    o = np.asarray(origin, dtype=np.float64)
    d = np.asarray(direction, dtype=np.float64)
    lo, hi, n, s = grid.origin, grid.upper_m, np.asarray(grid.shape), grid.voxel_m
    t0, t1 = float(t_min), float(t_max)
    for a in range(3):
        if d[a] == 0.0:
            if not lo[a] <= o[a] < hi[a]:
                return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
            continue
        ta, tb = sorted(((lo[a] - o[a]) / d[a], (hi[a] - o[a]) / d[a]))
        t0, t1 = max(t0, ta), min(t1, tb)
    if not t0 < t1:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0)
    ts = [np.array([t0, t1])]
    for a in range(3):
        if d[a] != 0.0:
            planes = lo[a] + np.arange(n[a] + 1) * s
            tc = (planes - o[a]) / d[a]
            ts.append(tc[(tc > t0) & (tc < t1)])
    t = np.unique(np.concatenate(ts))
    a_in, a_out = t[:-1], t[1:]
    keep = a_out > a_in
    a_in, a_out = a_in[keep], a_out[keep]
    mid = o[None, :] + 0.5 * (a_in + a_out)[:, None] * d[None, :]
    ijk = np.clip(np.floor((mid - lo) / s).astype(np.int64), 0, n - 1)
    flat = (ijk[:, 0] * n[1] + ijk[:, 1]) * n[2] + ijk[:, 2]
    # consecutive segments in one voxel (crossings that coincide within rounding) are merged
    first = np.ones(len(flat), bool)
    first[1:] = flat[1:] != flat[:-1]
    starts = np.flatnonzero(first)
    ends = np.append(starts[1:], len(flat)) - 1
    return flat[starts], a_in[starts], a_out[ends]


def ray_ig(
    p: NDArray[np.floating], h: NDArray[np.floating], voxels: NDArray[np.int64], eps: float = 0.0
) -> tuple[float, float]:
    """IG of one ray over its ordered voxels, and the entropy left on the ray after an early exit.

    ``sum_k H_k prod_{j<k} (1 - p_j)``, stopped after the first voxel where the transmission is
    <= eps (the same rule as the kernel). The skipped tail is bounded by eps * (entropy left).
    """
    pv = np.asarray(p, dtype=np.float64)[voxels]
    hv = np.asarray(h, dtype=np.float64)[voxels]
    trans = np.cumprod(1.0 - pv)
    before = np.concatenate([[1.0], trans[:-1]])
    stop = np.flatnonzero(trans <= eps)
    end = int(stop[0]) + 1 if len(stop) else len(voxels)
    return float(np.sum(hv[:end] * before[:end])), float(np.sum(hv[end:]))


def ig_rays_reference(
    p: NDArray[np.floating],
    h: NDArray[np.floating],
    origins: NDArray[np.floating],
    dirs: NDArray[np.floating],
    grid: GridSpec,
    t_min: float,
    t_max: float,
    eps: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-ray IG [V, R] and the entropy left after an early exit [V, R] (origins [V, 3], dirs [V, R, 3])."""
    nv, nr = dirs.shape[:2]
    ig = np.zeros((nv, nr))
    rest = np.zeros((nv, nr))
    for v in range(nv):
        for r in range(nr):
            vox = traverse(origins[v], dirs[v, r], grid, t_min, t_max)[0]
            ig[v, r], rest[v, r] = ray_ig(p, h, vox, eps)
    return ig, rest


def ig_views_reference(
    p: NDArray[np.floating],
    h: NDArray[np.floating],
    origins: NDArray[np.floating],
    dirs: NDArray[np.floating],
    grid: GridSpec,
    t_min: float,
    t_max: float,
    eps: float = 0.0,
) -> NDArray[np.float64]:
    """IG per view [V], float64."""
    return ig_rays_reference(p, h, origins, dirs, grid, t_min, t_max, eps)[0].sum(axis=1)


def after_view_reference(
    p: NDArray[np.floating],
    h: NDArray[np.floating],
    origin: NDArray[np.floating],
    dirs: NDArray[np.floating],
    grid: GridSpec,
    t_min: float,
    t_max: float,
) -> NDArray[np.float32]:
    """Entropy after a view: 0 on each ray's voxels up to and including its first p == 1 voxel."""
    out = np.array(h, dtype=np.float32, copy=True)
    for r in range(dirs.shape[0]):
        vox = traverse(origin, dirs[r], grid, t_min, t_max)[0]
        full = np.flatnonzero(np.asarray(p)[vox] >= 1.0)
        out[vox[: int(full[0]) + 1 if len(full) else len(vox)]] = 0.0
    return out
