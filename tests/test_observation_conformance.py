"""The observation-model conformance suite: the shipped models pass it, and models that break the
role's rules (change their input, drop below the prior, forget the ray record) fail it by name."""

from __future__ import annotations

import numpy as np
import pytest
from msmem_analytic.observation import AnalyticObservationModel

from msmem_core.interfaces import ObservationModel
from msmem_core.map.belief import EvidentialMap
from msmem_core.testing import ConformanceError, ConformanceUsageError, observation_model_conformance
from msmem_core.world.grid import GridSpec

SMALL = GridSpec(origin_m=(-0.4, -0.02, -0.02), voxel_m=0.02, shape=(40, 21, 16))


@pytest.mark.parametrize("name", ["analytic-observation", "column-fill"])
def test_the_analytic_models_conform(name: str) -> None:
    b = observation_model_conformance(name, grid=SMALL)
    assert (b.expected_occupancy() > 0.9).sum() > 10  # the scene's objects were seen


def test_the_default_learned_model_conforms() -> None:
    b = observation_model_conformance("cnabu-map", views=2)
    assert b.observed is not None
    assert b.observed.any()


class _InPlace(ObservationModel):
    def update(self, belief: EvidentialMap, observation: object) -> EvidentialMap:
        out = AnalyticObservationModel().update(belief, observation)  # type: ignore[arg-type]
        belief.alpha[...] = out.alpha  # writes into its input
        return out


class _BelowPrior(ObservationModel):
    def update(self, belief: EvidentialMap, observation: object) -> EvidentialMap:
        out = AnalyticObservationModel().update(belief, observation)  # type: ignore[arg-type]
        out.beta[0, 0, 0] = 0.5
        return out


class _Forgets(ObservationModel):
    def update(self, belief: EvidentialMap, observation: object) -> EvidentialMap:
        out = AnalyticObservationModel().update(belief, observation)  # type: ignore[arg-type]
        rec = np.zeros(belief.grid.shape, dtype=bool)
        rec[np.random.default_rng(belief.observed is not None).integers(0, 2, rec.shape).astype(bool)] = True
        return EvidentialMap(out.grid, out.alpha, out.beta, out.eta, rec)


@pytest.mark.parametrize(("model", "message"), [(_InPlace, "modified the belief it was given"),
                                                (_BelowPrior, "below the prior"),
                                                (_Forgets, "observed lost")])
def test_a_model_that_breaks_a_rule_fails_naming_it(model: type, message: str) -> None:
    with pytest.raises(ConformanceError, match=message):
        observation_model_conformance(model, grid=SMALL)


def test_the_suite_refuses_what_is_not_an_observation_model() -> None:
    with pytest.raises(ConformanceUsageError, match="ObservationModel"):
        observation_model_conformance(lambda: object(), grid=SMALL)  # type: ignore[arg-type, return-value]
