"""Objective term ``ig``: the information-gain part of OIG (paper eq. OIG).

Views: IG(v | belief), and for the argmax view the greedy second step max_v' IG(v' | after v) is
added ([MEM]'s two-step view value). Manipulations: max_v IG(v | predicted belief).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict

from msmem_core.interfaces import CandidateBatch, Term


class IGTermConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")

    two_step: bool = True
    """Add the greedy second view's IG to the best view's value."""


class IGTerm(Term):
    def __init__(self, config: IGTermConfig | None = None) -> None:
        self.config = config or IGTermConfig()

    def score(self, ctx: Any, batch: CandidateBatch) -> NDArray[np.float64]:
        if batch.category == "perception":
            assert batch.view_indices is not None
            ig = np.asarray(ctx.ig.view_ig(ctx.field), dtype=np.float64)
            scores = ig[batch.view_indices]
            if self.config.two_step and len(scores):
                v1, _ig1, _v2, ig2 = ctx.ig.best_two_step(ctx.field, set(ctx.visited))
                scores[batch.view_indices == v1] += ig2
            return scores
        assert batch.prediction is not None
        fields = [ctx.ig.prepare(b) for b in batch.prediction.beliefs]
        return np.asarray(ctx.ig.view_ig(fields), dtype=np.float64).max(axis=1)
