"""``column-fill``: the analytic observation update plus a floor-standing prior, the floor a learned
map-completing observation model must clear (issue: map prediction).

After every analytic update, in each column of the shelf interior the voxels that no ray has
reached yet (``alpha == beta == 1``) below the column's highest believed-occupied voxel (expected
occupancy > 0.5) are marked occupied, with the class of that top voxel: objects stand on the shelf
board, so what is hidden under a seen surface is most likely solid. A filled voxel holds
``alpha = 1 + fill_evidence`` and ``eta[c] = 1 + fill_evidence`` (the top voxel's object class c),
``beta = 1``. The fill is not evidence: each update first removes the previous fill (voxels in that
exact state), integrates the view analytically, then fills again from the new belief, so a fill
under a surface that later turns out free disappears with it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field

from msmem_analytic.observation import AnalyticObservationConfig, AnalyticObservationModel
from msmem_core.interfaces import Observation
from msmem_core.map.belief import EvidentialMap
from msmem_core.world.grid import GridSpec


class ColumnFillConfig(AnalyticObservationConfig):
    """``analytic-observation``'s parameters plus the fill."""

    fill_evidence: float = Field(2.0, gt=0.0, lt=10.0)
    """Occupancy and class evidence of a filled voxel (p = (1 + f) / (2 + f): 0.75 for 2). Must differ from
    every sum of the analytic weights, which marks fills apart from observations."""
    margin_voxels: int = Field(1, ge=0, le=10)
    """The grid's margin around the shelf interior (``grid.margin_voxels``): boards are never filled."""


def interior_mask(grid: GridSpec, margin_voxels: int) -> NDArray[np.bool_]:
    """[X, Y, Z]: the voxels of a grid built with ``margin_voxels`` around the shelf interior, without
    that margin (the interior's columns and heights)."""
    m = margin_voxels
    mask = np.zeros(tuple(grid.shape), dtype=bool)
    x, y, z = grid.shape
    mask[m:x - m, m:y - m, m:z - m] = True
    return mask


class ColumnFillObservationModel(AnalyticObservationModel):
    """sigma_o: the analytic update, then unobserved voxels under each column's top surface filled."""

    config: ColumnFillConfig

    def __init__(self, config: ColumnFillConfig | None = None, **kw: Any) -> None:
        base = config.model_dump() if config is not None else {}
        self.config = ColumnFillConfig(**{**base, **kw})
        self._inside: dict[Any, NDArray[np.bool_]] = {}

    def inside(self, grid: GridSpec) -> NDArray[np.bool_]:
        if grid not in self._inside:
            self._inside = {grid: interior_mask(grid, self.config.margin_voxels)}
        return self._inside[grid]

    def filled(self, belief: EvidentialMap) -> NDArray[np.bool_]:
        """The voxels in the fill state (``alpha = 1 + f``, ``beta = 1``, one class at ``1 + f``, the rest 1)."""
        f = np.float32(1 + self.config.fill_evidence)
        cand = (belief.alpha == f) & (belief.beta == 1)
        if not cand.any():
            return cand
        e = belief.eta[:, cand]
        ok = ((e == f).sum(0) == 1) & ((e == 1).sum(0) == belief.num_classes - 1)
        cand[cand] = ok
        return cand

    def unfill(self, belief: EvidentialMap) -> EvidentialMap:
        out = belief.copy()
        m = self.filled(belief)
        out.alpha[m] = 1
        out.eta[:, m] = 1
        return out

    def fill(self, belief: EvidentialMap) -> EvidentialMap:
        """The belief with unobserved voxels under each interior column's top believed-occupied voxel filled."""
        inside = self.inside(belief.grid)
        occ = (belief.expected_occupancy() > 0.5) & inside
        z = occ.shape[2]
        has = occ.any(2)
        top = z - 1 - np.argmax(occ[:, :, ::-1], axis=2)  # highest occupied z per column
        below = np.arange(z)[None, None, :] < top[:, :, None]
        unseen = (belief.alpha == 1) & (belief.beta == 1)
        m = below & has[:, :, None] & unseen & inside
        out = belief.copy()
        if not m.any():
            return out
        cls_top = np.argmax(belief.eta[1:], axis=0) + 1  # [X, Y, Z] object class per voxel
        top_cls = np.take_along_axis(cls_top, top[:, :, None], axis=2)[:, :, 0]  # [X, Y]
        f = np.float32(1 + self.config.fill_evidence)
        out.alpha[m] = f
        xs, ys, zs = np.nonzero(m)
        out.eta[:, xs, ys, zs] = 1
        out.eta[top_cls[xs, ys], xs, ys, zs] = f
        return out

    def update(self, belief: EvidentialMap, observation: Observation) -> EvidentialMap:
        return self.update_masks(belief, *self.masks(belief, observation))

    def update_masks(self, belief: EvidentialMap, free: NDArray[np.bool_], occ: NDArray[np.bool_],
                     seen: NDArray[np.bool_]) -> EvidentialMap:
        """The update from a view's ray masks (free, occ [X, Y, Z], seen [C, X, Y, Z])."""
        return self.fill(self.apply_masks(self.unfill(belief), free, occ, seen))
