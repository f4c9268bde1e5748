"""A test plugin: an objective term that makes any manipulation candidate win (forces a push in tests)."""

from collections.abc import Iterable
from typing import Any, ClassVar

import numpy as np
from pydantic import BaseModel, ConfigDict

from msmem_core.interfaces import CandidateBatch, Category, Term
from msmem_core.plugins import ObjectiveTermSpec, hookimpl


class BonusConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    value: float = 1e6


class ManipulationBonus(Term):
    applies_to: ClassVar[frozenset[Category]] = frozenset({"manipulation"})

    def __init__(self, config: BonusConfig) -> None:
        self.value = config.value

    def score(self, ctx: Any, batch: CandidateBatch) -> np.ndarray:
        return np.full(len(batch.actions), self.value)


@hookimpl
def msmem_objective_terms() -> Iterable[ObjectiveTermSpec]:
    yield ObjectiveTermSpec(name="manipulation-bonus", factory=ManipulationBonus, config_model=BonusConfig,
                            description="A large constant for manipulation candidates (tests only)")
