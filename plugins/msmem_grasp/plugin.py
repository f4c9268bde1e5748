"""The grasp skill (UGS with FE-UMGF) and its analytic effect model."""

from collections.abc import Iterable

from msmem_core.plugins import BeliefModelSpec, CommandSpec, SkillSpec, hookimpl
from msmem_grasp.effect import AnalyticGraspEffect, GraspEffectConfig
from msmem_grasp.skill import GraspConfig, GraspSkill


@hookimpl
def msmem_skills() -> Iterable[SkillSpec]:
    yield SkillSpec(
        name="grasp",
        factory=GraspSkill,
        config_model=GraspConfig,
        effect_model="cnabu-grasp",  # the better held-out NLL (docs/explanation/cnabu.md, tests/test_cnabu_shipped.py)
        description="Uncertainty-informed grasp selection (UGS): FE-vMF grasps fused over steps (FE-UMGF), "
                    "collision-free from the open front, lift and retreat out of the shelf",
    )


@hookimpl
def msmem_belief_models() -> Iterable[BeliefModelSpec]:
    yield BeliefModelSpec(
        name="grasp-analytic",
        factory=AnalyticGraspEffect,
        config_model=GraspEffectConfig,
        roles=frozenset({"effect"}),
        description="sigma_g: the grasped object's region returns to the prior; objects in its way out are "
                    "pushed out of the shelf, their corridor believed free",
    )


@hookimpl
def msmem_commands() -> Iterable[CommandSpec]:
    """``msmem datagen grasp, train fe-vmf, eval fe-vmf and bench-grasp`` (bodies import what they need on use)."""
    from msmem_grasp.commands import COMMANDS

    yield from COMMANDS
