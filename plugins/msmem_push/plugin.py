"""The push skill and its analytic effect model."""

from collections.abc import Iterable

from msmem_core.plugins import BeliefModelSpec, CommandSpec, SkillSpec, hookimpl
from msmem_push.effect import AnalyticPushEffect, PushEffectConfig
from msmem_push.skill import PushConfig, PushSkill


@hookimpl
def msmem_skills() -> Iterable[SkillSpec]:
    yield SkillSpec(
        name="push",
        factory=PushSkill,
        config_model=PushConfig,
        effect_model="cnabu-push",  # the better held-out NLL (docs/explanation/cnabu.md, tests/test_cnabu_shipped.py)
        description="Uncertainty-informed push selection (UPS): push occluders of unseen regions, closed gripper",
    )


@hookimpl
def msmem_belief_models() -> Iterable[BeliefModelSpec]:
    yield BeliefModelSpec(
        name="push-analytic",
        factory=AnalyticPushEffect,
        config_model=PushEffectConfig,
        roles=frozenset({"effect"}),
        description="sigma_p: move pushed objects' evidence (chain included), lower confidence where they swept",
    )


@hookimpl
def msmem_commands() -> Iterable[CommandSpec]:
    """``msmem perf push`` (bodies import what they need on use)."""
    from msmem_push.commands import COMMANDS

    yield from COMMANDS
