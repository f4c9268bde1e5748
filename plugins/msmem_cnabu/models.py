"""The learned belief models (plugins ``cnabu-observe``, ``cnabu-push``, ``cnabu-grasp``).

- ``cnabu-observe`` (role *observe*, sigma_o): the view's ray masks (free / occupied / class seen,
  the analytic traversal of ``msmem_analytic``) and the belief go through the observe network; the
  voxels the view's rays reached (outside the shelf's boards) take the predicted evidence, every
  other voxel keeps the prior exactly.
- ``cnabu-push`` / ``cnabu-grasp`` (role *effect*, sigma_p / sigma_g): the K candidates are predicted
  in batches of ``batch`` (the belief's share of the network's stem is computed once). The changed
  mask is ``p_change > change_threshold`` (outside the shelf's boards); there the new evidence is
  ``old * (1 - p_change) + pred * p_change``; outside it the prior is copied exactly. The result is
  a sparse ``DeltaBeliefs`` holding only the changed voxels (those whose evidence differs), so the
  incremental IG stays incremental. ``cnabu-grasp`` reports the grasped object's believed region
  (as ``grasp-analytic`` finds it) in ``Prediction.excluded`` for CDC.

Weights: ``weights`` (default: the shipped ``msmem_cnabu/weights/cnabu_<kind>.pt``), loaded when the
model is built, with ``torch.load(weights_only=True)`` and the sha256 of their sidecar; a missing file
names the commands that make it.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch
from numpy.typing import NDArray

from msmem_cnabu.configs import CNABUEffectConfig, CNABUObserveConfig
from msmem_cnabu.features import (
    belief_features,
    grid_interior,
    manipulation_channels,
    observe_channels,
    prior_evidence,
    to_tensor,
    wall_mask,
)
from msmem_cnabu.weights import WeightsError, load_cnabu
from msmem_core.belief import BeliefDelta, DeltaBeliefs, EvidentialMap
from msmem_core.camera import Observation
from msmem_core.interfaces import Action, EffectModel, ObservationModel, Prediction


class _Threads:
    def __init__(self, n: int | None) -> None:
        self.n, self.before = n, 0

    def __enter__(self) -> None:
        if self.n is not None:
            self.before = torch.get_num_threads()
            torch.set_num_threads(self.n)

    def __exit__(self, *exc: object) -> None:
        if self.n is not None:
            torch.set_num_threads(self.before)


def _check_grid(kind: str, net: Any, belief: EvidentialMap) -> None:
    want = tuple(net.config.grid_shape)
    if tuple(belief.grid.shape) != want or belief.num_classes != net.config.num_classes:
        raise WeightsError(f"cnabu-{kind}: the weights were trained on a {want} grid with {net.config.num_classes} "
                           f"classes, the belief has {tuple(belief.grid.shape)} and {belief.num_classes}; train "
                           "weights for this grid with `msmem datagen cnabu --voxel ...` and `msmem train cnabu`")


def _inputs(belief: EvidentialMap) -> tuple[torch.Tensor, torch.Tensor]:
    a, b, e = to_tensor(belief.alpha)[None], to_tensor(belief.beta)[None], to_tensor(belief.eta)[None]
    return belief_features(a, b, e), prior_evidence(a, b, e)


def _delta(belief: EvidentialMap, idx: torch.Tensor, p: torch.Tensor, ev: torch.Tensor) -> BeliefDelta:
    """The blended change at ``idx`` (sorted flat indices), keeping only voxels whose evidence differs."""
    i = idx.numpy().astype(np.int64)
    c = belief.num_classes
    old_a = belief.alpha.reshape(-1)[i]
    old_b = belief.beta.reshape(-1)[i]
    old_e = belief.eta.reshape(c, -1)[:, i]
    pn = p.numpy().astype(np.float32)
    e = ev.numpy().astype(np.float32)
    na = old_a * (1 - pn) + e[:, 0] * pn
    nb = old_b * (1 - pn) + e[:, 1] * pn
    ne = old_e * (1 - pn)[None] + e[:, 2:].T * pn[None]
    na, nb, ne = np.maximum(na, 1.0), np.maximum(nb, 1.0), np.maximum(ne, 1.0)  # float rounding only
    keep = (na != old_a) | (nb != old_b) | np.any(ne != old_e, axis=0)
    return BeliefDelta(i[keep], na[keep].astype(np.float32), nb[keep].astype(np.float32),
                       ne[:, keep].astype(np.float32))


class CNABUObservationModel(ObservationModel):
    """sigma_o by the learned observe network (see the module docstring)."""

    kind: ClassVar[str] = "observe"

    def __init__(self, config: CNABUObserveConfig | None = None) -> None:
        from msmem_analytic.observation import AnalyticObservationConfig, AnalyticObservationModel

        self.config = cfg = config or CNABUObserveConfig()
        self.net, self.meta = load_cnabu("observe", cfg.weights)
        self.rays = AnalyticObservationModel(AnalyticObservationConfig(
            pixel_stride=cfg.pixel_stride, surface_offset_m=cfg.surface_offset_m, far_m=cfg.far_m))
        self._walls: dict[Any, NDArray[np.bool_]] = {}

    def walls(self, belief: EvidentialMap) -> NDArray[np.bool_]:
        if belief.grid not in self._walls:
            self._walls = {belief.grid: wall_mask(belief.grid, grid_interior(belief.grid, self.config.margin_voxels))}
        return self._walls[belief.grid]

    def update(self, belief: EvidentialMap, observation: Observation) -> EvidentialMap:
        return self.update_masks(belief, *self.rays.masks(belief, observation))

    def update_masks(self, belief: EvidentialMap, free: NDArray[np.bool_], occ: NDArray[np.bool_],
                     seen: NDArray[np.bool_]) -> EvidentialMap:
        """The update from a view's ray masks (free, occ [X, Y, Z], seen [C, X, Y, Z])."""
        _check_grid("observe", self.net, belief)
        with _Threads(self.config.threads):
            feats, prior = _inputs(belief)
            act = torch.from_numpy(observe_channels(free, occ, seen))[None]  # bool: the stem scatters its nonzeros
            region = torch.from_numpy((free | occ) & ~self.walls(belief))[None]
            [(idx, p, ev)] = self.net.predict_many(feats, prior, act, torch.zeros(1, 0), 0.5, region=region)
        return _delta(belief, idx, p, ev).apply(belief)


class _CNABUEffect(EffectModel):
    kind: ClassVar[str] = ""

    def __init__(self, config: CNABUEffectConfig | None = None) -> None:
        self.config = config or CNABUEffectConfig()
        self.net, self.meta = load_cnabu(self.kind, self.config.weights)

    def predict(self, belief: EvidentialMap, actions: Sequence[Action]) -> Prediction:
        cfg = self.config
        grid = belief.grid
        _check_grid(self.kind, self.net, belief)
        self._check_actions(actions)
        k_n = len(actions)
        changed = np.zeros((k_n, grid.size), dtype=bool)
        excluded = np.zeros((k_n, grid.size), dtype=bool) if self.kind == "grasp" else None
        deltas: list[BeliefDelta] = []
        if k_n == 0:
            return Prediction(DeltaBeliefs(belief, []), changed.reshape(0, *grid.shape),
                              excluded=None if excluded is None else excluded.reshape(0, *grid.shape))
        with _Threads(cfg.threads):
            feats, prior = _inputs(belief)
            walls: dict[tuple[float, ...], torch.Tensor] = {}
            for start in range(0, k_n, cfg.batch):
                chunk = list(actions[start:start + cfg.batch])
                vox, scalars, regions = manipulation_channels(self.kind, belief, chunk)
                interiors = [tuple(a.interior_m) for a in chunk]  # type: ignore[attr-defined]
                for it in set(interiors):
                    if it not in walls:
                        walls[it] = torch.from_numpy(~wall_mask(grid, it))
                region = (walls[interiors[0]][None] if len(set(interiors)) == 1
                          else torch.stack([walls[it] for it in interiors]))
                outs = self.net.predict_many(feats, prior, torch.from_numpy(np.ascontiguousarray(vox, dtype=bool)),
                                             torch.from_numpy(scalars),
                                             cfg.change_threshold, region=region)
                for j, (idx, p, ev) in enumerate(outs):
                    d = _delta(belief, idx, p, ev)
                    changed[start + j, d.idx] = True
                    if excluded is not None and regions is not None:
                        excluded[start + j, regions[j]] = True
                    deltas.append(d)
        shape = (k_n, *grid.shape)
        return Prediction(DeltaBeliefs(belief, deltas), changed.reshape(shape),
                          excluded=None if excluded is None else excluded.reshape(shape))

    def _check_actions(self, actions: Sequence[Action]) -> None:
        from msmem_grasp.skill import GraspAction
        from msmem_push.skill import PushAction

        want = PushAction if self.kind == "push" else GraspAction
        for a in actions:
            if not isinstance(a, want):
                raise TypeError(f"cnabu-{self.kind} predicts {self.kind} actions, got a {a.kind!r} action")


class CNABUPushEffect(_CNABUEffect):
    """sigma_p by the learned push network."""

    kind: ClassVar[str] = "push"


class CNABUGraspEffect(_CNABUEffect):
    """sigma_g by the learned grasp network."""

    kind: ClassVar[str] = "grasp"
