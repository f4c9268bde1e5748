"""Volumetric information gain of candidate views (paper eq. oig, after MEM's NBV planner).

``IG(v | Phi) = sum_{rays of v} sum_k H(p_k) prod_{j<k} (1 - p_j)`` along each ray's exact voxel
traversal from the camera, with ``p`` the expected occupancy clamped as MEM (> 0.95 -> 1,
< 0.05 -> 0, shelf boards occupied) and ``H`` the binary Shannon entropy of the clamped ``p`` in
**nats** (an unknown voxel contributes ln 2 = 0.693). Rays run from the near to the far plane of the
camera; t along a ray is the z-depth. Views visited since the last manipulation get no IG: callers
pass them as ``excluded`` to :meth:`IGService.best_two_step`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core import raycast
from msmem_core.belief import EvidentialMap, bernoulli_entropy
from msmem_core.camera import CameraConfig
from msmem_core.grid import GridSpec
from msmem_core.scene import ShelfSpec


class IGConfig(BaseModel):
    """How IG is computed."""

    model_config = ConfigDict(extra="forbid")

    ray_stride_px: int = Field(8, ge=1)
    """Cast a ray through every n-th pixel in u and v (640x480 / 8 = 80x60 = 4800 rays per view)."""
    early_exit: float = Field(1e-3, ge=0.0, lt=1.0)
    """Stop a ray once its transmission is <= this; error per ray <= early_exit * entropy left on it."""
    p_occ_clamp: float = Field(0.95, gt=0.5, le=1.0)
    """Expected occupancy above this counts as certainly occupied (p = 1, H = 0), as MEM."""
    p_free_clamp: float = Field(0.05, ge=0.0, lt=0.5)
    """Expected occupancy below this counts as certainly free (p = 0, H = 0), as MEM."""


def shelf_wall_mask(grid: GridSpec, shelf: ShelfSpec) -> NDArray[np.bool_]:
    """Voxels whose centre lies outside the shelf interior, except in front of it (y < 0, open).

    These are the side, back, top and bottom boards seen through the grid's margin; IG treats them
    as occupied.
    """
    c = grid.centers()
    lo, hi = shelf.interior_lower, shelf.interior_upper
    outside = np.any((c < lo) | (c > hi), axis=-1)
    return outside & (c[..., 1] >= lo[1])


@dataclass
class IGField:
    """What IG reads from a belief: flat float32 clamped occupancy ``p`` and its entropy ``H`` (nats)."""

    p: NDArray[np.float32]
    H: NDArray[np.float32]

    def copy(self) -> IGField:
        return IGField(self.p.copy(), self.H.copy())


class IGService:
    """IG of a fixed set of viewpoints over beliefs on one grid.

    Per-view world ray directions (every ``ray_stride_px``-th pixel) are computed once here.
    """

    def __init__(
        self,
        grid: GridSpec,
        camera: CameraConfig,
        viewpoints: NDArray[np.floating],
        shelf: ShelfSpec,
        config: IGConfig | None = None,
    ) -> None:
        self.grid = grid
        self.camera = camera
        self.config = config or IGConfig()
        self.viewpoints = np.asarray(viewpoints, dtype=np.float64)
        if self.viewpoints.ndim != 3 or self.viewpoints.shape[1:] != (4, 4):
            raise ValueError(f"viewpoints must be [V, 4, 4] camera-to-world poses, got {self.viewpoints.shape}")
        self.walls = shelf_wall_mask(grid, shelf).ravel()
        self._g0, self._s, self._n = raycast.grid_params(grid)
        cam_dirs = camera.pixel_rays(self.config.ray_stride_px).reshape(-1, 3)
        self.origins = np.ascontiguousarray(self.viewpoints[:, :3, 3])
        """Camera centre per view, [V, 3]."""
        self.dirs = np.ascontiguousarray(np.einsum("vij,rj->vri", self.viewpoints[:, :3, :3], cam_dirs))
        """World ray direction per view and ray (image order), [V, R, 3], scaled so that t is the z-depth."""
        self.t_min, self.t_max = float(camera.near_m), float(camera.far_m)
        self.rays = raycast.RayTable.build(self.origins, self.dirs, grid, self.t_min, self.t_max)
        """The same rays with their grid entry/exit, grid-crossing rays first (what the kernels read)."""

    @property
    def num_views(self) -> int:
        return int(self.viewpoints.shape[0])

    @property
    def rays_per_view(self) -> int:
        return int(self.dirs.shape[1])

    def prepare(self, belief: EvidentialMap) -> IGField:
        """Clamped occupancy (MEM: > p_occ_clamp -> 1, < p_free_clamp -> 0, walls 1) and its entropy."""
        if belief.grid != self.grid:
            raise ValueError("belief grid differs from the IG service's grid")
        p = belief.expected_occupancy().ravel().astype(np.float32)
        p[p > self.config.p_occ_clamp] = 1.0
        p[p < self.config.p_free_clamp] = 0.0
        p[self.walls] = 1.0
        return IGField(p, bernoulli_entropy(p).astype(np.float32))

    def view_ig(self, fields: IGField | Sequence[IGField], exact: bool = False) -> NDArray[np.float64]:
        """IG of every view: float64 [V] for one field, [K, V] for a sequence of K fields.

        ``exact`` turns the early exit off (the result then matches the float64 reference).
        """
        eps = 0.0 if exact else self.config.early_exit
        args = (*self.rays.args(), self._g0, self._s, self._n, eps)
        if isinstance(fields, IGField):
            return raycast.ig_views(fields.p, fields.H, *args)
        if len(fields) == 0:
            return np.zeros((0, self.num_views))
        p = np.stack([f.p for f in fields], axis=1)  # voxel-major [N, K], as the batch kernel wants
        h = np.stack([f.H for f in fields], axis=1)
        stop = np.all(p >= 1.0, axis=1).astype(np.uint8)
        return raycast.ig_views_batch(p, h, stop, *args)

    def ray_ig(self, field: IGField, exact: bool = False) -> NDArray[np.float64]:
        """Per-ray IG, float64 [V, R] in image order of ``dirs`` (for debugging and tests)."""
        eps = 0.0 if exact else self.config.early_exit
        return self.rays.unsort(raycast.ig_rays(field.p, field.H, *self.rays.args(), self._g0, self._s, self._n, eps))

    def after_view(self, field: IGField, view: int) -> IGField:
        """Expected field after observing ``view``: H = 0 on its rays up to each first p == 1 voxel."""
        h = raycast.zero_entropy_along_view(
            field.p, field.H, self.origins[view], self.dirs[view], self._g0, self._s, self._n, self.t_min, self.t_max
        )
        return IGField(field.p, h)

    def best_two_step(
        self, field: IGField, excluded: set[int] | frozenset[int] = frozenset()
    ) -> tuple[int, float, int, float]:
        """Greedy two-view lookahead (paper eq. oig, view branch, as MEM).

        ``v1 = argmax IG(v)`` over views not excluded, then ``v2 = argmax IG(v | after_view(v1))``
        over views not in ``excluded | {v1}``. Returns ``(v1, ig1, v2, ig2)``; ``v2 = -1, ig2 = 0``
        when no second view is left. Raises ``ValueError`` if every view is excluded.
        """
        allowed = np.ones(self.num_views, dtype=bool)
        allowed[[v for v in excluded if 0 <= v < self.num_views]] = False
        if not allowed.any():
            raise ValueError("every viewpoint is excluded")
        ig = np.where(allowed, self.view_ig(field), -np.inf)
        v1 = int(np.argmax(ig))
        allowed[v1] = False
        if not allowed.any():
            return v1, float(ig[v1]), -1, 0.0
        ig2 = np.where(allowed, self.view_ig(self.after_view(field, v1)), -np.inf)
        v2 = int(np.argmax(ig2))
        return v1, float(ig[v1]), v2, float(ig2[v2])
