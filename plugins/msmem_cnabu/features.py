"""What the CNABU networks read: belief features per voxel, the action's channels, the shelf's walls.

- *Belief features* ``[3 + C, X, Y, Z]``: expected occupancy alpha / S, occupancy uncertainty 2 / S
  (S = alpha + beta), semantic vacuity C / sum(eta) and the expected class probabilities. Prior
  evidence (alpha, beta, eta) is handed to the network separately (its evidence is a residual on it).
- *Action channels* (``observe_channels``, ``manipulation_indices``), from the belief and the action
  only, never ground truth:
  - observe: the view's per-voxel masks of the analytic ray traversal (``AnalyticObservationModel
    .masks``): free, occupied, and one "seen as class c" channel per class (2 + C voxel channels);
  - push: the tool's swept volume and the tool at its start (2 voxel channels); scalars: the push
    direction (x, y), the length / 0.25 m and the tool height / 0.1 m;
  - grasp: the gripper's swept volume (approach, lift, retreat) and the grasped object's believed
    region (``AnalyticGraspEffect.target_region``, plus the contact voxel); scalars: the approach
    axis (x, y, z) and the width / 0.08 m.
- *Walls*: voxels outside the shelf interior except in front of it (``ig.shelf_wall_mask``'s rule)
  are the boards: no loss is taken there and predictions never change them.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

from msmem_core.interfaces import Workspace
from msmem_core.world.grid import GridSpec

Interior = tuple[float, float, float, float, float, float]


def grid_interior(grid: GridSpec, margin_voxels: int = 1) -> Interior:
    """The shelf interior of a grid built with ``margin_voxels`` around it (``RunConfig.grid_spec``)."""
    m = margin_voxels * grid.voxel_m
    lo = grid.origin + m
    hi = grid.upper_m - m
    return (float(lo[0]), float(lo[1]), float(lo[2]), float(hi[0]), float(hi[1]), float(hi[2]))


def wall_mask(grid: GridSpec, interior: Sequence[float] | NDArray[np.float64]) -> NDArray[np.bool_]:
    """[X, Y, Z]: voxel centres outside the interior, except in front of it (the open side)."""
    c = grid.centers()
    lo, hi = np.asarray(interior[:3]), np.asarray(interior[3:])
    outside = np.any((c < lo) | (c > hi), axis=-1)
    return outside & (c[..., 1] >= lo[1])


def belief_features(alpha: Tensor, beta: Tensor, eta: Tensor) -> Tensor:
    """[B, 3 + C, X, Y, Z] from evidence ``alpha, beta`` [B, X, Y, Z] and ``eta`` [B, C, X, Y, Z]."""
    s = alpha + beta
    tot = eta.sum(1, keepdim=True)
    c = eta.shape[1]
    return torch.cat([(alpha / s)[:, None], (2.0 / s)[:, None], c / tot, eta / tot], 1)


def prior_evidence(alpha: Tensor, beta: Tensor, eta: Tensor) -> Tensor:
    """[B, 2 + C, X, Y, Z]: the evidence stacked as the network's prior."""
    return torch.cat([alpha[:, None], beta[:, None], eta], 1)


def to_tensor(a: NDArray[Any]) -> Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))


# ------------------------------------------------------------------------------------------ actions
def observe_channels(free: NDArray[np.bool_], occ: NDArray[np.bool_], seen: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """[2 + C, X, Y, Z] voxel channels of one view from its masks."""
    return np.concatenate([free[None], occ[None], seen]).astype(bool)


def push_indices(workspace: Workspace, action: Any) -> tuple[list[NDArray[np.int64]], NDArray[np.float32]]:
    """The voxel channels of a ``PushAction`` as flat indices ([swept volume, tool at the start]) and
    its [4] scalars."""
    from msmem_push.geometry import swept_voxels

    u = action.u
    scalars = np.array([u[0], u[1], action.length_m / 0.25, action.height_m / 0.1], np.float32)
    at_start = swept_voxels(workspace.grid, action.start, action.u, action.height_m, action.tool(workspace.gripper))
    return [action.swept_indices(workspace), at_start], scalars


def grasp_indices(workspace: Workspace, action: Any, region: NDArray[np.int64]
                  ) -> tuple[list[NDArray[np.int64]], NDArray[np.float32]]:
    """The voxel channels of a ``GraspAction`` as flat indices ([swept volume, grasped region and the
    contact voxel]) and its [4] scalars; ``region``: flat indices of the grasped object's believed voxels."""
    grid = workspace.grid
    second = region
    ijk = grid.index_of(np.asarray(action.contact_m)[None])[0]
    if grid.contains_index(ijk):
        second = np.append(region, np.ravel_multi_index(tuple(ijk), grid.shape))
    a = action.matrix[:3, 2]
    scalars = np.array([a[0], a[1], a[2], action.width_m / 0.08], np.float32)
    return [action.swept_indices(workspace), second], scalars


def dense_channels(grid: GridSpec, channels: Sequence[NDArray[np.int64]]) -> NDArray[np.bool_]:
    """[F, X, Y, Z] bool channels from flat indices per channel."""
    vox = np.zeros((len(channels), grid.size), dtype=bool)
    for c, ind in enumerate(channels):
        vox[c, ind] = True
    return vox.reshape(len(channels), *grid.shape)


def grasp_regions(belief: Any, actions: Sequence[Any], workspace: Workspace) -> list[NDArray[np.int64]]:
    """The grasped object's believed region (flat indices) of each grasp, as ``grasp-analytic`` sees it."""
    from msmem_grasp.effect import AnalyticGraspEffect
    from msmem_grasp.planning import Objects

    twin = AnalyticGraspEffect()
    if not actions:
        return []
    objects = Objects.of(belief, workspace.interior_box, twin.config.occupied_threshold)
    return [twin.target_region(belief, objects, a)[1] for a in actions]


def grasp_removals(belief: Any, actions: Sequence[Any], workspace: Workspace) -> list[NDArray[np.int64]]:
    """The intended removal (flat indices) of each grasp, as ``grasp-analytic`` reports it for CDC: the
    whole grasped object (``AnalyticGraspEffect.removal``)."""
    from msmem_grasp.effect import AnalyticGraspEffect
    from msmem_grasp.planning import Objects

    twin = AnalyticGraspEffect()
    if not actions:
        return []
    objects = Objects.of(belief, workspace.interior_box, twin.config.occupied_threshold)
    occupied = twin.occupied(belief)
    return [twin.removal(belief, objects, a, occupied) for a in actions]


def manipulation_indices(kind: str, belief: Any, actions: Sequence[Any], workspace: Workspace
                         ) -> tuple[list[list[NDArray[np.int64]]], NDArray[np.float32], list[NDArray[np.int64]] | None]:
    """(per action its two voxel channels as flat indices, [K, 4] scalars, grasped regions or None)."""
    if kind == "push":
        pairs = [push_indices(workspace, a) for a in actions]
        regions = None
    elif kind == "grasp":
        regions = grasp_regions(belief, actions, workspace)
        pairs = [grasp_indices(workspace, a, r) for a, r in zip(actions, regions, strict=True)]
    else:
        raise ValueError(f"not a manipulation kind: {kind!r}")
    scalars = np.stack([p[1] for p in pairs]) if pairs else np.zeros((0, 4), np.float32)
    return [p[0] for p in pairs], scalars, regions


def sparse_channels(grid: GridSpec, channels: Sequence[Sequence[NDArray[np.int64]]]
                    ) -> tuple[Tensor, tuple[Tensor, ...]]:
    """K actions' channels (flat indices per channel) as the dense bool [K, F, X, Y, Z] tensor and its
    nonzero coordinates (k, f, i, j, z), as ``torch.nonzero(..., as_tuple=True)`` gives them but
    without scanning the dense tensor."""
    k_n, f_n = len(channels), (len(channels[0]) if channels else 0)
    flat = [ind if _increasing(ind) else np.unique(ind) for per in channels for ind in per]  # (k, f) order
    counts = np.array([len(ind) for ind in flat], dtype=np.int64)
    cat = np.concatenate(flat) if flat else np.zeros(0, np.int64)
    kf = np.repeat(np.arange(k_n * f_n), counts)
    dense = np.zeros((k_n * f_n, grid.size), dtype=bool)
    dense[kf, cat] = True
    ny, nz = grid.shape[1], grid.shape[2]
    coords = (kf // max(f_n, 1), kf % max(f_n, 1), cat // (ny * nz), (cat // nz) % ny, cat % nz)
    return (torch.from_numpy(dense.reshape(k_n, f_n, *grid.shape)),
            tuple(torch.from_numpy(np.ascontiguousarray(c)) for c in coords))


def _increasing(a: NDArray[np.int64]) -> bool:
    return bool(len(a) < 2 or np.all(a[1:] > a[:-1]))


def manipulation_channels(kind: str, belief: Any, actions: Sequence[Any], workspace: Workspace
                          ) -> tuple[NDArray[np.bool_], NDArray[np.float32], list[NDArray[np.int64]] | None]:
    """([K, 2, X, Y, Z], [K, 4], grasped regions or None) of K push or grasp actions on ``belief``."""
    grid = belief.grid
    ind, scalars, regions = manipulation_indices(kind, belief, actions, workspace)
    if not ind:
        return np.zeros((0, 2, *grid.shape), bool), scalars, regions
    return np.stack([dense_channels(grid, c) for c in ind]), scalars, regions


def dilate(mask: NDArray[np.bool_], voxels: int = 1) -> NDArray[np.bool_]:
    """Binary dilation by a (2v + 1)^3 cube over the last three axes."""
    if voxels <= 0:
        return mask.copy()
    from scipy import ndimage

    structure = np.ones((1,) * (mask.ndim - 3) + (2 * voxels + 1,) * 3, dtype=bool)
    return ndimage.binary_dilation(mask, structure=structure)
