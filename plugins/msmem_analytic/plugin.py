from collections.abc import Iterable

from msmem_analytic.observation import AnalyticObservationConfig, AnalyticObservationModel
from msmem_core.plugins import BeliefModelSpec, hookimpl


@hookimpl
def msmem_belief_models() -> Iterable[BeliefModelSpec]:
    yield BeliefModelSpec(
        name="analytic-observation",
        factory=AnalyticObservationModel,
        config_model=AnalyticObservationConfig,
        roles=frozenset({"observe"}),
        description="sigma_o by exact ray traversal: free/background evidence before the hit, occupied+class at it",
    )
