"""Objective term scoring candidates at random (a baseline policy for the next-best-view benchmark)."""

from collections.abc import Iterable
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict

from msmem_core.interfaces import CandidateBatch, Term
from msmem_core.plugins import ObjectiveTermSpec, hookimpl


class RandomConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    seed: int = 0


class RandomTerm(Term):
    def __init__(self, config: RandomConfig) -> None:
        self.rng = np.random.default_rng(config.seed)

    def score(self, ctx: Any, batch: CandidateBatch) -> np.ndarray:
        return self.rng.random(len(batch.actions))


@hookimpl
def msmem_objective_terms() -> Iterable[ObjectiveTermSpec]:
    yield ObjectiveTermSpec(name="random-score", factory=RandomTerm, config_model=RandomConfig,
                            description="Uniform random scores (baseline)")
