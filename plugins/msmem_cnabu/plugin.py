"""Learned CNABU belief models: ``cnabu-observe`` (sigma_o), ``cnabu-push`` (sigma_p), ``cnabu-grasp`` (sigma_g)."""

from collections.abc import Iterable
from typing import Any

from msmem_cnabu.configs import CNABUEffectConfig, CNABUMapConfig, CNABUObserveConfig
from msmem_core.plugins import BeliefModelSpec, CommandSpec, hookimpl


def _observe(config: Any) -> Any:
    from msmem_cnabu.models import CNABUObservationModel

    return CNABUObservationModel(config)


def _map(config: Any) -> Any:
    from msmem_cnabu.mapmodel import CNABUMapObservationModel
    from msmem_core.world.scene import model_classes

    model = CNABUMapObservationModel(config)
    if config.class_map is not None:  # the classes its weights know, which a map that does not fit is told
        model.trained_classes = model_classes(model.meta.get("classes"), model.net.config.num_classes)
    return model


def _push(config: Any) -> Any:
    from msmem_cnabu.models import CNABUPushEffect

    return CNABUPushEffect(config)


def _grasp(config: Any) -> Any:
    from msmem_cnabu.models import CNABUGraspEffect

    return CNABUGraspEffect(config)


_WEIGHTS = ("Weights: msmem_cnabu/weights/cnabu_{k}.pt unless `weights` names a file (`msmem datagen cnabu` + "
            "`msmem train cnabu --kind {k}` make them)")


@hookimpl
def msmem_belief_models() -> Iterable[BeliefModelSpec]:
    yield BeliefModelSpec(
        name="cnabu-observe",
        factory=_observe,
        config_model=CNABUObserveConfig,
        roles=frozenset({"observe"}),
        description="sigma_o by a learned 2.5-D U-Net (CNABU) on the view's ray masks; voxels the rays did not "
                    "reach keep the prior exactly. " + _WEIGHTS.format(k="observe"),
    )
    yield BeliefModelSpec(
        name="cnabu-map",
        factory=_map,
        config_model=CNABUMapConfig,
        roles=frozenset({"observe"}),
        description="sigma_o over the whole map: a 2.5-D U-Net takes the previous belief and the view's ray masks "
                    "and predicts every voxel (interiors, backs, behind the front row), with bounded evidence. "
                    "Weights: msmem_cnabu/weights/cnabu_map.pt unless `weights` names a file (`msmem train "
                    "cnabu-map` makes them)",
    )
    yield BeliefModelSpec(
        name="cnabu-push",
        factory=_push,
        config_model=CNABUEffectConfig,
        roles=frozenset({"effect"}),
        description="sigma_p by a learned 2.5-D U-Net (CNABU) with a change map: outside p_change > "
                    "change_threshold the prior is copied exactly. " + _WEIGHTS.format(k="push"),
    )
    yield BeliefModelSpec(
        name="cnabu-grasp",
        factory=_grasp,
        config_model=CNABUEffectConfig,
        roles=frozenset({"effect"}),
        description="sigma_g by a learned 2.5-D U-Net (CNABU) with a change map: outside p_change > "
                    "change_threshold the prior is copied exactly. " + _WEIGHTS.format(k="grasp"),
    )


@hookimpl
def msmem_commands() -> Iterable[CommandSpec]:
    """``msmem datagen cnabu``, ``train cnabu``, ``train cnabu-map``, ``eval belief-models``, ``eval map`` (bodies
    import ``msmem_cnabu.learn`` on use)."""
    from msmem_cnabu.commands import COMMANDS

    yield from COMMANDS
