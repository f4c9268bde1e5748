"""Analytic effect model of a nudge (belief model ``nudge-effect``, role *effect*).

The target is the believed object the skill planned with: the believed-occupied voxels of object
classes in its footprint columns. Its evidence moves sideways by the nudge distance (rounded to whole voxels)
and the voxels it leaves return to the prior: nothing is known yet about what the object hid. Changed
voxels are the union of the two. Not modelled: rotation, tipping, objects in the way (the skill does
not propose nudges into believed neighbours) and the object's unseen parts, which stay where they were.
The prediction is sparse (one ``BeliefDelta`` of the changed voxels per action), so the built-in ``ig``
term re-scores only the rays the change touches.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.interfaces import Action, EffectModel, Prediction, Workspace
from msmem_core.map.belief import BeliefDelta, EvidentialMap
from msmem_nudge.skill import shift_x


class NudgeEffectConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    occupied_threshold: float = Field(0.5, ge=0.0, lt=1.0)
    """Voxels above this expected occupancy belong to the target and move with it."""
    moved_keep: float = Field(1.0, ge=0.0, le=1.0)
    """Fraction of the evidence above the prior the moved voxels keep (1: the object is as sure as before)."""


class NudgeEffect(EffectModel):
    def __init__(self, config: NudgeEffectConfig | None = None) -> None:
        self.config = config or NudgeEffectConfig()

    def target_voxels(self, belief: EvidentialMap, action: Action) -> np.ndarray:
        """[X, Y, Z] believed voxels of the nudged object: believed-occupied voxels of any object class
        in its footprint columns (a voxel on its boundary may carry a noisy class)."""
        grid = belief.grid
        o, s = grid.origin, grid.voxel_m
        x_lo, y_lo, x_hi, y_hi = action.footprint_m  # type: ignore[attr-defined]
        i0, j0 = np.floor((np.array([x_lo, y_lo]) - o[:2]) / s + 1e-6).astype(int)
        i1, j1 = np.ceil((np.array([x_hi, y_hi]) - o[:2]) / s - 1e-6).astype(int)
        mask = np.zeros(grid.shape, dtype=bool)
        region = (slice(max(i0, 0), i1), slice(max(j0, 0), j1), slice(None))
        p = belief.expected_occupancy()[region]
        cls = np.argmax(belief.eta[(slice(None), *region)], axis=0)
        mask[region] = (p > self.config.occupied_threshold) & (cls != 0)
        return mask

    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        grid = belief.grid
        keep = self.config.moved_keep
        a0, b0 = belief.alpha.reshape(-1), belief.beta.reshape(-1)
        e0 = belief.eta.reshape(belief.num_classes, -1)
        changes = []
        for a in actions:
            src = self.target_voxels(belief, a)
            n = round(a.nudge_m * a.direction[0] / grid.voxel_m)  # type: ignore[attr-defined]
            dst = shift_x(src, n)
            vacated = src & ~dst
            idx = np.flatnonzero(vacated | dst)
            alpha, beta = np.ones(len(idx), np.float32), np.ones(len(idx), np.float32)
            eta = np.ones((belief.num_classes, len(idx)), np.float32)
            # where each destination voxel's evidence comes from: n voxels back along x
            d = np.flatnonzero(dst)
            src_of = np.ravel_multi_index(np.unravel_index(d, grid.shape) - np.array([[n], [0], [0]]), grid.shape)
            pos = np.searchsorted(idx, d)
            alpha[pos] = 1.0 + keep * (a0[src_of] - 1.0)
            beta[pos] = 1.0 + keep * (b0[src_of] - 1.0)
            eta[:, pos] = 1.0 + keep * (e0[:, src_of] - 1.0)
            changes.append(BeliefDelta(idx, alpha, beta, eta).against(belief))  # only what differs
        return Prediction(belief, changes)
