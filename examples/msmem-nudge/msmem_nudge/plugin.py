"""Hook implementations: what this package adds to msmem (listed by ``msmem plugins``)."""

from collections.abc import Iterable

from msmem_core.plugins import BeliefModelSpec, ObjectiveTermSpec, SkillSpec, hookimpl
from msmem_nudge.effect import NudgeEffect, NudgeEffectConfig
from msmem_nudge.skill import NudgeConfig, NudgeSkill
from msmem_nudge.travel import TravelCost, TravelCostConfig


@hookimpl
def msmem_skills() -> Iterable[SkillSpec]:
    yield SkillSpec(
        name="nudge",
        factory=NudgeSkill,
        config_model=NudgeConfig,
        effect_model="nudge-effect",
        description="Nudge an object's top sideways: fingers lowered beside it from above, moved 3-5 cm across",
    )


@hookimpl
def msmem_belief_models() -> Iterable[BeliefModelSpec]:
    yield BeliefModelSpec(
        name="nudge-effect",
        factory=NudgeEffect,
        config_model=NudgeEffectConfig,
        roles=frozenset({"effect"}),
        description="Analytic nudge effect: shift the target's believed voxels sideways, the vacated ones to the prior",
    )


@hookimpl
def msmem_objective_terms() -> Iterable[ObjectiveTermSpec]:
    yield ObjectiveTermSpec(
        name="travel-cost",
        factory=TravelCost,
        config_model=TravelCostConfig,
        description="Minus the seconds an action takes: a time per action kind plus camera or gripper travel",
    )
