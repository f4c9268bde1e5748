from collections.abc import Iterable

from msmem_core.plugins import SkillSpec, hookimpl
from msmem_view.skill import ViewConfig, ViewSkill


@hookimpl
def msmem_skills() -> Iterable[SkillSpec]:
    yield SkillSpec(
        name="view",
        factory=ViewSkill,
        config_model=ViewConfig,
        description="Next-best view: observe from one of the candidate viewpoints",
    )
