"""msmem's plugin system (pluggy, one entry-point group ``msmem``), modelled on conda's.

A plugin is a module with functions decorated by ``hookimpl`` that yield spec records::

    from msmem_core.plugins import hookimpl, SkillSpec

    @hookimpl
    def msmem_skills():
        yield SkillSpec(name="nudge", factory=NudgeSkill, config_model=NudgeConfig,
                        description="Sideways nudge of an object's top")

and is registered in its distribution's ``pyproject.toml``::

    [project.entry-points.msmem]
    nudge = "my_package.plugin"
"""

from msmem_core.plugins.hookspec import hookimpl, hookspec
from msmem_core.plugins.manager import ComponentRef, MsmemPluginManager, get_plugin_manager
from msmem_core.plugins.types import (
    BeliefModelSpec,
    CommandSpec,
    ObjectiveTermSpec,
    RobotSpec,
    SimulatorSpec,
    SkillSpec,
    missing_extra_factory,
)

__all__ = [
    "BeliefModelSpec",
    "CommandSpec",
    "ComponentRef",
    "MsmemPluginManager",
    "ObjectiveTermSpec",
    "RobotSpec",
    "SimulatorSpec",
    "SkillSpec",
    "get_plugin_manager",
    "hookimpl",
    "hookspec",
    "missing_extra_factory",
]
