"""Objective term ``semantic-entropy``: the Delta-H part of OIG for manipulation candidates.

``dH = min(0, H(before) - H(after))`` with ``H`` the Shannon entropy (nats) of the expected
categorical summed over all voxels (``EvidentialMap.total_semantic_entropy``). Clipped at 0 as in
DESIGN.md: a manipulation is penalised for the semantic uncertainty its predicted scene change adds,
never rewarded for entropy the effect model happens to remove. Weighted by [MEM]'s zeta_o = 0.2 in
the presets. Only the changed voxels contribute, so each candidate is scored on its change
(``Prediction.changes``) alone.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from msmem_core.interfaces import CandidateBatch, Category, Term
from msmem_core.map.belief import categorical_entropy


class SemanticEntropyConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")


class SemanticEntropyTerm(Term):
    applies_to: ClassVar[frozenset[Category]] = frozenset({"manipulation"})

    def __init__(self, config: SemanticEntropyConfig | None = None) -> None:
        self.config = config or SemanticEntropyConfig()

    def score(self, ctx: Any, batch: CandidateBatch) -> NDArray[np.float64]:
        pred = batch.prediction
        assert pred is not None
        eta0 = pred.base.eta.reshape(pred.base.num_classes, -1)
        out = np.zeros(len(pred))
        for k, d in enumerate(pred.changes):
            out[k] = float(categorical_entropy(eta0[:, d.idx]).sum() - categorical_entropy(d.eta).sum())
        return np.minimum(0.0, out)
