"""Registers a skill named ``view``, clashing with the built-in one."""

from collections.abc import Iterable

from msmem_core.plugins import SkillSpec, hookimpl
from tests.support.good_plugin import WaitConfig, WaitSkill


@hookimpl
def msmem_skills() -> Iterable[SkillSpec]:
    yield SkillSpec(name="view", factory=WaitSkill, config_model=WaitConfig, description="clash")
