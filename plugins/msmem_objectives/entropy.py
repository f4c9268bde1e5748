"""Objective term ``semantic-entropy``: the Delta-H part of OIG for manipulation candidates.

``dH = H(before) - H(after)`` (the paper's Eq. for Delta-H), with ``H`` the Shannon entropy (nats)
of the expected categorical summed over all voxels (``EvidentialMap.total_semantic_entropy``). Only
the changed voxels contribute, so each candidate is scored on its change (``Prediction.changes``)
alone. Weighted by [MEM]'s zeta_o = 0.2 in the presets.

``clip: true`` is MEM's reference rule (docs/explanation/msas.md), ``min(0, dH)``: a manipulation is penalised for
the semantic uncertainty its predicted change adds and never rewarded for entropy the prediction
removes. The presets keep it until the unclipped form is tuned on tune10 (docs/explanation/msas.md): with
the learned effect models a push's predicted change *removes* about one nat per changed voxel (the
swept space predicted free), so unclipped dH is +2,000 to +6,500 for the best pushes, larger than
their IG, and 40 to 340 for grasps. On the completed beliefs of ``cnabu-map`` with the effect models
fine-tuned on them it is the other way round: the predictions are less certain than the belief, dH is
negative for the chosen candidates (-700 for a grasp on ``tune10`` scene 0) and the clip changes
nothing (docs/explanation/msas.md; the tune10 sweep is in docs/lab/).
"""

from __future__ import annotations

from typing import ClassVar, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from msmem_core.interfaces import CandidateBatch, Category, DecisionContext, Term
from msmem_core.map.gain import class_entropies, class_entropy, class_entropy_at


class SemanticEntropyConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    clip: bool = True
    """MEM's reference rule ``min(0, dH)``; false: the paper's ``dH`` as written."""
    removal: Literal["exempt", "counted"] = "exempt"
    """The voxels of a grasp's intended removal (``Prediction.excluded``, the whole grasped object).
    ``exempt``: they do not count, as the paper exempts them from CDC: the object leaves on purpose, and
    the space it leaves, believed free on two views' evidence, has a vaguer class (background at 0.6
    against 14 object classes) than the object it held; counted, that rise (about 1.4 nats a voxel)
    charges a grasp about as much as what it reveals. ``counted``: every changed voxel counts (the
    paper's dH as written)."""


class SemanticEntropyTerm(Term):
    applies_to: ClassVar[frozenset[Category]] = frozenset({"manipulation"})

    def __init__(self, config: SemanticEntropyConfig | None = None) -> None:
        self.config = config or SemanticEntropyConfig()

    def score(self, ctx: DecisionContext, batch: CandidateBatch) -> NDArray[np.float64]:
        pred = batch.prediction
        assert pred is not None
        eta0 = pred.base.eta.reshape(pred.base.num_classes, -1)
        out = np.zeros(len(pred))
        # the base belief's entropy per voxel: once for the whole grid where the changes cover more voxels
        # (belief.categorical_entropy's values, from one numba pass: gain.class_entropy; the whole grid's
        # at the changed voxels only)
        h0 = None
        if sum(len(d.idx) for d in pred.changes) > eta0.shape[1]:
            changed = np.zeros(eta0.shape[1], dtype=bool)
            for d in pred.changes:
                changed[d.idx] = True
            union = np.flatnonzero(changed)
            h0 = np.empty(eta0.shape[1])
            h0[union] = class_entropy_at(eta0, union)
        after = class_entropies([d.eta for d in pred.changes])
        for k, d in enumerate(pred.changes):
            before = h0[d.idx] if h0 is not None else class_entropy(eta0[:, d.idx])
            dh = before - after[k]
            gone = pred.excluded_among(k) if self.config.removal == "exempt" else None
            out[k] = float(dh.sum() if gone is None else dh[~gone].sum())
        return np.minimum(0.0, out) if self.config.clip else out
