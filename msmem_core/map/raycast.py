"""Numba ray kernels over a voxel grid: exact Amanatides-Woo DDA traversal.

A grid is passed as ``(g0, s, n)``: minimum corner (3 floats), voxel edge, shape (3 ints), from
:func:`grid_params`. Voxel (i, j, k) covers ``[g0 + i*s, g0 + (i+1)*s)`` and has flat index
``(i*ny + j)*nz + k`` (C order of ``[X, Y, Z]`` arrays). A ray is ``o + t*d`` for t in
``[t_min, t_max]``; ``d`` need not be unit length (camera rays use d = R @ (x, y, 1), so t is the
z-depth). A ray is clipped to the grid box with the slab test (once, in a :class:`RayTable`, for
the IG kernels), then its voxels are visited in order with the parameter interval ``[t_in, t_out)``
of each (Amanatides-Woo: the next boundary crossing per axis, advanced by ``s / |d|``; rounding
~1e-15 relative). Voxels the ray only touches at an edge or corner (zero length) are skipped, so the
sequence is exactly the voxels the segment passes through (tested against Siddon's method in
:mod:`msmem_core.map.ig_reference`).

Parallel kernels (``prange``) write shared uint8 masks / float32 arrays only with constant stores
(1 into a mask, 0 into an entropy): two threads storing the same value to the same byte race
benignly (whichever store wins, the value is the same; aligned byte/word stores do not tear on the
CPUs we run on). No kernel does a read-modify-write on memory another thread writes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from msmem_core.world.grid import GridSpec

GridParams = tuple[NDArray[np.float64], float, NDArray[np.int64]]
_CHUNK = 64
"""Rays per parallel work item in the per-ray kernels (each item owns one traversal buffer)."""


def grid_params(grid: GridSpec) -> GridParams:
    """``(g0, s, n)`` of a grid, as the kernels take them."""
    return grid.origin.astype(np.float64), float(grid.voxel_m), np.asarray(grid.shape, dtype=np.int64)


# ------------------------------------------------------------------------------------ traversal
@njit(cache=True, fastmath=False, inline="always")
def _slab(o: float, d: float, lo: float, hi: float, t0: float, t1: float) -> tuple[float, float]:
    """Clip [t0, t1] to the slab lo <= o + t*d <= hi (t0 >= t1 afterwards if the ray misses it)."""
    if d != 0.0:
        ta = (lo - o) / d
        tb = (hi - o) / d
        if ta > tb:
            ta, tb = tb, ta
        if ta > t0:
            t0 = ta
        if tb < t1:
            t1 = tb
    elif o < lo or o >= hi:
        t0 = 1.0
        t1 = 0.0
    return t0, t1


@njit(cache=True, fastmath=False, inline="always")
def _clip(ox, oy, oz, dx, dy, dz, g0, s, n, t_min, t_max):
    """Slab test of the ray against the grid box: (t_enter, t_exit), empty when t_enter >= t_exit."""
    t0, t1 = _slab(ox, dx, g0[0], g0[0] + n[0] * s, t_min, t_max)
    t0, t1 = _slab(oy, dy, g0[1], g0[1] + n[1] * s, t0, t1)
    return _slab(oz, dz, g0[2], g0[2] + n[2] * s, t0, t1)


@njit(cache=True, fastmath=False, inline="always")
def _axis_init(o: float, d: float, t0: float, g0: float, s: float, n: int) -> tuple[int, int, float, float]:
    """DDA start on one axis: voxel index at t0, step, t of the first boundary crossing, t per voxel."""
    i = math.floor((o + t0 * d - g0) / s)
    if i < 0:
        i = 0
    elif i >= n:
        i = n - 1
    if d > 0.0:
        return i, 1, (g0 + (i + 1) * s - o) / d, s / d
    if d < 0.0:
        return i, -1, (g0 + i * s - o) / d, -s / d
    return i, 0, np.inf, np.inf


@njit(cache=True, fastmath=False, inline="always")
def _dda_start(ox, oy, oz, dx, dy, dz, t0, gx, gy, gz, s, nx, ny, nz):
    """DDA state of a ray clipped to the grid, at t0 (:func:`_axis_init` on each axis).

    Returns ``(ix, iy, iz, idx, tx, ty, tz, sx, sy, sz, kx, ky, kz)``: the voxel and its flat index,
    each axis's next boundary crossing, step (+-1 or 0) and t per voxel, as :func:`_dda_next` takes them.
    Scalars in and out: array arguments cost a reference-count update per ray, and a tuple of tuples
    trips numba's array analysis in the ``prange`` kernels.
    """
    ix, sx, tx, kx = _axis_init(ox, dx, t0, gx, s, nx)
    iy, sy, ty, ky = _axis_init(oy, dy, t0, gy, s, ny)
    iz, sz, tz, kz = _axis_init(oz, dz, t0, gz, s, nz)
    return ix, iy, iz, (ix * ny + iy) * nz + iz, tx, ty, tz, sx, sy, sz, kx, ky, kz


@njit(cache=True, fastmath=False, inline="always")
def _dda_exit(tx: float, ty: float, tz: float) -> tuple[float, int]:
    """Where the ray leaves the current voxel: (t, axis) of the nearest boundary crossing (x, then y on ties)."""
    if tx <= ty and tx <= tz:
        return tx, 0
    if ty <= tz:
        return ty, 1
    return tz, 2


@njit(cache=True, fastmath=False, inline="always")
def _dda_next(ax, tn, t1, ix, iy, iz, idx, tx, ty, tz, sx, sy, sz, kx, ky, kz, nx, ny, nz):
    """Step across the boundary at ``tn`` on axis ``ax`` (from :func:`_dda_exit`) into the next voxel.

    Returns ``(more, ix, iy, iz, idx, tx, ty, tz)``; ``more`` is False when the ray ends: ``tn >= t1``
    or the step leaves the grid (the other values are then meaningless).
    """
    if tn >= t1:
        return False, ix, iy, iz, idx, tx, ty, tz
    if ax == 0:
        ix += sx
        return 0 <= ix < nx, ix, iy, iz, idx + sx * ny * nz, tx + kx, ty, tz
    if ax == 1:
        iy += sy
        return 0 <= iy < ny, ix, iy, iz, idx + sy * nz, tx, ty + ky, tz
    iz += sz
    return 0 <= iz < nz, ix, iy, iz, idx + sz, tx, ty, tz + kz


@njit(cache=True, fastmath=False)
def traverse(ox, oy, oz, dx, dy, dz, g0, s, n, t_min, t_max, stop, vox, tin, tout):
    """Write the ray's voxels in order into ``vox`` with their intervals ``[tin, tout)``; return the count.

    Stops after the first voxel with ``stop[idx] != 0`` (pass an empty ``stop`` for none). Buffers
    need ``n[0] + n[1] + n[2]`` entries.
    """
    t0, t1 = _clip(ox, oy, oz, dx, dy, dz, g0, s, n, t_min, t_max)
    if t0 >= t1:
        return 0
    return _traverse_clipped(ox, oy, oz, dx, dy, dz, g0, s, n, t0, t1, stop, vox, tin, tout)


@njit(cache=True, fastmath=False, inline="always")
def _traverse_clipped(ox, oy, oz, dx, dy, dz, g0, s, n, t0, t1, stop, vox, tin, tout):
    """:func:`traverse` of a ray already clipped to the grid (t0 < t1 from :func:`_clip`)."""
    nx, ny, nz = n[0], n[1], n[2]
    ix, iy, iz, idx, tx, ty, tz, sx, sy, sz, kx, ky, kz = _dda_start(
        ox, oy, oz, dx, dy, dz, t0, g0[0], g0[1], g0[2], s, nx, ny, nz
    )
    use_stop = stop.shape[0] > 0
    t = t0
    m = 0
    while True:
        tn, ax = _dda_exit(tx, ty, tz)
        te = tn if tn < t1 else t1
        if te > t:
            vox[m] = idx
            tin[m] = t
            tout[m] = te
            m += 1
            if use_stop and stop[idx] != 0:
                break
        more, ix, iy, iz, idx, tx, ty, tz = _dda_next(ax, tn, t1, ix, iy, iz, idx, tx, ty, tz,
                                                      sx, sy, sz, kx, ky, kz, nx, ny, nz)
        if not more:
            break
        t = tn
    return m


# ------------------------------------------------------------------------------------------ IG
@njit(cache=True, fastmath=False)
def _ray_ig(p, h, ox, oy, oz, dx, dy, dz, g0, s, n, t0, t1, eps):
    """IG of one ray clipped to [t0, t1): ``sum_k H_k prod_{j<k} (1 - p_j)``, stopping once the
    product is <= eps (:func:`_ray_ig_stop` without the stop)."""
    return _ray_ig_stop(p, h, ox, oy, oz, dx, dy, dz, g0, s, n, t0, t1, eps)[0]


@njit(cache=True, fastmath=False, parallel=True)
def clip_rays(origins, dirs, g0, s, n, t_min, t_max):
    """Grid entry and exit t of every ray (origins [V, 3], dirs [V, R, 3]); entry >= exit: a miss."""
    nv, nr = dirs.shape[0], dirs.shape[1]
    t_enter = np.empty((nv, nr), dtype=np.float64)
    t_exit = np.empty((nv, nr), dtype=np.float64)
    for v in prange(nv):
        for r in range(nr):
            t_enter[v, r], t_exit[v, r] = _clip(
                origins[v, 0], origins[v, 1], origins[v, 2], dirs[v, r, 0], dirs[v, r, 1], dirs[v, r, 2],
                g0, s, n, t_min, t_max,
            )
    return t_enter, t_exit


@dataclass
class RayTable:
    """The rays of V views, with what can be computed once: each ray's grid entry and exit.

    Per view, the rays that cross the grid come first (``count[v]`` of them), in camera order; the
    remaining slots are rays that miss the grid. ``ray_index[v, i]`` is slot i's original ray number.
    """

    origins: NDArray[np.float64]
    """[V, 3] camera centres."""
    dirs: NDArray[np.float64]
    """[V, R, 3] world directions (t along them is whatever the caller's unit is, e.g. z-depth)."""
    t_enter: NDArray[np.float64]
    t_exit: NDArray[np.float64]
    count: NDArray[np.int64]
    ray_index: NDArray[np.int64]

    @classmethod
    def build(
        cls, origins: NDArray[np.floating], dirs: NDArray[np.floating], grid: GridSpec, t_min: float, t_max: float
    ) -> RayTable:
        o = np.ascontiguousarray(origins, dtype=np.float64)
        d = np.ascontiguousarray(dirs, dtype=np.float64)
        t0, t1 = clip_rays(o, d, *grid_params(grid), float(t_min), float(t_max))
        hit = t0 < t1
        order = np.argsort(~hit, axis=1, kind="stable")
        return cls(
            origins=o,
            dirs=np.ascontiguousarray(np.take_along_axis(d, order[..., None], axis=1)),
            t_enter=np.ascontiguousarray(np.take_along_axis(t0, order, axis=1)),
            t_exit=np.ascontiguousarray(np.take_along_axis(t1, order, axis=1)),
            count=hit.sum(axis=1).astype(np.int64),
            ray_index=order.astype(np.int64),
        )

    def subset(self, views: NDArray[np.int64]) -> RayTable:
        """The table of the listed views only (rows copied, in the order given)."""
        return RayTable(origins=self.origins[views], dirs=self.dirs[views], t_enter=self.t_enter[views],
                        t_exit=self.t_exit[views], count=self.count[views], ray_index=self.ray_index[views])

    def unsort(self, per_slot: NDArray[np.float64]) -> NDArray[np.float64]:
        """A [V, R] per-slot array back in the original ray order."""
        out = np.empty_like(per_slot)
        np.put_along_axis(out, self.ray_index, per_slot, axis=1)
        return out

    def args(self) -> tuple[NDArray[Any], NDArray[Any], NDArray[Any], NDArray[Any], NDArray[Any]]:
        """``(origins, dirs, t_enter, t_exit, count)``, the leading arguments of the IG kernels."""
        return self.origins, self.dirs, self.t_enter, self.t_exit, self.count


@njit(cache=True, fastmath=False, parallel=True)
def ig_views(p, h, origins, dirs, t_enter, t_exit, count, g0, s, n, eps):
    """IG of every view (volumetric IG of paper eq. oig): per view v, the sum over its rays of
    ``sum_k H(p_k) prod_{j<k} (1 - p_j)`` along the DDA traversal, early exit at transmission <= eps.

    p, h: float32 [N] (clamped occupancy, its entropy); the rays as in :class:`RayTable`. Returns
    float64 [V]. eps = 0 is exact (it still stops once the transmission is exactly 0).
    """
    nv = dirs.shape[0]
    out = np.zeros(nv, dtype=np.float64)
    for v in prange(nv):
        ox, oy, oz = origins[v, 0], origins[v, 1], origins[v, 2]
        acc = 0.0
        for r in range(count[v]):
            dx, dy, dz = dirs[v, r, 0], dirs[v, r, 1], dirs[v, r, 2]
            acc += _ray_ig(p, h, ox, oy, oz, dx, dy, dz, g0, s, n, t_enter[v, r], t_exit[v, r], eps)
        out[v] = acc
    return out


@njit(cache=True, fastmath=False, parallel=True)
def ig_rays(p, h, origins, dirs, t_enter, t_exit, count, g0, s, n, eps):
    """Per-ray IG, float64 [V, R] in :class:`RayTable` slot order (debugging, the error-bound test)."""
    nv, nr = dirs.shape[0], dirs.shape[1]
    out = np.zeros((nv, nr), dtype=np.float64)
    for v in prange(nv):
        ox, oy, oz = origins[v, 0], origins[v, 1], origins[v, 2]
        for r in range(count[v]):
            dx, dy, dz = dirs[v, r, 0], dirs[v, r, 1], dirs[v, r, 2]
            out[v, r] = _ray_ig(p, h, ox, oy, oz, dx, dy, dz, g0, s, n, t_enter[v, r], t_exit[v, r], eps)
    return out


@njit(cache=True, fastmath=False, parallel=True)
def ig_views_batch(p, h, stop, origins, dirs, t_enter, t_exit, count, g0, s, n, eps):
    """:func:`ig_views` for K beliefs at once, equal to K separate calls: float64 [K, V].

    ``p, h`` are voxel-major float32 [N, K] (the K values of a voxel share a cache line). ``stop``
    (uint8 [N]) marks voxels with p == 1 in every belief (walls, unmoved objects): each ray is
    traversed once, up to its first stop voxel, and the K sums run over that voxel list, each
    belief's transmission set to 0 once it is <= eps (adding exact zeros afterwards). prange over
    views: the K beliefs share each traversal (docs/explanation/performance.md, "IG sweep").
    """
    nk = p.shape[1]
    nv = dirs.shape[0]
    out = np.zeros((nk, nv), dtype=np.float64)
    nbuf = n[0] + n[1] + n[2]
    for v in prange(nv):
        vox = np.empty(nbuf, dtype=np.int64)
        tin = np.empty(nbuf, dtype=np.float64)
        tout = np.empty(nbuf, dtype=np.float64)
        trans = np.empty(nk, dtype=np.float64)
        ig = np.empty(nk, dtype=np.float64)
        acc = np.zeros(nk, dtype=np.float64)
        ox, oy, oz = origins[v, 0], origins[v, 1], origins[v, 2]
        for r in range(count[v]):
            m = _traverse_clipped(
                ox, oy, oz, dirs[v, r, 0], dirs[v, r, 1], dirs[v, r, 2], g0, s, n, t_enter[v, r], t_exit[v, r],
                stop, vox, tin, tout,
            )
            trans[:] = 1.0
            ig[:] = 0.0
            for j in range(m):
                pj = p[vox[j]]
                hj = h[vox[j]]
                alive = 0
                for k in range(nk):
                    tk = trans[k]
                    ig[k] += hj[k] * tk
                    tk = tk * (1.0 - pj[k])
                    live = tk > eps
                    trans[k] = tk if live else 0.0
                    alive += live
                if alive == 0:
                    break
            for k in range(nk):
                acc[k] += ig[k]
        for k in range(nk):
            out[k, v] = acc[k]
    return out


@njit(cache=True, fastmath=False, parallel=True)
def zero_entropy_along_view(p, h, origin, dirs, g0, s, n, t_min, t_max):
    """Expected entropy after a view: a copy of h with 0 on every voxel each ray (dirs [R, 3] from
    origin [3]) traverses, up to and including its first confident-occupied voxel (p == 1)."""
    out = h.copy()
    stop = (p >= 1.0).astype(np.uint8)
    nr = dirs.shape[0]
    nbuf = n[0] + n[1] + n[2]
    for c in prange((nr + _CHUNK - 1) // _CHUNK):
        vox = np.empty(nbuf, dtype=np.int64)
        tin = np.empty(nbuf, dtype=np.float64)
        tout = np.empty(nbuf, dtype=np.float64)
        for r in range(c * _CHUNK, min(nr, (c + 1) * _CHUNK)):
            m = traverse(origin[0], origin[1], origin[2], dirs[r, 0], dirs[r, 1], dirs[r, 2], g0, s, n,
                          t_min, t_max, stop, vox, tin, tout)
            for j in range(m):
                out[vox[j]] = 0.0
    return out


# ------------------------------------------------------------------------------ observation rays
@njit(cache=True, fastmath=False, parallel=True)
def integrate_rays(origins, dirs, hit_t, hit_valid, hit_class, num_classes, g0, s, n, t_min, t_far):
    """Per-view evidence masks of the analytic observation update.

    For ray i (origins/dirs [M, 3]): if ``hit_valid[i]``, the voxel whose interval contains
    ``hit_t[i]`` is *occupied* and seen with class ``hit_class[i]``, and the voxels strictly before it
    are *free*; a ray without a return marks free up to ``t_far``. Returns uint8 ``free [N]``,
    ``occ [N]`` and ``seen [num_classes, N]`` (1 = the voxel was hit by a pixel of that class), each
    voxel set at most once per kind however many rays cross it.
    """
    nvox = n[0] * n[1] * n[2]
    free = np.zeros(nvox, dtype=np.uint8)
    occ = np.zeros(nvox, dtype=np.uint8)
    seen = np.zeros((num_classes, nvox), dtype=np.uint8)
    no_stop = np.zeros(0, dtype=np.uint8)
    nr = dirs.shape[0]
    nbuf = n[0] + n[1] + n[2]
    for c in prange((nr + _CHUNK - 1) // _CHUNK):
        vox = np.empty(nbuf, dtype=np.int64)
        tin = np.empty(nbuf, dtype=np.float64)
        tout = np.empty(nbuf, dtype=np.float64)
        for r in range(c * _CHUNK, min(nr, (c + 1) * _CHUNK)):
            valid = hit_valid[r]
            th = hit_t[r]
            # a ray with a return is followed to the grid exit, so the voxel holding the return is found
            m = traverse(origins[r, 0], origins[r, 1], origins[r, 2], dirs[r, 0], dirs[r, 1], dirs[r, 2], g0, s, n,
                          t_min, np.inf if valid else t_far, no_stop, vox, tin, tout)
            if m == 0 or (valid and th < tin[0]):
                continue  # misses the grid, or the return lies before it
            for j in range(m):
                if valid and tout[j] > th:
                    occ[vox[j]] = 1
                    cls = hit_class[r]
                    if 0 <= cls < num_classes:
                        seen[cls, vox[j]] = 1
                    break
                free[vox[j]] = 1
    return free, occ, seen


@njit(cache=True, fastmath=False, parallel=True)
def first_hit(occ, origins, dirs, g0, s, n, t_min, t_max):
    """First voxel with ``occ != 0`` (uint8 [N]) along each ray (origins/dirs [M, 3]).

    Returns ``t_in, t_out`` float64 [M] (the hit voxel's interval on the ray; inf when no hit) and
    ``idx`` int64 [M] (flat voxel index, -1 when no hit). A synthetic depth camera over a voxel scene
    uses the interval midpoint as the return, which lies strictly inside the hit voxel.
    """
    nr = dirs.shape[0]
    t_in = np.full(nr, np.inf)
    t_out = np.full(nr, np.inf)
    hit = np.full(nr, -1, dtype=np.int64)
    nbuf = n[0] + n[1] + n[2]
    for c in prange((nr + _CHUNK - 1) // _CHUNK):
        vox = np.empty(nbuf, dtype=np.int64)
        tin = np.empty(nbuf, dtype=np.float64)
        tout = np.empty(nbuf, dtype=np.float64)
        for r in range(c * _CHUNK, min(nr, (c + 1) * _CHUNK)):
            m = traverse(origins[r, 0], origins[r, 1], origins[r, 2], dirs[r, 0], dirs[r, 1], dirs[r, 2], g0, s, n,
                          t_min, t_max, occ, vox, tin, tout)
            if m > 0 and occ[vox[m - 1]] != 0:
                t_in[r] = tin[m - 1]
                t_out[r] = tout[m - 1]
                hit[r] = vox[m - 1]
    return t_in, t_out, hit


# ------------------------------------------------------------------------------ incremental IG
@njit(cache=True, fastmath=False, inline="always")
def _ray_ig_stop(p, h, ox, oy, oz, dx, dy, dz, g0, s, n, t0, t1, eps):
    """:func:`_ray_ig` that also returns where the ray stopped: the exit t of the voxel at which its
    transmission fell to <= eps, or t1 if it never did. The traversal of :func:`_traverse_clipped`,
    fused with the sum (the hot loop; inlined, so :func:`_ray_ig` costs nothing more)."""
    nx, ny, nz = n[0], n[1], n[2]
    ix, iy, iz, idx, tx, ty, tz, sx, sy, sz, kx, ky, kz = _dda_start(
        ox, oy, oz, dx, dy, dz, t0, g0[0], g0[1], g0[2], s, nx, ny, nz
    )
    t = t0
    trans = 1.0
    ig = 0.0
    while True:
        tn, ax = _dda_exit(tx, ty, tz)
        te = tn if tn < t1 else t1
        if te > t:
            ig += h[idx] * trans
            trans *= 1.0 - p[idx]
            if trans <= eps:
                return ig, te
        more, ix, iy, iz, idx, tx, ty, tz = _dda_next(ax, tn, t1, ix, iy, iz, idx, tx, ty, tz,
                                                      sx, sy, sz, kx, ky, kz, nx, ny, nz)
        if not more:
            break
        t = tn
    return ig, t1


@njit(cache=True, fastmath=False, parallel=True)
def ig_views_stop(p, h, origins, dirs, t_enter, t_exit, count, g0, s, n, eps):
    """:func:`ig_views` (equal to it bit for bit) that also returns each ray's stop: float64 [V, R] in
    :class:`RayTable` slot order, the t up to which the ray was marched (see :func:`_ray_ig_stop`).
    Beyond it the ray's IG cannot depend on the field: what :func:`ig_views_delta` skips by."""
    nv, nr = dirs.shape[0], dirs.shape[1]
    out = np.zeros(nv, dtype=np.float64)
    t_stop = np.zeros((nv, nr), dtype=np.float64)
    for v in prange(nv):
        ox, oy, oz = origins[v, 0], origins[v, 1], origins[v, 2]
        acc = 0.0
        for r in range(count[v]):
            g, te = _ray_ig_stop(p, h, ox, oy, oz, dirs[v, r, 0], dirs[v, r, 1], dirs[v, r, 2], g0, s, n,
                                 t_enter[v, r], t_exit[v, r], eps)
            acc += g
            t_stop[v, r] = te
        out[v] = acc
    return out, t_stop


@njit(cache=True, fastmath=False, parallel=True)
def ig_views_delta(p, h, stop, slot, pu, hu, cand_ptr, cand_k, origins, dirs, t_enter, t_exit, count, t_stop,
                   box_lo, box_hi, g0, s, n, eps):
    """The change of every view's IG under K sparsely changed fields, float64 [K, V]: the sum over
    the rays whose base traversal meets a candidate's changed voxels of (ray IG under the candidate
    - ray IG under the base), so that ``IG(v | k) = IG(v | base) + out[k, v]``.

    ``p, h`` (float32 [N]): the base field. ``slot`` (int32 [N]): position of a voxel in the union U
    of all changed voxels, -1 elsewhere. ``pu, hu`` (float32 [U, K], voxel-major): every candidate's
    values on U (the base value where that candidate leaves a voxel unchanged). ``cand_ptr``
    (int64 [U + 1]) / ``cand_k`` (int64): CSR list of the candidates that change each union voxel.
    ``stop`` (uint8 [N]): voxels with p == 1 that no candidate changes (walls, unmoved confident
    surfaces); traversal ends after one. ``t_stop`` [V, R]: where each base ray stopped
    (:func:`ig_views_stop` with the same eps); ``box_lo, box_hi``: a box holding every union voxel.

    Which rays: a ray whose segment from the grid entry to its base stop misses the box cannot meet
    a changed voxel before its stop and is skipped (its delta is exactly 0); so are the candidate
    updates on voxels with p = H = 0 outside U (they change no candidate's ray). The other rays are
    traversed once, carrying the base ray IG with the rule of :func:`_ray_ig` (stop once the
    transmission is <= eps). Where the base ray, before its stop, first meets a voxel a candidate
    changes, that candidate's ray starts from the base prefix (sum and transmission) and is carried
    along in step with the same rule and the candidate's values, until its own transmission is
    <= eps. A candidate whose changed voxels the base ray does not reach before its stop sees the
    same prefix, hence the same stop and the same ray IG: its delta is exactly 0. The traversal ends
    when the base and every started candidate are done, or after a ``stop`` voxel (p == 1 for every
    candidate). So ``IG(v | base) + out`` equals a full re-score of each candidate field with the
    same eps (up to float64 summation order), with early exit on or off.
    """
    nk = pu.shape[1]
    nv = dirs.shape[0]
    out = np.zeros((nk, nv), dtype=np.float64)
    nx, ny, nz = n[0], n[1], n[2]
    for v in prange(nv):
        stamp = np.full(nk, -1, dtype=np.int64)
        aff = np.empty(nk, dtype=np.int64)
        fin = np.empty(nk, dtype=np.float64)
        act = np.empty(nk, dtype=np.int64)
        atr = np.empty(nk, dtype=np.float64)
        ag = np.empty(nk, dtype=np.float64)
        delta = np.zeros(nk, dtype=np.float64)
        ox, oy, oz = origins[v, 0], origins[v, 1], origins[v, 2]
        for r in range(count[v]):
            dx, dy, dz = dirs[v, r, 0], dirs[v, r, 1], dirs[v, r, 2]
            t0, t1 = t_enter[v, r], t_exit[v, r]
            b0, b1 = _slab(ox, dx, box_lo[0], box_hi[0], t0, t_stop[v, r])
            b0, b1 = _slab(oy, dy, box_lo[1], box_hi[1], b0, b1)
            b0, b1 = _slab(oz, dz, box_lo[2], box_hi[2], b0, b1)
            if b0 > b1:  # no changed voxel before the base stop
                continue
            ix, iy, iz, idx, tx, ty, tz, sx, sy, sz, kx, ky, kz = _dda_start(
                ox, oy, oz, dx, dy, dz, t0, g0[0], g0[1], g0[2], s, nx, ny, nz
            )
            t = t0
            trans = 1.0
            ig = 0.0
            naff = 0
            nact = 0
            done = False
            while True:
                tn, ax = _dda_exit(tx, ty, tz)
                if (tn if tn < t1 else t1) > t:
                    sl = slot[idx]
                    pv = p[idx]
                    hv = h[idx]
                    if not done and sl >= 0:
                        # candidates changing this voxel that the ray reaches for the first time:
                        # they start from the base prefix
                        for c in range(cand_ptr[sl], cand_ptr[sl + 1]):
                            k = cand_k[c]
                            if stamp[k] != r:
                                stamp[k] = r
                                aff[naff] = k
                                naff += 1
                                act[nact] = k
                                atr[nact] = trans
                                ag[nact] = ig
                                nact += 1
                    if sl >= 0 or pv != 0.0 or hv != 0.0:
                        # the candidates' rays, in step with the base ray: first every update (on a voxel
                        # no candidate changes, one loop the compiler vectorises), then the finished ones out
                        if sl >= 0:
                            for a in range(nact):
                                k = act[a]
                                ag[a] = ag[a] + hu[sl, k] * atr[a]
                                atr[a] = atr[a] * (1.0 - pu[sl, k])
                        else:
                            q = 1.0 - pv
                            for a in range(nact):
                                ag[a] = ag[a] + hv * atr[a]
                                atr[a] = atr[a] * q
                        a = 0
                        while a < nact:
                            if atr[a] <= eps:  # this candidate's ray is finished
                                fin[act[a]] = ag[a]
                                nact -= 1
                                act[a] = act[nact]
                                atr[a] = atr[nact]
                                ag[a] = ag[nact]
                            else:
                                a += 1
                    if not done:
                        ig += hv * trans
                        trans *= 1.0 - pv
                        if trans <= eps:
                            done = True
                    if stop[idx] != 0 or (done and nact == 0):
                        break
                more, ix, iy, iz, idx, tx, ty, tz = _dda_next(ax, tn, t1, ix, iy, iz, idx, tx, ty, tz,
                                                              sx, sy, sz, kx, ky, kz, nx, ny, nz)
                if not more:
                    break
                t = tn
            for a in range(nact):  # still transmitting where the ray left the grid
                fin[act[a]] = ag[a]
            for a in range(naff):
                delta[aff[a]] += fin[aff[a]] - ig
        for k in range(nk):
            out[k, v] = delta[k]
    return out
