"""Geometry shared by the grasp skill and its effect model: the gripper as points, its swept volume
along a path, the voxels a grasp may not touch, and the believed objects (connected components).

Rasterisation rule: a body covers the voxels holding any of its sample points, sampled on a lattice
of at most half a voxel (in the body's frame, boxes shrunk by a tolerance), and a translation is
sampled every half voxel; a voxel-sized obstacle therefore cannot slip between two samples.

Collision tests of many grasps at once (:func:`sweep_hits`): one numba kernel walks each test's
body points through its positions and stops at the first point in a blocked voxel, testing a
voxel's membership in the exempt target region (``Objects.region``) from its label and the
region's box in the grasp frame, without building the region. The gripper's points for many
openings come from one lattice (:func:`gripper_points_batch`, equal to :func:`gripper_points`).
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import shelf_wall_mask
from msmem_core.map.raycast import grid_params
from msmem_core.world.geometry import F64
from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec, HandDims
from msmem_core.world.scene import ShelfSpec

I64 = NDArray[np.int64]


def box_lattice(centre: F64, half: F64, spacing: float, shrink: float = 0.0) -> F64:
    """Points [P, 3] of a lattice filling the box (centre, half-extents) shrunk by ``shrink``, with at
    most ``spacing`` between neighbours and points on every face."""
    h = np.maximum(np.asarray(half, dtype=np.float64) - shrink, 0.0)
    axes = [np.linspace(-v, v, max(2, math.ceil(2 * v / spacing) + 1)) if v > 0 else np.zeros(1) for v in h]
    g = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    return g + np.asarray(centre, dtype=np.float64)


def gripper_boxes(gripper: GripperSpec, opening_m: float, hand_m: HandDims | None = None) -> list[tuple[F64, F64]]:
    """(centre, half-extents) of the fingers at ``opening_m`` and the palm in the gripper frame
    (``GripperSpec.boxes``); with ``hand_m`` the palm is the hand: ``width`` along the closing axis,
    ``thickness`` along the gripper's y, ``depth`` along the approach behind the fingers, centred on
    the approach axis, then the wrist if given (a square section of its width, ``length`` long)."""
    boxes = gripper.boxes(float(np.clip(opening_m, 0.0, gripper.max_opening_m)))
    if hand_m is None:
        return boxes
    width, thick, depth, *wrist = (float(v) for v in hand_m)
    fl = gripper.finger_length_m
    out = [*boxes[:2], (np.array([0.0, 0.0, -fl - depth / 2]), np.array([width / 2, thick / 2, depth / 2]))]
    if wrist:
        ww, wl = wrist
        out.append((np.array([0.0, 0.0, -fl - depth - wl / 2]), np.array([ww / 2, ww / 2, wl / 2])))
    return out


def gripper_points(gripper: GripperSpec, opening_m: float, spacing: float, shrink: float = 0.0,
                   hand_m: HandDims | None = None) -> F64:
    """Sample points [P, 3] of the two fingers (at ``opening_m``) and the palm (or ``hand_m``'s hand
    and wrist, :func:`gripper_boxes`), in the gripper frame (read-only; the last few hundred are
    cached: candidates share openings)."""
    key = (tuple(gripper.model_dump().values()), float(opening_m), float(spacing), float(shrink),
           None if hand_m is None else tuple(map(float, hand_m)))
    pts = _POINTS.get(key)
    if pts is None:
        boxes = gripper_boxes(gripper, float(opening_m), hand_m)
        pts = np.concatenate([box_lattice(c, h, spacing, shrink) for c, h in boxes])
        pts.flags.writeable = False
        if len(_POINTS) >= 512:
            _POINTS.pop(next(iter(_POINTS)))
        _POINTS[key] = pts
    return pts


_POINTS: dict[tuple[object, ...], F64] = {}


def gripper_points_batch(gripper: GripperSpec, openings_m: F64, spacing: float, shrink: float = 0.0,
                         hand_m: HandDims | None = None) -> F64:
    """:func:`gripper_points` for each opening [N] at once: [N, P, 3], equal to it to the bit (the same
    lattice offsets plus each opening's box centres)."""
    openings = np.clip(np.asarray(openings_m, dtype=np.float64), 0.0, gripper.max_opening_m)
    (_, finger_half), _, *rest = gripper_boxes(gripper, 0.0, hand_m)
    finger = box_lattice(np.zeros(3), finger_half, spacing, shrink)  # offsets from a finger's centre
    palm = np.concatenate([box_lattice(c, h, spacing, shrink) for c, h in rest])
    fx = openings / 2 + gripper.finger_thickness_m / 2  # as GripperSpec.boxes
    fz = -gripper.finger_length_m / 2
    n = len(openings)
    left = np.zeros((n, 3))
    left[:, 0], left[:, 2] = -fx, fz
    right = np.zeros((n, 3))
    right[:, 0], right[:, 2] = fx, fz
    return np.concatenate([finger[None] + left[:, None], finger[None] + right[:, None],
                           np.broadcast_to(palm, (n, *palm.shape))], axis=1)


def path_offsets(waypoints: F64, spacing: float) -> F64:
    """Positions [T, 3] along the polyline through ``waypoints`` [W, 3], at most ``spacing`` apart
    (the waypoints included)."""
    w = np.asarray(waypoints, dtype=np.float64).reshape(-1, 3)
    if len(w) == 1:
        return w.copy()
    out = [w[:1]]
    for a, b in itertools.pairwise(w):
        n = max(1, math.ceil(float(np.linalg.norm(b - a)) / spacing))
        t = np.arange(1, n + 1)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out)


def segment_paths(starts: F64, ends: F64, spacing: float) -> tuple[F64, I64]:
    """``path_offsets`` of many segments at once: the positions along ``starts[q]`` -> ``ends[q]`` [Q, 3],
    concatenated [T, 3], and pointers [Q + 1] (segment q's positions are ``ptr[q]:ptr[q + 1]``)."""
    a = np.asarray(starts, dtype=np.float64).reshape(-1, 3)
    b = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
    n = np.maximum(1, np.ceil(np.linalg.norm(b - a, axis=1) / spacing)).astype(np.int64)
    ptr = np.concatenate([[0], np.cumsum(n + 1)])
    q = np.repeat(np.arange(len(n)), n + 1)
    t = (np.arange(ptr[-1]) - ptr[q]) / n[q]
    return a[q] + t[:, None] * (b[q] - a[q]), ptr


def swept_indices(grid: GridSpec, rotation: F64, local_points: F64, positions: F64) -> I64:
    """Flat indices (sorted, unique) of the voxels holding the body's points (``local_points`` in a
    frame with ``rotation``) at every origin of ``positions``; points outside the grid are dropped.
    (A numba kernel marks them in a grid mask: the same voxels as ``swept_indices_reference``.)"""
    mask = np.zeros(grid.size, dtype=np.bool_)
    mark_swept(mask, grid, rotation, local_points, positions)
    return np.flatnonzero(mask)


def mark_swept(mask: NDArray[np.bool_], grid: GridSpec, rotation: F64, local_points: F64, positions: F64) -> None:
    """Set, in the flat grid ``mask``, the voxels ``swept_indices`` returns (several sweeps, one mask)."""
    local = np.ascontiguousarray(np.asarray(local_points, dtype=np.float64) @ np.asarray(rotation, dtype=np.float64).T)
    g0, s, n = grid_params(grid)
    _mark_swept(mask, g0, s, n, local, np.ascontiguousarray(np.asarray(positions, dtype=np.float64).reshape(-1, 3)))


def swept_indices_reference(grid: GridSpec, rotation: F64, local_points: F64, positions: F64) -> I64:
    """``swept_indices`` in plain numpy (all points at once, ``np.unique``): the oracle of its test."""
    local = np.asarray(local_points) @ np.asarray(rotation).T
    world = (np.asarray(positions)[:, None, :] + local[None]).reshape(-1, 3)
    ijk = grid.index_of(world)
    ii = ijk[grid.contains_index(ijk)]
    return np.unique((ii[:, 0] * grid.shape[1] + ii[:, 1]) * grid.shape[2] + ii[:, 2])


@njit(cache=True, fastmath=False)
def _mark_swept(mask, g0, s, n, local, positions):  # type: ignore[no-untyped-def]
    """Mark the voxel of every ``positions[t] + local[m]`` inside the grid (``grid.index_of``'s rounding)."""
    nx, ny, nz = n[0], n[1], n[2]
    for t in range(positions.shape[0]):
        for m in range(local.shape[0]):
            i = math.floor((positions[t, 0] + local[m, 0] - g0[0]) / s)
            j = math.floor((positions[t, 1] + local[m, 1] - g0[1]) / s)
            k = math.floor((positions[t, 2] + local[m, 2] - g0[2]) / s)
            if 0 <= i < nx and 0 <= j < ny and 0 <= k < nz:
                mask[(i * ny + j) * nz + k] = True


@njit(cache=True, fastmath=False, parallel=True)
def _sweep_hits(blocked, labels, g0, s, n, local, positions, ptr, body, label, frame, half_x, radius, depth):
    """The kernel of :func:`sweep_hits` (arguments as there, grid as ``raycast.grid_params``); the tests
    run in parallel over numba's threads."""
    nx, ny, nz = n[0], n[1], n[2]
    out = np.zeros(len(body), dtype=np.bool_)
    for q in prange(len(body)):
        b, lab = body[q], label[q]
        hit = False
        for t in range(ptr[q], ptr[q + 1]):
            for m in range(local.shape[1]):
                i = math.floor((positions[t, 0] + local[b, m, 0] - g0[0]) / s)
                j = math.floor((positions[t, 1] + local[b, m, 1] - g0[1]) / s)
                k = math.floor((positions[t, 2] + local[b, m, 2] - g0[2]) / s)
                if not (0 <= i < nx and 0 <= j < ny and 0 <= k < nz):
                    if j >= 0:  # beside, behind, above or below the grid: the boards
                        hit = True
                        break
                    continue
                v = (i * ny + j) * nz + k
                if not blocked[v]:
                    continue
                if lab > 0 and labels[v] == lab:  # in the region: the label's voxels inside its box
                    cx = g0[0] + (i + 0.5) * s - frame[q, 0, 3]
                    cy = g0[1] + (j + 0.5) * s - frame[q, 1, 3]
                    cz = g0[2] + (k + 0.5) * s - frame[q, 2, 3]
                    lx = cx * frame[q, 0, 0] + cy * frame[q, 1, 0] + cz * frame[q, 2, 0]
                    ly = cx * frame[q, 0, 1] + cy * frame[q, 1, 1] + cz * frame[q, 2, 1]
                    lz = cx * frame[q, 0, 2] + cy * frame[q, 1, 2] + cz * frame[q, 2, 2]
                    if abs(lx) <= half_x[q] and abs(ly) <= radius and -radius <= lz <= depth:
                        continue
                hit = True
                break
            if hit:
                break
        out[q] = hit
    return out


def sweep_hits(grid: GridSpec, blocked: NDArray[np.bool_], labels: NDArray[np.int32], local: F64, positions: F64,
               ptr: I64, body: I64, label: I64, frame: F64, opening_m: F64, max_radius_m: float,
               max_depth_m: float = 0.3) -> NDArray[np.bool_]:
    """Collision tests [Q]: does body ``body[q]`` (its points ``local[body[q]]`` [P, 3], already
    rotated into the world's axes) at the origins ``positions[ptr[q]:ptr[q + 1]]`` touch a voxel of
    ``blocked`` (flat [X*Y*Z]) other than those of the exempt region, or leave the grid other than
    towards the front (-y)? The region of test q is ``Objects.region(grid, label[q], frame[q],
    opening_m[q], max_radius_m, max_depth_m)`` (``label[q] <= 0``: none), tested per voxel from
    ``labels`` (flat) and the same box in the frame [4, 4]."""
    half_x = np.asarray(opening_m, dtype=np.float64) / 2 + grid.voxel_m / 2  # as Objects.region
    g0 = grid.origin.astype(np.float64)
    return _sweep_hits(np.asarray(blocked, dtype=np.bool_).reshape(-1), np.asarray(labels, np.int32).reshape(-1), g0,
                       float(grid.voxel_m), np.asarray(grid.shape, dtype=np.int64),
                       np.ascontiguousarray(local, dtype=np.float64), np.ascontiguousarray(positions, dtype=np.float64),
                       np.asarray(ptr, np.int64), np.asarray(body, np.int64), np.asarray(label, np.int64),
                       np.ascontiguousarray(frame, dtype=np.float64), half_x, float(max_radius_m), float(max_depth_m))


def voxel_centres(grid: GridSpec, flat: I64) -> F64:
    """World centres [N, 3] of voxels given by flat index."""
    ijk = np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), grid.shape), axis=-1)
    return grid.origin + (ijk + 0.5) * grid.voxel_m


def blocked_mask(belief: EvidentialMap, shelf: ShelfSpec, occupied_threshold: float = 0.5,
                 unknown_vacuity: float = 0.9, unknown_band: float = 0.1) -> NDArray[np.bool_]:
    """[X, Y, Z]: voxels a gripper may not enter: believed occupied (p > ``occupied_threshold``),
    unknown (never seen, ``EvidentialMap.never_seen(unknown_vacuity)``, and |p - 0.5| < ``unknown_band``),
    or the shelf's boards (``ig.shelf_wall_mask``). On a completed belief (``cnabu-map``) a voxel no
    ray reached is unknown only where the prediction is not confident either: a confidently predicted
    free voxel may be entered, a predicted occupied one may not."""
    p = belief.expected_occupancy()
    unknown = belief.never_seen(unknown_vacuity) & (np.abs(p - 0.5) < unknown_band)
    return (p > occupied_threshold) | unknown | shelf_wall_mask(belief.grid, shelf)


@dataclass
class Objects:
    """Believed objects: connected components (26-neighbourhood) of the believed-occupied voxels of
    one argmax class inside the shelf interior (background-class voxels are the shelf's boards)."""

    labels: NDArray[np.int32]
    """[X, Y, Z] component per voxel (0: none)."""
    classes: I64
    """[L + 1] class of each component (index 0 unused)."""
    cls: I64
    """[X, Y, Z] argmax class."""

    @classmethod
    def of(cls, belief: EvidentialMap, interior: tuple[float, ...], occupied_threshold: float = 0.5) -> Objects:
        """The components of ``belief`` inside ``interior`` = (x_lo, y_lo, z_lo, x_hi, y_hi, z_hi)."""
        from scipy import ndimage
        grid = belief.grid
        c = grid.centers()
        inside = np.all((c > np.asarray(interior[:3])) & (c < np.asarray(interior[3:])), axis=-1)
        k = np.argmax(belief.eta, axis=0)
        occ = (belief.expected_occupancy() > occupied_threshold) & inside & (k != 0)
        labels = np.zeros(grid.shape, np.int32)
        classes = [0]
        for c_id in np.unique(k[occ]):
            lab, m = ndimage.label(occ & (k == c_id), structure=np.ones((3, 3, 3), dtype=bool))
            labels[lab > 0] = lab[lab > 0] + len(classes) - 1
            classes += [int(c_id)] * m
        return cls(labels, np.asarray(classes, dtype=np.int64), k)

    def voxels_of(self, label: int) -> I64:
        """Flat indices of component ``label`` (cached: candidates share targets)."""
        cache = self.__dict__.setdefault("_voxels", {})
        if label not in cache:
            cache[label] = np.flatnonzero(self.labels.reshape(-1) == label)
        return cache[label]

    def label_at(self, grid: GridSpec, points: F64, target_class: I64 | None = None) -> I64:
        """Component at each point [N, 3]: that of the nearest voxel of its 3x3x3 neighbourhood (its
        own voxel first) holding one (of ``target_class`` when given); 0 if none."""
        ijk = grid.index_of(points)
        offs = np.stack(np.meshgrid(*([np.arange(-1, 2)] * 3), indexing="ij"), -1).reshape(-1, 3)
        offs = offs[np.argsort(np.abs(offs).sum(1), kind="stable")]  # the point's own voxel first
        q = ijk[:, None, :] + offs[None]
        ok = grid.contains_index(q)
        qc = np.clip(q, 0, np.asarray(grid.shape) - 1)
        lab = np.where(ok, self.labels[qc[..., 0], qc[..., 1], qc[..., 2]], 0).astype(np.int64)
        if target_class is not None:
            lab = np.where(self.classes[lab] == np.asarray(target_class)[:, None], lab, 0)
        first = np.argmax(lab > 0, axis=1)
        return lab[np.arange(len(lab)), first]

    def region(self, grid: GridSpec, label: int, pose: F64, opening_m: float, max_radius_m: float,
               max_depth_m: float = 0.3) -> I64:
        """Flat indices of component ``label`` clipped to the gripper's opening box: voxel centres
        within ``opening_m / 2`` plus half a voxel of the grasp centre along the closing axis, within
        ``max_radius_m`` across it, and from the palm to ``max_depth_m`` beyond the fingertips along
        the approach (touching objects of one class stay separate)."""
        vox = self.voxels_of(label)
        if not len(vox) or label <= 0:
            return np.zeros(0, np.int64)
        s = grid.voxel_m
        centres = self.__dict__.setdefault("_centres", {})  # per label, cached as voxels_of
        if label not in centres:
            centres[label] = voxel_centres(grid, vox)
        local = (centres[label] - pose[:3, 3]) @ pose[:3, :3]
        keep = (np.abs(local[:, 0]) <= opening_m / 2 + s / 2) & (np.abs(local[:, 1]) <= max_radius_m)
        keep &= (local[:, 2] >= -max_radius_m) & (local[:, 2] <= max_depth_m)
        return vox[keep]

    def carried(self, grid: GridSpec, label: int, vox: I64, margin_m: float) -> I64:
        """``vox`` plus component ``label``'s voxels, at any height, in the columns within ``margin_m``
        of ``vox``'s footprint (sorted flat indices): the whole object a grasp of ``vox`` carries out
        (the region the fingers close on is clipped to the opening; the object goes on above it, and
        believed objects are up to about 2 cm fatter than the width a grasp measures)."""
        from scipy import ndimage
        vox = np.asarray(vox, dtype=np.int64)
        if not len(vox) or label <= 0:
            return np.unique(vox)
        nx, ny, nz = grid.shape
        near = np.zeros(nx * ny, dtype=bool)
        near[np.unique(vox // nz)] = True
        near = near.reshape(nx, ny)
        margin = math.floor(margin_m / grid.voxel_m + 1e-9)
        if margin > 0:
            near = ndimage.binary_dilation(near, np.ones((3, 3), dtype=bool), iterations=margin)
        own = self.voxels_of(label)
        return np.union1d(vox, own[near.reshape(-1)[own // nz]])


def _column_tops(grid: GridSpec, body: I64) -> I64:
    """Per column (flat [X * Y]) how many voxels from the floor :func:`under_top` covers: up to ``body``'s
    top in its columns, all in the columns its footprint surrounds, none elsewhere (-1)."""
    from scipy import ndimage
    nx, ny, nz = grid.shape
    cols = np.asarray(body, dtype=np.int64) // nz
    foot = np.zeros(nx * ny, dtype=bool)
    foot[cols] = True
    top = np.full(nx * ny, -1, dtype=np.int64)
    np.maximum.at(top, cols, np.asarray(body, dtype=np.int64) % nz)
    foot2 = foot.reshape(nx, ny)
    top[(ndimage.binary_fill_holes(foot2) & ~foot2).reshape(-1)] = nz
    return top


def under_top(grid: GridSpec, body: I64) -> NDArray[np.bool_]:
    """Flat mask of the voxels below ``body``'s top in each of its columns, and at any height in the
    columns its footprint surrounds. Objects stand on the shelf floor, so nothing else stands there:
    on the default belief, believed-occupied voxels there are the object's own, of another class."""
    nz = grid.shape[2]
    return (np.arange(nz)[None, :] < _column_tops(grid, body)[:, None]).reshape(-1)


def clear_under_top(grid: GridSpec, body: I64, mask: NDArray[np.bool_]) -> None:
    """``mask &= ~under_top(grid, body)`` in place (flat ``mask``), touching only the body's columns."""
    nz = grid.shape[2]
    top = _column_tops(grid, body)
    cols = np.flatnonzero(top > 0)
    block = mask.reshape(-1, nz)[cols]
    block &= ~(np.arange(nz)[None, :] < top[cols, None])
    mask.reshape(-1, nz)[cols] = block


def shift_voxels(grid: GridSpec, vox: I64, di: int, dj: int, dk: int) -> tuple[I64, NDArray[np.bool_]]:
    """Flat indices of voxels moved by (di, dj, dk) and which of them stay inside the grid."""
    nx, ny, nz = grid.shape
    i, j, k = np.unravel_index(vox, grid.shape)
    i, j, k = i + di, j + dj, k + dk
    ok = (i >= 0) & (i < nx) & (j >= 0) & (j < ny) & (k >= 0) & (k < nz)
    return np.where(ok, (i * ny + j) * nz + k, 0).astype(np.int64), ok


def way_out(grid: GridSpec, vox: I64, lift: int) -> tuple[I64, I64]:
    """The voxels a body sweeps when lifted by ``lift`` voxels and then carried along -y out of the
    grid: (flat indices in the grid, step of the sweep at which each is first reached)."""
    if not len(vox):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    j = np.unravel_index(vox, grid.shape)[1]
    parts, steps = [], []
    for dk in range(1, lift + 1):
        f, ok = shift_voxels(grid, vox, 0, 0, dk)
        parts.append(f[ok])
        steps.append(np.full(int(ok.sum()), dk - 1))
    for m in range(1, int(j.max()) + 2):
        f, ok = shift_voxels(grid, vox, 0, -m, lift)
        parts.append(f[ok])
        steps.append(np.full(int(ok.sum()), lift + m - 1))
    flat, step = np.concatenate(parts), np.concatenate(steps)
    if not len(flat):  # no lift, and nothing in front of the body's voxels (all in the first row)
        return flat.astype(np.int64), step.astype(np.int64)
    order = np.lexsort((step, flat))
    flat, step = flat[order], step[order]
    first = np.r_[True, flat[1:] != flat[:-1]]
    return flat[first], step[first]


@njit(cache=True, fastmath=False)
def _way_out_meets(vox, lift, nj, nk, mask):  # type: ignore[no-untyped-def]
    for v in vox:  # lifted one voxel at a time
        base = v - v % nk
        for dk in range(1, lift + 1):
            kk = v % nk + dk
            if kk < nk and mask[base + kk]:
                return True
    for v in vox:  # then carried along -y at the lift
        kk = v % nk + lift
        if kk >= nk:
            continue
        j = (v // nk) % nj
        for m in range(1, j + 1):
            if mask[v - m * nk + lift]:
                return True
    return False


def way_out_meets(grid: GridSpec, vox: I64, lift: int, mask: NDArray[np.bool_]) -> bool:
    """Whether the voxels :func:`way_out` gives (``vox`` lifted by ``lift`` voxels, then carried along -y
    out of the grid) meet ``mask`` (flat), ``mask[way_out(grid, vox, lift)[0]].any()``, without listing them."""
    if not len(vox):
        return False
    return bool(_way_out_meets(np.asarray(vox, dtype=np.int64), int(lift), int(grid.shape[1]), int(grid.shape[2]),
                               np.asarray(mask, dtype=np.bool_).reshape(-1)))


def fill_down(grid: GridSpec, p: NDArray[np.floating], labels: NDArray[np.int32], vox: I64, label: int,
              free_threshold: float) -> I64:
    """``vox`` plus, below the lowest voxel of each of its columns, the voxels down to the floor that
    are not believed free (p >= ``free_threshold``) and belong to no other object: the hidden lower
    part of an object standing on the shelf (a view over a low object in front sees only the top of
    the one behind it)."""
    if not len(vox):
        return vox
    i, j, k = np.unravel_index(vox, grid.shape)
    col = i * grid.shape[1] + j
    order = np.lexsort((k, col))
    first = np.r_[True, col[order][1:] != col[order][:-1]]
    ci, cj, ck = i[order][first], j[order][first], k[order][first]
    pz = np.asarray(p)[ci, cj]  # [C, Z]
    lz = labels[ci, cj]
    z = np.arange(grid.shape[2])
    floor = grid.origin[2] + (z + 0.5) * grid.voxel_m > 0.0
    solid = (pz >= free_threshold) & ((lz == 0) | (lz == label)) & floor[None]
    below = z[None] < ck[:, None]
    # the run of solid voxels right below each column's lowest voxel
    run = np.flip(np.cumprod(np.flip(solid | ~below, axis=1), axis=1), axis=1).astype(bool) & below
    ii, kk = np.nonzero(run)
    extra = (ci[ii] * grid.shape[1] + cj[ii]) * grid.shape[2] + kk
    return np.union1d(vox, extra)


@njit(cache=True, fastmath=False)
def _carried_way(region, label, p, labels, thr, k_floor, own, margin, nx, ny, nz, way):  # type: ignore[no-untyped-def]
    ncol = nx * ny
    low = np.full(ncol, nz, dtype=np.int64)  # per column, the region's lowest voxel (nz: none)
    inb = np.zeros(ncol * nz, dtype=np.bool_)
    for v in region:
        c = v // nz
        low[c] = min(low[c], v - c * nz)
        inb[v] = True
    near = np.zeros(ncol, dtype=np.bool_)
    for c in range(ncol):
        if low[c] == nz:
            continue
        k = low[c] - 1  # fill_down: the run of solid voxels of no other object right below, above the floor
        while k >= k_floor:
            lv = labels[c * nz + k]
            if p[c * nz + k] >= thr and (lv == 0 or lv == label):
                inb[c * nz + k] = True
                k -= 1
            else:
                break
        i, j = c // ny, c % ny  # Objects.carried: the columns within margin (a square: iterated 3x3 dilation)
        for a in range(max(0, i - margin), min(nx, i + margin + 1)):
            for b in range(max(0, j - margin), min(ny, j + margin + 1)):
                near[a * ny + b] = True
    if label > 0:
        for v in own:
            if near[v // nz]:
                inb[v] = True
    # the body, sorted; its top per column; its footprint
    count = 0
    top = np.full(ncol, -1, dtype=np.int64)
    for c in range(ncol):
        if not near[c]:
            continue
        for k in range(nz):
            if inb[c * nz + k]:
                count += 1
                top[c] = k
    body = np.empty(count, dtype=np.int64)
    m = 0
    for c in range(ncol):
        if top[c] < 0:
            continue
        for k in range(top[c] + 1):
            if inb[c * nz + k]:
                body[m] = c * nz + k
                m += 1
    # the footprint's holes (binary_fill_holes, 4-connected background): background not reached from the border
    reached = np.zeros(ncol, dtype=np.bool_)
    stack = np.empty(ncol, dtype=np.int64)
    ns = 0
    for c in range(ncol):
        i, j = c // ny, c % ny
        if top[c] < 0 and (i == 0 or i == nx - 1 or j == 0 or j == ny - 1):
            reached[c] = True
            stack[ns] = c
            ns += 1
    while ns > 0:
        ns -= 1
        c = stack[ns]
        i, j = c // ny, c % ny
        for a, b in ((i - 1, j), (i + 1, j), (i, j - 1), (i, j + 1)):
            if 0 <= a < nx and 0 <= b < ny:
                d = a * ny + b
                if top[d] < 0 and not reached[d]:
                    reached[d] = True
                    stack[ns] = d
                    ns += 1
    for c in range(ncol):  # clear_under_top: under the top in its columns, all of the columns it surrounds
        upto = top[c] if top[c] >= 0 else (nz if not reached[c] else 0)
        for k in range(upto):
            way[c * nz + k] = False
    for v in body:
        way[v] = False
    # the body's sides one voxel in: voxels both of whose x neighbours are the body's
    stride = ny * nz
    keep = np.zeros(count, dtype=np.bool_)
    for q in range(count):
        v = body[q]
        keep[q] = v >= stride and inb[v - stride] and v + stride < ncol * nz and inb[v + stride]
    return body, body[keep]


def carried_way(grid: GridSpec, p: NDArray[np.floating], objects: Objects, label: int, region: I64,
                free_threshold: float, margin_m: float,
                occupied: NDArray[np.bool_]) -> tuple[I64, NDArray[np.bool_], I64]:
    """The grasp skill's carried body and what may stop it, in one pass: ``(body, way, core)`` with
    ``body = objects.carried(grid, label, fill_down(grid, p, objects.labels, region, label, free_threshold),
    margin_m)``, ``way`` a copy of the flat mask ``occupied`` with ``clear_under_top(grid, body, .)``
    applied and the body's voxels cleared, and ``core`` the body's voxels both of whose x neighbours are
    the body's (the same arrays as those numpy calls; a test compares them). An empty ``region``
    carries nothing: ``(region, occupied.copy(), region)``."""
    way = np.array(occupied, dtype=np.bool_).reshape(-1)  # a copy
    region = np.asarray(region, dtype=np.int64)
    if not len(region):
        return region, way, region
    nx, ny, nz = grid.shape
    z = np.arange(nz)
    above = np.flatnonzero(grid.origin[2] + (z + 0.5) * grid.voxel_m > 0.0)
    k_floor = int(above[0]) if len(above) else nz
    pf = np.asarray(p).reshape(-1)
    # the threshold as numpy compares it: a Python float against a float32 array is a float32
    thr = pf.dtype.type(free_threshold)
    own = objects.voxels_of(label) if label > 0 else np.zeros(0, np.int64)
    margin = math.floor(margin_m / grid.voxel_m + 1e-9)
    body, core = _carried_way(region, int(label), pf, np.asarray(objects.labels, dtype=np.int32).reshape(-1), thr,
                              k_floor, own, max(margin, 0), nx, ny, nz, way)
    return body, way, core
