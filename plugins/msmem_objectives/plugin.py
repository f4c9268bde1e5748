from collections.abc import Iterable

from msmem_core.plugins import ObjectiveTermSpec, hookimpl
from msmem_objectives.cdc import CDCConfig, CDCTerm
from msmem_objectives.entropy import SemanticEntropyConfig, SemanticEntropyTerm
from msmem_objectives.ig import IGTerm, IGTermConfig


@hookimpl
def msmem_objective_terms() -> Iterable[ObjectiveTermSpec]:
    yield ObjectiveTermSpec(
        name="ig",
        factory=IGTerm,
        config_model=IGTermConfig,
        description="Occlusion-aware information gain: two-step IG for views, best next-view IG after a manipulation",
    )
    yield ObjectiveTermSpec(
        name="semantic-entropy",
        factory=SemanticEntropyTerm,
        config_model=SemanticEntropyConfig,
        description="Delta-H: min(0, H(before) - H(after)) of the summed semantic entropy, manipulation only",
    )
    yield ObjectiveTermSpec(
        name="cdc",
        factory=CDCTerm,
        config_model=CDCConfig,
        description="Collateral disturbance: -|U_diff|, confident voxels whose known class the action changes (DOIG)",
    )
