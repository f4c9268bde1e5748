"""The hooks a plugin may implement. Each yields frozen spec records (see ``types``)."""

from __future__ import annotations

from collections.abc import Iterable

import pluggy

from msmem_core.plugins.types import BeliefModelSpec, CommandSpec, ObjectiveTermSpec, SimulatorSpec, SkillSpec

PROJECT = "msmem"
hookspec = pluggy.HookspecMarker(PROJECT)
hookimpl = pluggy.HookimplMarker(PROJECT)
"""Decorator for plugin functions implementing the hooks below."""


class MsmemSpecs:
    """Hook specifications. Every hook takes no arguments and yields spec records."""

    @hookspec
    def msmem_skills(self) -> Iterable[SkillSpec]:
        """Register skills (actions MSAS can choose), e.g.::

            @hookimpl
            def msmem_skills():
                yield SkillSpec(name="nudge", factory=NudgeSkill, config_model=NudgeConfig,
                                description="Sideways nudge of an object's top",
                                effect_model="nudge-effect")
        """
        yield from ()

    @hookspec
    def msmem_belief_models(self) -> Iterable[BeliefModelSpec]:
        """Register belief models (observation update and/or effect prediction), e.g.::

            @hookimpl
            def msmem_belief_models():
                yield BeliefModelSpec(name="nudge-effect", factory=NudgeEffect,
                                      config_model=NudgeEffectConfig, roles=frozenset({"effect"}),
                                      description="Analytic effect of a nudge")
        """
        yield from ()

    @hookspec
    def msmem_simulators(self) -> Iterable[SimulatorSpec]:
        """Register simulator backends, e.g.::

            @hookimpl
            def msmem_simulators():
                yield SimulatorSpec(name="mujoco", factory=MujocoSimulator,
                                    config_model=MujocoConfig, description="MuJoCo backend")
        """
        yield from ()

    @hookspec
    def msmem_objective_terms(self) -> Iterable[ObjectiveTermSpec]:
        """Register objective terms, summed with config weights into the objective, e.g.::

            @hookimpl
            def msmem_objective_terms():
                yield ObjectiveTermSpec(name="travel-cost", factory=TravelCost,
                                        config_model=TravelCostConfig,
                                        description="Penalise long gripper paths")
        """
        yield from ()

    @hookspec
    def msmem_commands(self) -> Iterable[CommandSpec]:
        """Register command-line commands (``msmem [GROUP] NAME``), e.g.::

            @hookimpl
            def msmem_commands():
                yield CommandSpec(name="nudge", action=datagen_nudge, group="datagen",
                                  summary="Training data for the nudge effect model")

        ``action`` is a function with typer-annotated parameters (or a ``typer.Typer`` group); import
        heavy modules inside its body, so that ``msmem --help`` stays fast. A hook that raises is
        reported by plugin name and the rest of the command line still works.
        """
        yield from ()
