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
from numba import njit
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.interfaces import CandidateBatch, Category, DecisionContext, Term
from msmem_core.map.gain import _sum, sums_pairwise


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


@njit(cache=True, fastmath=False)
def _count_disturbed(eta0, idx, eta1, tau, pairwise0, pairwise1, excluded, use_excluded):  # type: ignore[no-untyped-def]
    nc = eta0.shape[0]
    c = np.float32(nc)
    e0 = np.empty(nc, dtype=np.float32)
    e1 = np.empty(nc, dtype=np.float32)
    count = 0
    for m in range(len(idx)):
        if use_excluded and excluded[m]:
            continue
        b0, b1 = 0, 0
        for k in range(nc):  # argmax: the first of the largest, as numpy's
            e0[k] = eta0[k, idx[m]]
            e1[k] = eta1[k, m]
            if e0[k] > e0[b0]:
                b0 = k
            if e1[k] > e1[b1]:
                b1 = k
        if b0 != b1 and c / _sum(e0, nc, pairwise0) < tau and c / _sum(e1, nc, pairwise1) < tau:
            count += 1
    return count


def count_disturbed(eta: NDArray[np.float32], idx: NDArray[np.int64], eta_after: NDArray[np.float32], tau_chi: float,
                    excluded: NDArray[np.bool_] | None = None) -> int:
    """``disturbed_voxels(eta[:, idx], eta_after, tau_chi, excluded).sum()`` for float32 evidence ``eta``
    [C, N] and ``eta_after`` [C, M] in one pass, with the same float32 sums (a test); other dtypes go
    to numpy."""
    eta_after = np.asarray(eta_after)
    if eta.dtype != np.float32 or eta_after.dtype != np.float32 or eta.ndim != 2:
        return int(disturbed_voxels(eta[:, idx], eta_after, tau_chi, excluded).sum())
    ex = np.zeros(0, dtype=np.bool_) if excluded is None else np.asarray(excluded, dtype=np.bool_)
    idx = np.asarray(idx, dtype=np.int64)
    # the layout numpy gives eta[:, idx] (column-major: its class sums are pairwise), from two columns
    pairwise0 = sums_pairwise(eta[:, idx[:2]]) if len(idx) > 1 else True
    return int(_count_disturbed(eta, idx, eta_after, np.float32(tau_chi), pairwise0, sums_pairwise(eta_after), ex,
                                excluded is not None))


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
            out[k] = count_disturbed(eta0, d.idx, d.eta, tau, pred.excluded_among(k))
        return -out
