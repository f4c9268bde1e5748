"""The voxel grid every belief, ground truth and metric is defined on."""

from __future__ import annotations

from typing import Annotated

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, Field

from msmem_core.util.validation import FROZEN_MODEL_CONFIG, Int

Count = Annotated[Int, Field(ge=1)]


class GridSpec(BaseModel):
    """Axis-aligned voxel grid: voxel (i, j, k) covers ``[o + i*s, o + (i+1)*s)`` per axis."""

    model_config = FROZEN_MODEL_CONFIG

    origin_m: tuple[float, float, float] = (-0.39, -0.01, -0.01)
    """World position of the grid's minimum corner, metres."""
    voxel_m: float = Field(0.01, gt=0.0, le=0.1)
    """Edge length of one cubic voxel, metres."""
    shape: tuple[Count, Count, Count] = (78, 40, 30)
    """Number of voxels along x, y, z."""

    @property
    def origin(self) -> NDArray[np.float64]:
        return np.asarray(self.origin_m, dtype=np.float64)

    @property
    def upper_m(self) -> NDArray[np.float64]:
        """World position of the grid's maximum corner."""
        return self.origin + self.voxel_m * np.asarray(self.shape)

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def index_of(self, points: ArrayLike) -> NDArray[np.int64]:
        """Voxel index (N, 3) containing each world point (N, 3); may lie outside the grid."""
        p = np.asarray(points, dtype=np.float64)
        return np.floor((p - self.origin) / self.voxel_m).astype(np.int64)

    def contains_index(self, idx: ArrayLike) -> NDArray[np.bool_]:
        i = np.asarray(idx)
        return np.all((i >= 0) & (i < np.asarray(self.shape)), axis=-1)

    def centers(self) -> NDArray[np.float64]:
        """World coordinates of all voxel centres, shape (X, Y, Z, 3)."""
        axes = [self.origin[a] + (np.arange(n) + 0.5) * self.voxel_m for a, n in enumerate(self.shape)]
        return np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)

    def column_boxes(self, mask: ArrayLike) -> NDArray[np.float64]:
        """Boxes [N, 2, 3] (lower and upper world corners) covering exactly the voxels of ``mask`` (the
        grid's shape): one per run of consecutive marked voxels along z in each (x, y) column."""
        m = np.asarray(mask, dtype=bool).reshape(self.shape)
        pad = np.zeros((*self.shape[:2], 1), dtype=bool)
        edges = np.diff(np.concatenate([pad, m, pad], axis=2).astype(np.int8), axis=2)
        i, j, k0 = np.nonzero(edges == 1)  # a run starts at voxel k0 ...
        _, _, k1 = np.nonzero(edges == -1)  # ... and ends before k1 (both in (i, j, k) order)
        s = self.voxel_m
        lo = self.origin + s * np.stack([i, j, k0], axis=1)
        hi = self.origin + s * np.stack([i + 1, j + 1, k1], axis=1)
        return np.stack([lo, hi], axis=1).astype(np.float64)

    @classmethod
    def around_box(cls, lower_m: ArrayLike, upper_m: ArrayLike, voxel_m: float, margin_voxels: int = 1) -> GridSpec:
        """The grid that covers the box [lower, upper] with ``margin_voxels`` on every side."""
        lo = np.asarray(lower_m, dtype=np.float64) - margin_voxels * voxel_m
        hi = np.asarray(upper_m, dtype=np.float64) + margin_voxels * voxel_m
        shape = np.ceil((hi - lo) / voxel_m - 1e-9).astype(int)
        return cls(origin_m=tuple(float(v) for v in lo), voxel_m=voxel_m, shape=tuple(int(v) for v in shape))
