from collections.abc import Iterable

from msmem_analytic.columnfill import ColumnFillConfig, ColumnFillObservationModel
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
    yield BeliefModelSpec(
        name="column-fill",
        factory=ColumnFillObservationModel,
        config_model=ColumnFillConfig,
        roles=frozenset({"observe"}),
        description="analytic-observation plus a floor-standing prior: unobserved voxels under each column's top "
                    "believed-occupied voxel are marked occupied with its class (the floor for map prediction)",
    )
