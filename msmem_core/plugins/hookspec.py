"""The hooks a plugin may implement. Each yields frozen spec records (see ``types``)."""

from __future__ import annotations

from collections.abc import Iterable

import pluggy

from msmem_core.plugins.types import (
    BeliefModelSpec,
    CommandSpec,
    ObjectiveTermSpec,
    RobotSpec,
    SimulatorSpec,
    SkillSpec,
)
from msmem_core.world.scene import ClassSpec

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
    def msmem_robots(self) -> Iterable[RobotSpec]:
        """Register robots (the arm that carries the camera and the gripper; config ``robot``), e.g.::

            @hookimpl
            def msmem_robots():
                yield RobotSpec(name="ur5", factory=UR5Robot, config_model=UR5Config,
                                description="UR5 with a wrist camera")
        """
        yield from ()

    @hookspec
    def msmem_object_classes(self) -> Iterable[ClassSpec]:
        """Declare object classes any scene may name, declared as a scene file declares them::

            @hookimpl
            def msmem_object_classes():
                yield ClassSpec(name="chips_can", parts=(Part(kind="cylinder", size_m=(0.038, 0.25),
                                                               position_m=(0, 0, 0.125)),), mass_kg=0.2)

        A scene whose objects name such a class gets it declared, after its own classes (ids after
        the built-ins and the scene's), so the scene written to a run folder stands alone. A class
        named like a built-in, or declared by two plugins, is left out with a warning naming the plugin.
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
