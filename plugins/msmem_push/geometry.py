"""The pushing tool and its swept volume on the voxel grid.

The tool is the closed parallel-jaw gripper of ``GripperSpec`` pointing straight down, with its
closing axis along the push: the two closed fingers form a peg ``2 * finger_thickness`` deep (along
the push) and ``finger_width`` wide, reaching from the tip up ``finger_length``; the palm above
them is ``palm_length`` (10 cm) long along the push and ``palm_width`` wide, so it reaches
``palm_length / 2 - finger_thickness`` (4 cm) ahead of the fingers. The whole tool is 2 cm wide
across the push: in a cluttered shelf a palm held across the push (10 cm wide) would collide with
the neighbours of most targets. For an object taller than the fingers' reach the palm touches it
first; the sampler and the effect model use the leading face of the tool part at the object's height.

Geometry is expressed in the *push frame*: ``along`` the unit push direction u, ``across`` it
(w = u rotated by +90 deg about z) and z up from the tool tip. Each tool part is an axis-aligned
box there: ``(half_along, half_across, z_lo, z_hi)``, centred on the tool's position, or
``(half_along, half_across, z_lo, z_hi, centre_along, centre_across)`` for a part centred away from it.

``palm="forward"`` is the other tool: the closed gripper pointing *into* the shelf (+y), its closing
axis along x and the hand's back (where a wrist camera rides) up, as an arm reaches into a shelf. It
pushes straight in (+y), the fingers leading and the hand following behind them, or sideways (+-x),
the fingers reaching in beside the object and the hand trailing behind them; the hand's width
(``hand_m``, the run's gripper's palm by default) lies along x, its thickness around the tip height.

Rasterisation rule (shared by the sampler, ``PushAction.swept_volume`` and the effect model): a
voxel belongs to a swept prism when its centre lies within half a voxel of the prism (the prism's
half-planes moved out by s/2, z likewise) — exact for axis-aligned pushes, slightly under the
exact overlap at the corners of oblique ones. A voxel only touching the prism's boundary is not in it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from msmem_core.world.grid import GridSpec
from msmem_core.world.gripper import GripperSpec, HandDims

_SIGNS = np.array([[-1.0, -1.0], [-1.0, 1.0], [1.0, -1.0], [1.0, 1.0]])
Box = tuple[float, ...]
"""(half_along, half_across, z_lo, z_hi[, centre_along, centre_across]) of one tool part in the push
frame, z from the tool tip; without the centre the part is centred on the tool's position."""


def tool_boxes(gripper: GripperSpec, palm: str = "along", hand_m: HandDims | None = None,
               u: ArrayLike = (0.0, 1.0)) -> tuple[Box, ...]:
    """Fingers (closed) and palm of the gripper pointing down; closing axis along the push
    (``palm="along"``) or across it (``"across"``: a 10 cm wide palm flush with the fingers). For
    ``"forward"`` (pointing into the shelf, +y): the fingers reach back ``finger_length`` from the tip,
    ``2 * finger_thickness`` wide along x and ``finger_width`` high; behind them the hand (``hand_m``;
    default the gripper's palm: ``palm_length`` wide, ``palm_width`` thick, ``palm_depth`` deep),
    centred on the tip's height, and behind the hand the wrist if ``hand_m`` gives one (a square
    section of its width); in the push frame of ``u``, one of +y, +x, -x."""
    fl, pd = gripper.finger_length_m, gripper.palm_depth_m
    if palm == "forward":
        width, thick, depth, *wrist = hand_m or (gripper.palm_length_m, gripper.palm_width_m, pd)
        fw = gripper.finger_width_m
        ux, uy = (float(v) for v in np.asarray(u, dtype=np.float64))
        wy, wx = ux, -uy  # w = u turned +90 deg
        solids = [(-fl / 2, fl / 2, gripper.finger_thickness_m, -fw / 2, fw / 2),
                  (-fl - depth / 2, depth / 2, width / 2, -thick / 2, thick / 2)]
        if wrist:
            ww, wl = wrist
            solids.append((-fl - depth - wl / 2, wl / 2, ww / 2, -ww / 2, ww / 2))
        parts = []  # (centre along y, half along y, half along x, z_lo, z_hi) in the hand's frame
        for cy, hy, hx, zl, zh in solids:
            parts.append((abs(uy) * hy + abs(ux) * hx, abs(wy) * hy + abs(wx) * hx, zl, zh, cy * uy, cy * wy))
        return tuple(parts)
    if palm == "across":
        return (gripper.finger_width_m / 2, gripper.finger_thickness_m, 0.0, fl), (
            gripper.palm_width_m / 2, gripper.palm_length_m / 2, fl, fl + pd)
    fingers = (gripper.finger_thickness_m, gripper.finger_width_m / 2, 0.0, fl)
    palm_box = (gripper.palm_length_m / 2, gripper.palm_width_m / 2, fl, fl + pd)
    return fingers, palm_box


def box6(box: Box) -> tuple[float, float, float, float, float, float]:
    """A part with its centre offsets (0 where it gives none)."""
    b = tuple(float(v) for v in box)
    return (*b, 0.0, 0.0) if len(b) == 4 else b  # type: ignore[return-value]


def boxes_array(boxes: Sequence[Box]) -> NDArray[np.float64]:
    """The parts as an array [P, 6] (centre offsets filled in)."""
    return np.array([box6(b) for b in boxes], dtype=np.float64).reshape(-1, 6)


def leading_half_depth(boxes: Sequence[Box], tip_z: float, top_z: float) -> float:
    """How far ahead of the tool's position its leading face is, for an object reaching up to ``top_z``
    on the tool's line: the largest ``centre_along + half_along`` of the parts on that line (their
    across range holds 0) whose height range overlaps it (below ``top_z``)."""
    parts = [b for b in map(box6, boxes) if abs(b[5]) <= b[1] + 1e-12]
    reach = [b[4] + b[0] for b in parts if tip_z + b[2] < top_z]
    return max(reach) if reach else min(b[4] + b[0] for b in parts)


def across(u: NDArray[np.float64]) -> NDArray[np.float64]:
    """u rotated by +90 deg about z."""
    return np.array([-u[1], u[0]])


def gripper_pose(xy: ArrayLike, tip_z: float, u: ArrayLike, palm: str = "along") -> NDArray[np.float64]:
    """``GripperSpec`` pose of the pushing tool: origin at the fingertips, approach axis down,
    closing axis along the push direction u (``"across"``: across it); ``"forward"``: approach into
    the shelf (+y), closing axis along x, gripper y up."""
    ua, xa = np.asarray(u, dtype=np.float64), np.asarray(xy, dtype=np.float64)
    ux, uy = float(ua[0]), float(ua[1])
    t = np.eye(4)
    if palm == "forward":  # approach into the shelf (+y), closing axis along x, the hand's back up
        t[:3, 0] = (-1.0, 0.0, 0.0)
        t[:3, 1] = (0.0, 0.0, 1.0)
        t[:3, 2] = (0.0, 1.0, 0.0)
        t[:3, 3] = (float(xa[0]), float(xa[1]), float(tip_z))
        return t
    if palm == "across":
        t[:3, 0] = (-uy, ux, 0.0)
        t[:3, 1] = (ux, uy, 0.0)
    else:
        t[:3, 0] = (ux, uy, 0.0)
        t[:3, 1] = (uy, -ux, 0.0)
    t[:3, 2] = (0.0, 0.0, -1.0)
    t[:3, 3] = (float(xa[0]), float(xa[1]), float(tip_z))
    return t


def box_corners(start: NDArray[np.float64], u: NDArray[np.float64], box: Box) -> NDArray[np.float64]:
    """World xy corners [4, 2] of one tool part's footprint with the tool at ``start``."""
    w = np.array([-u[1], u[0]])
    b = box6(box)
    centre = start + b[4] * u + b[5] * w
    return centre + _SIGNS[:, :1] * (b[0] * u) + _SIGNS[:, 1:] * (b[1] * w)


def corners_extent(start: NDArray[np.float64], u: NDArray[np.float64], boxes: Sequence[Box]
                   ) -> tuple[float, float, float, float]:
    """(x min, x max, y min, y max) over the corners of the tool's parts at ``start``: the corners of
    :func:`box_corners`, by the same arithmetic in Python floats (the same values, without arrays)."""
    sx, sy = float(start[0]), float(start[1])
    ux, uy = float(u[0]), float(u[1])
    wx, wy = -uy, ux
    xs: list[float] = []
    ys: list[float] = []
    for box in boxes:
        b0, b1, _, _, b4, b5 = box6(box)
        cx, cy = sx + b4 * ux + b5 * wx, sy + b4 * uy + b5 * wy
        ax, ay, bx, by = b0 * ux, b0 * uy, b1 * wx, b1 * wy
        for sa, sb in ((-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)):
            xs.append(cx + sa * ax + sb * bx)
            ys.append(cy + sa * ay + sb * by)
    return min(xs), max(xs), min(ys), max(ys)


def sweep_halfplanes(
    start: NDArray[np.float64], u: NDArray[np.float64], box: Box, v: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Half-planes ``N @ x <= b`` of one part's footprint swept by the translation v (a convex
    hexagon: the Minkowski sum of the rectangle and the segment [0, v]), and its xy corners."""
    corners = box_corners(start, u, box)
    w = np.array([-u[1], u[0]])
    vn = float(np.hypot(v[0], v[1]))
    if vn > 1e-12:
        pv = np.array([-v[1], v[0]]) / vn
        n = np.stack([u, -u, w, -w, pv, -pv])
    else:
        n = np.stack([u, -u, w, -w])
    support = (corners @ n.T).max(axis=0) + np.maximum(0.0, n @ v)
    return n, support, np.concatenate([corners, corners + v])


def prism_voxels(
    grid: GridSpec, normals: NDArray[np.float64], offsets: NDArray[np.float64], corners: NDArray[np.float64],
    z_lo: float, z_hi: float,
) -> NDArray[np.int64]:
    """Flat indices (sorted) of the voxels of a vertical prism (xy polygon given by half-planes) by
    the module's rasterisation rule; voxels outside the grid are dropped."""
    s = grid.voxel_m
    o = grid.origin
    shape = np.asarray(grid.shape)
    lo = np.floor((np.array([*corners.min(axis=0), z_lo]) - o) / s).astype(np.int64) - 1
    hi = np.floor((np.array([*corners.max(axis=0), z_hi]) - o) / s).astype(np.int64) + 1
    lo = np.maximum(lo, 0)
    hi = np.minimum(hi, shape - 1)
    if np.any(hi < lo):
        return np.zeros(0, np.int64)
    ix = np.arange(lo[0], hi[0] + 1)
    iy = np.arange(lo[1], hi[1] + 1)
    iz = np.arange(lo[2], hi[2] + 1)
    tol = 1e-9 * s  # a voxel whose face only touches the prism is out, whatever the rounding
    zc = o[2] + (iz + 0.5) * s
    iz = iz[(zc > z_lo - s / 2 + tol) & (zc < z_hi + s / 2 - tol)]
    if len(iz) == 0:
        return np.zeros(0, np.int64)
    xc = o[0] + (ix + 0.5) * s
    yc = o[1] + (iy + 0.5) * s
    inside = np.all(
        normals[:, 0, None, None] * xc[None, :, None] + normals[:, 1, None, None] * yc[None, None, :]
        < offsets[:, None, None] + s / 2 - tol,
        axis=0,
    )
    gi, gj = np.nonzero(inside)
    if len(gi) == 0:
        return np.zeros(0, np.int64)
    flat_xy = (ix[gi] * shape[1] + iy[gj]) * shape[2]
    return np.sort((flat_xy[:, None] + iz[None, :]).ravel())


def swept_voxels(
    grid: GridSpec, start: ArrayLike, u: ArrayLike, tip_z: float, boxes: Sequence[Box],
    travel: ArrayLike = (0.0, 0.0),
) -> NDArray[np.int64]:
    """Voxels (flat, sorted, unique) the tool covers at ``start`` and while translating by ``travel``.
    (A numba kernel: the same voxels as ``swept_voxels_reference``, its test's oracle.)"""
    st = np.asarray(start, dtype=np.float64)
    ua = np.asarray(u, dtype=np.float64)
    v = np.asarray(travel, dtype=np.float64)
    b = boxes_array(boxes)
    return _swept(grid.origin.astype(np.float64), float(grid.voxel_m), np.asarray(grid.shape, dtype=np.int64),
                  st[0], st[1], ua[0], ua[1], v[0], v[1], float(tip_z), b)


def swept_voxels_reference(
    grid: GridSpec, start: ArrayLike, u: ArrayLike, tip_z: float, boxes: Sequence[Box],
    travel: ArrayLike = (0.0, 0.0),
) -> NDArray[np.int64]:
    """``swept_voxels`` in plain numpy: each part's half-planes rasterised by ``prism_voxels``."""
    st = np.asarray(start, dtype=np.float64)
    ua = np.asarray(u, dtype=np.float64)
    v = np.asarray(travel, dtype=np.float64)
    parts = []
    for box in boxes:
        n, b, corners = sweep_halfplanes(st, ua, box, v)
        parts.append(prism_voxels(grid, n, b, corners, tip_z + box[2], tip_z + box[3]))
    if len(parts) == 1:
        return parts[0]
    return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


@njit(cache=True, fastmath=False)
def _swept(o, s, shape, sx, sy, ux, uy, vx, vy, tip_z, boxes):  # type: ignore[no-untyped-def]
    """The kernel of ``swept_voxels``: ``sweep_halfplanes`` and ``prism_voxels`` per part, the parts
    marked in one mask over their joint bounding box, read out in flat (sorted) order."""
    nb = boxes.shape[0]
    wx, wy = -uy, ux
    vn = math.hypot(vx, vy)
    nn = 6 if vn > 1e-12 else 4
    normals = np.empty((nn, 2))
    normals[0, 0], normals[0, 1] = ux, uy
    normals[1, 0], normals[1, 1] = -ux, -uy
    normals[2, 0], normals[2, 1] = wx, wy
    normals[3, 0], normals[3, 1] = -wx, -wy
    if nn == 6:
        px, py = -vy / vn, vx / vn
        normals[4, 0], normals[4, 1] = px, py
        normals[5, 0], normals[5, 1] = -px, -py
    tol = 1e-9 * s
    lo = np.empty((nb, 3), np.int64)
    hi = np.empty((nb, 3), np.int64)
    offsets = np.empty((nb, nn))
    for p in range(nb):
        cx = np.empty(4)
        cy = np.empty(4)
        for c in range(4):
            a = -1.0 if c < 2 else 1.0  # _SIGNS' order
            w = -1.0 if c % 2 == 0 else 1.0
            along = boxes[p, 4] + a * boxes[p, 0]
            side = boxes[p, 5] + w * boxes[p, 1]
            cx[c] = sx + along * ux + side * wx
            cy[c] = sy + along * uy + side * wy
        for q in range(nn):
            best = -np.inf
            for c in range(4):
                d = cx[c] * normals[q, 0] + cy[c] * normals[q, 1]
                if d > best:
                    best = d
            offsets[p, q] = best + max(0.0, normals[q, 0] * vx + normals[q, 1] * vy)
        xmin = min(cx.min(), (cx + vx).min())
        xmax = max(cx.max(), (cx + vx).max())
        ymin = min(cy.min(), (cy + vy).min())
        ymax = max(cy.max(), (cy + vy).max())
        lo[p, 0] = max(math.floor((xmin - o[0]) / s) - 1, 0)
        lo[p, 1] = max(math.floor((ymin - o[1]) / s) - 1, 0)
        lo[p, 2] = max(math.floor((tip_z + boxes[p, 2] - o[2]) / s) - 1, 0)
        hi[p, 0] = min(math.floor((xmax - o[0]) / s) + 1, shape[0] - 1)
        hi[p, 1] = min(math.floor((ymax - o[1]) / s) + 1, shape[1] - 1)
        hi[p, 2] = min(math.floor((tip_z + boxes[p, 3] - o[2]) / s) + 1, shape[2] - 1)
    glo = np.empty(3, np.int64)
    ghi = np.empty(3, np.int64)
    for d in range(3):
        glo[d] = lo[:, d].min()
        ghi[d] = hi[:, d].max()
    if ghi[0] < glo[0] or ghi[1] < glo[1] or ghi[2] < glo[2]:
        return np.zeros(0, np.int64)
    mx, my, mz = ghi[0] - glo[0] + 1, ghi[1] - glo[1] + 1, ghi[2] - glo[2] + 1
    mask = np.zeros((mx, my, mz), np.bool_)
    count = 0
    for p in range(nb):
        if hi[p, 0] < lo[p, 0] or hi[p, 1] < lo[p, 1] or hi[p, 2] < lo[p, 2]:
            continue
        z_lo, z_hi = tip_z + boxes[p, 2], tip_z + boxes[p, 3]
        for i in range(lo[p, 0], hi[p, 0] + 1):
            xc = o[0] + (i + 0.5) * s
            for j in range(lo[p, 1], hi[p, 1] + 1):
                yc = o[1] + (j + 0.5) * s
                inside = True
                for q in range(nn):
                    if not normals[q, 0] * xc + normals[q, 1] * yc < offsets[p, q] + s / 2 - tol:
                        inside = False
                        break
                if not inside:
                    continue
                for k in range(lo[p, 2], hi[p, 2] + 1):
                    zc = o[2] + (k + 0.5) * s
                    if zc > z_lo - s / 2 + tol and zc < z_hi + s / 2 - tol:
                        m = mask[i - glo[0], j - glo[1], k - glo[2]]
                        if not m:
                            mask[i - glo[0], j - glo[1], k - glo[2]] = True
                            count += 1
    out = np.empty(count, np.int64)
    n = 0
    for i in range(mx):
        for j in range(my):
            for k in range(mz):
                if mask[i, j, k]:
                    out[n] = ((i + glo[0]) * shape[1] + (j + glo[1])) * shape[2] + (k + glo[2])
                    n += 1
    return out


def swept_extent(
    start: NDArray[np.float64], u: NDArray[np.float64], tip_z: float, boxes: Sequence[Box], travel: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Exact xyz bounds (lower, upper) of the tool swept by ``travel`` (for the wall test)."""
    pts = np.concatenate([sweep_halfplanes(start, u, b, travel)[2] for b in boxes])
    z_lo = tip_z + min(b[2] for b in boxes)
    z_hi = tip_z + max(b[3] for b in boxes)
    return np.array([*pts.min(axis=0), z_lo]), np.array([*pts.max(axis=0), z_hi])


@njit(cache=True, fastmath=False)
def footprint_sweep_hits(cells, u, steps, s, labels, wall):  # type: ignore[no-untyped-def]
    """Sweep a BEV footprint along ``u``: cells ``[N, 2]`` (grid indices) moved by each of ``steps``
    (metres, increasing), a moved cell being the one its centre falls in.

    Returns the index of the first step at which a cell leaves the grid or enters ``wall`` (-1: none)
    and, per label of ``labels`` ``[X, Y]`` (int, 0: none), the index of the first step at which a cell
    enters it (-1: never, or not before that wall step; the step of the wall hit itself is included).
    The same arithmetic as ``floor((cells + 0.5) + steps * u / s)`` on arrays, so the same cells."""
    nx, ny = labels.shape
    first = np.full(labels.max() + 1, -1, np.int64)
    for t in range(steps.shape[0]):
        dx = steps[t] * u[0] / s
        dy = steps[t] * u[1] / s
        hit = False
        for c in range(cells.shape[0]):
            i = math.floor((cells[c, 0] + 0.5) + dx)
            j = math.floor((cells[c, 1] + 0.5) + dy)
            if i < 0 or i >= nx or j < 0 or j >= ny:
                hit = True
                continue
            if wall[i, j]:
                hit = True
            k = labels[i, j]
            if k > 0 and first[k] < 0:
                first[k] = t
        if hit:
            return t, first
    return -1, first


@njit(cache=True, fastmath=False)
def chain_room(target_cells, target_height, u, steps, s, labels, wall, own, fragile, heights, cell_ptr, cell_ij,
               clearance, trip_ratio, use_trip, travel, use_travel):  # type: ignore[no-untyped-def]
    """``PushSkill._chain_room`` in one pass (the same rule and float arithmetic, a test compares them):
    how far the target (``target_cells`` [N, 2], believed ``target_height`` above the floor) can be
    pushed along ``u`` before a chain object enters ``wall`` or meets a fragile one (or trips over a
    much lower one with ``use_trip``), less ``clearance``. Per label (index): ``own`` the target's own
    labels, ``fragile``, ``heights`` above the floor, and its cells ``cell_ij[cell_ptr[k]:cell_ptr[k + 1]]``.
    The objects are taken in order of the target travel at which they start moving (ties: lower label
    first, the target, label 0, first of all)."""
    n_lab = heights.shape[0]
    queued = np.full(n_lab, np.inf)  # the travel at which a label waits in the queue (inf: not queued)
    queued[0] = 0.0
    start = np.full(n_lab, np.inf)
    room = np.inf
    while True:
        k = -1
        e = np.inf
        for j in range(n_lab):  # the queue's smallest (travel, label)
            if queued[j] < e:
                e = queued[j]
                k = j
        if k < 0:
            break
        queued[k] = np.inf
        if e >= room:
            break
        if k == 0:
            at_wall, first = footprint_sweep_hits(target_cells, u, steps, s, labels, wall)
            height = target_height
        else:
            at_wall, first = footprint_sweep_hits(cell_ij[cell_ptr[k]:cell_ptr[k + 1]], u, steps, s, labels, wall)
            height = heights[k]
        if at_wall >= 0:
            room = min(room, e + (steps[at_wall] - s / 2))
        for j in range(first.shape[0]):
            if first[j] < 0 or own[j] or j == k:
                continue
            d = e + (steps[first[j]] - s / 2)
            trips = use_trip and height > trip_ratio * heights[j]
            if fragile[j] or trips:  # a thin, tall object would be pushed or trip the mover: stop before it
                room = min(room, d)
            elif d < start[j] and d < room:
                start[j] = d
                queued[j] = d
                if use_travel:  # a driven object moves at most this far
                    room = min(room, d + travel + clearance)
    return room - clearance


@njit(cache=True, fastmath=False)
def last_on_footprint(q0, q1, u0, u1, ts, o0, o1, s, foot):  # type: ignore[no-untyped-def]
    """The largest index i of ``ts`` whose point ``q - ts[i] * u`` lies in a cell of ``foot`` [X, Y]
    (cells of size ``s`` from the origin ``(o0, o1)``), -1 if none: where a push line through ``q``
    along ``u``, followed back, last crosses the footprint. The same arithmetic as
    ``floor(((q - ts * u) - o) / s)`` on arrays."""
    nx, ny = foot.shape
    for i in range(ts.shape[0] - 1, -1, -1):
        x = math.floor(((q0 - ts[i] * u0) - o0) / s)
        y = math.floor(((q1 - ts[i] * u1) - o1) / s)
        if 0 <= x < nx and 0 <= y < ny and foot[x, y]:
            return i
    return -1
