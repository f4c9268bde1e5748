"""A third-party-style plugin used by the plugin-system tests: one skill and one objective term."""

from collections.abc import Iterable
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.interfaces import Action, CandidateBatch, Outcome, Simulator, Skill, Term
from msmem_core.plugins import ObjectiveTermSpec, SkillSpec, hookimpl


class WaitConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    seconds: float = Field(0.1, gt=0)


class WaitSkill(Skill):
    """Lets physics run for a while; proposes one action."""

    def __init__(self, config: WaitConfig) -> None:
        self.config = config

    def propose(self, ctx: Any) -> list[Action]:
        return [Action(kind="wait", category="perception")]

    def execute(self, sim: Simulator, action: Action, ctx: Any) -> Outcome:
        sim.step(self.config.seconds)
        return Outcome()


class ConstantConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    value: float = 1.0


class ConstantTerm(Term):
    def __init__(self, config: ConstantConfig) -> None:
        self.value = config.value

    def score(self, ctx: Any, batch: CandidateBatch) -> np.ndarray:
        return np.full(len(batch.actions), self.value)


@hookimpl
def msmem_skills() -> Iterable[SkillSpec]:
    yield SkillSpec(name="wait", factory=WaitSkill, config_model=WaitConfig, description="Let physics run")


@hookimpl
def msmem_objective_terms() -> Iterable[ObjectiveTermSpec]:
    yield ObjectiveTermSpec(name="constant", factory=ConstantTerm, config_model=ConstantConfig,
                            description="A constant bonus")
