"""Objective term ``cdc``: the Collateral Disturbance Constraint of DOIG (paper eq. udiff, doig).

``U_diff`` = voxels that are confident after the action (semantic vacuity ``chi_{t+1} < tau_chi``)
and whose most likely class differs from the class they had before. A voxel whose class was
*unknown* before (``chi_t >= tau_chi``) is never counted: learning what an unseen voxel is, is the
point of acting, not a disturbance. Voxels in ``Prediction.excluded`` (a grasp's intended removal:
the grasped object's region clipped to the gripper's opening box) are ignored too.

The term returns ``-|U_diff|``; with weight ``zeta_cdc`` the objective becomes
``DOIG = OIG - zeta_cdc * |U_diff|``. Views change nothing, so the term applies to manipulation
candidates only. Only each candidate's changed voxels (``Prediction.changes``) can differ, so only
those are compared.
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.interfaces import CandidateBatch, Category, DecisionContext, Term


class CDCConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    tau_chi: float | None = Field(None, gt=0.0, le=1.0)
    """Vacuity threshold of a confident voxel; None: the MSAS ``tau_chi``."""


def disturbed_voxels(
    eta_before: NDArray[np.floating],
    eta_after: NDArray[np.floating],
    tau_chi: float,
    excluded: NDArray[np.bool_] | None = None,
) -> NDArray[np.bool_]:
    """``U_diff`` over a set of voxels: Dirichlet evidence ``[C, M]`` before and after -> mask ``[M]``."""
    c = eta_before.shape[0]
    known_before = c / eta_before.sum(axis=0) < tau_chi
    confident_after = c / eta_after.sum(axis=0) < tau_chi
    changed = np.argmax(eta_before, axis=0) != np.argmax(eta_after, axis=0)
    out = known_before & confident_after & changed
    if excluded is not None:
        out &= ~excluded
    return out


class CDCTerm(Term):
    applies_to: ClassVar[frozenset[Category]] = frozenset({"manipulation"})

    def __init__(self, config: CDCConfig | None = None) -> None:
        self.config = config or CDCConfig()

    def score(self, ctx: DecisionContext, batch: CandidateBatch) -> NDArray[np.float64]:
        pred = batch.prediction
        assert pred is not None
        tau = self.config.tau_chi if self.config.tau_chi is not None else ctx.tau_chi
        eta0 = pred.base.eta.reshape(pred.base.num_classes, -1)
        out = np.zeros(len(pred))
        for k, d in enumerate(pred.changes):
            out[k] = disturbed_voxels(eta0[:, d.idx], d.eta, tau, pred.excluded_among(k)).sum()
        return -out
