"""The learned belief models (plugins ``cnabu-observe``, ``cnabu-push``, ``cnabu-grasp``).

- ``cnabu-observe`` (role *observe*, sigma_o): the view's ray masks (free / occupied / class seen,
  the analytic traversal of ``msmem_analytic``) and the belief go through the observe network; the
  voxels the view's rays reached (outside the shelf's boards) take the predicted evidence, every
  other voxel keeps the prior exactly.
- ``cnabu-push`` / ``cnabu-grasp`` (role *effect*, sigma_p / sigma_g): the K candidates are predicted
  in batches of ``batch`` (the belief's share of the network's stem is computed once). The changed
  mask is ``p_change > change_threshold`` (outside the shelf's boards); there the new evidence is
  ``old * (1 - p_change) + pred * p_change``; outside it the prior is copied exactly. The result is
  a sparse ``Prediction`` holding only the changed voxels (those whose evidence differs, or with
  ``change_epsilon`` > 0 those whose expected occupancy or a class probability moves by more than
  it), so the incremental IG stays incremental. ``cnabu-grasp`` reports the whole grasped object
  (as ``grasp-analytic`` finds it, ``AnalyticGraspEffect.removal``) in ``Prediction.excluded`` for
  CDC. The shelf interior and the gripper (for the swept volumes) come from the ``Workspace``.

Weights: ``weights`` (default: the shipped ``msmem_cnabu/weights/cnabu_<kind>.pt``), loaded when the
model is built, with ``torch.load(weights_only=True)`` and the sha256 of their sidecar; a missing file
names the commands that make it.

Scenes of other classes: ``class_map`` maps each of the scene's object classes onto a distinct trained
class (``msmem_cnabu.classmap``); the network sees and predicts the mapped classes, and the evidence
of trained classes no scene class maps to is dropped.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, ClassVar

import numpy as np
import torch
from numba import njit, prange
from numpy.typing import NDArray

from msmem_cnabu.classmap import mapped_classes, onto_slots
from msmem_cnabu.configs import CNABUEffectConfig, CNABUObserveConfig
from msmem_cnabu.features import (
    belief_features,
    grasp_removals,
    grid_interior,
    manipulation_indices,
    observe_channels,
    sparse_channels,
    to_tensor,
    wall_mask,
)
from msmem_cnabu.network import FlatPrediction
from msmem_cnabu.weights import WeightsError, load_cnabu
from msmem_core.interfaces import Action, EffectModel, ObservationModel, Prediction, Workspace
from msmem_core.map.belief import BeliefDelta, EvidentialMap
from msmem_core.world.camera import Observation
from msmem_core.world.scene import model_classes


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


def _check_grid(kind: str, net: Any, belief: EvidentialMap, index: NDArray[np.int64] | None = None) -> None:
    want = tuple(net.config.grid_shape)
    if tuple(belief.grid.shape) != want:
        raise WeightsError(f"cnabu-{kind}: the weights were trained on a {want} grid, the belief has "
                           f"{tuple(belief.grid.shape)}; train weights for this grid with `msmem datagen cnabu "
                           "--voxel ...` and `msmem train cnabu`")
    if index is not None and belief.num_classes != len(index):
        raise WeightsError(f"cnabu-{kind}: its class_map takes {len(index)} classes (background and "
                           f"{len(index) - 1} scene classes), the belief has {belief.num_classes}; map each of the "
                           "scene's object classes (class_map)")
    if index is None and belief.num_classes != net.config.num_classes:
        raise WeightsError(f"cnabu-{kind}: the weights were trained on {net.config.num_classes} classes (background "
                           f"and {net.config.num_classes - 1} object classes), the belief has {belief.num_classes}; "
                           "set class_map to map the scene's object classes onto the trained ones")


def _features(belief: EvidentialMap, index: NDArray[np.int64] | None = None, num_classes: int = 0) -> torch.Tensor:
    """The network's belief features (its prior evidence is not needed: ``_blend`` reads the belief); with
    a class map (``index``, onto ``num_classes`` trained classes) the class evidence goes into the mapped
    classes' slots, the others holding none (evidence 1)."""
    eta = belief.eta if index is None else onto_slots(belief.eta, index, num_classes, fill=1)
    return belief_features(to_tensor(belief.alpha)[None], to_tensor(belief.beta)[None], to_tensor(eta)[None])


def _scene_classes(out: FlatPrediction, index: NDArray[np.int64] | None) -> FlatPrediction:
    """With a class map (``index``): the prediction's class evidence of the mapped trained classes, in the
    scene's class order (that of the trained classes no scene class maps to is dropped)."""
    if index is None:
        return out
    return dataclasses.replace(out, residual=out.residual[torch.from_numpy(np.r_[0, 1, 2 + index])])


def _deltas(belief: EvidentialMap, out: FlatPrediction, epsilon: float = 0.0) -> list[BeliefDelta]:
    """Per action the blended change (``_blend``), keeping only voxels whose evidence differs (``epsilon``
    0) or whose expected occupancy or a class probability moves by more than ``epsilon``."""
    c = belief.num_classes
    i = out.idx.numpy().astype(np.int64)  # a copy: _blend compacts it in place
    na, nb, ne, kept = _blend(belief.alpha.reshape(-1), belief.beta.reshape(-1), belief.eta.reshape(c, -1), i,
                              out.p.numpy().astype(np.float32, copy=False),
                              np.ascontiguousarray(out.residual.numpy(), dtype=np.float32),
                              out.counts.numpy().astype(np.int64), np.float32(epsilon))
    res, start = [], 0
    for n in kept:
        res.append(BeliefDelta(i[start:start + n], na[start:start + n], nb[start:start + n], ne[:, start:start + n]))
        start += n
    return res


@njit(cache=True, parallel=True)
def _blend(alpha, beta, eta, idx, p, ev, counts, epsilon):  # type: ignore[no-untyped-def]
    """``old * (1 - p) + pred * p`` per selected voxel in float32, floored at 1 (float rounding only),
    with the network's evidence ``pred = relu(old - 1 + res) + 1`` from its residual ``res``
    ([2 + C, M]). With ``epsilon`` 0, voxels whose evidence equals the old one are dropped; above 0,
    voxels whose expected occupancy and every expected class probability move by at most
    ``epsilon``. Channel by channel in parallel (each streaming through one of the belief's arrays),
    then compacted in input order: ``idx`` is overwritten with the kept indices. Returns the new
    evidence and how many voxels each action (``counts``) kept."""
    m, c = idx.shape[0], eta.shape[0]
    one = np.float32(1.0)
    new = np.empty((2 + c, m), np.float32)
    differs = np.zeros((2 + c, m), np.bool_)
    for ch in prange(2 + c):
        old = alpha if ch == 0 else beta if ch == 1 else eta[ch - 2]
        for t in range(m):
            v, q = idx[t], p[t]
            o = old[v]
            x = max(o * (one - q) + (max(o - one + ev[ch, t], np.float32(0.0)) + one) * q, one)
            new[ch, t] = x
            differs[ch, t] = x != o
    keep = np.zeros(m, np.bool_)
    if epsilon > 0:
        for t in prange(m):
            v = idx[t]
            a0, b0, a1, b1 = alpha[v], beta[v], new[0, t], new[1, t]
            moved = abs(a1 / (a1 + b1) - a0 / (a0 + b0)) > epsilon
            t0, t1 = np.float32(0.0), np.float32(0.0)
            for k in range(c):
                t0 += eta[k, v]
                t1 += new[2 + k, t]
            for k in range(c):
                moved |= abs(new[2 + k, t] / t1 - eta[k, v] / t0) > epsilon
            keep[t] = moved
    else:
        for ch in range(2 + c):
            for t in range(m):
                keep[t] |= differs[ch, t]
    kept = np.zeros(counts.shape[0], np.int64)
    n, t = 0, 0
    for o in range(counts.shape[0]):
        for _ in range(counts[o]):
            if keep[t]:
                idx[n] = idx[t]
                for ch in range(2 + c):
                    new[ch, n] = new[ch, t]
                n += 1
                kept[o] += 1
            t += 1
    return new[0, :n], new[1, :n], new[2:, :n], kept


class CNABUObservationModel(ObservationModel):
    """sigma_o by the learned observe network (see the module docstring)."""

    kind: ClassVar[str] = "observe"

    def __init__(self, config: CNABUObserveConfig | None = None) -> None:
        from msmem_analytic.observation import AnalyticObservationConfig, AnalyticObservationModel

        self.config = cfg = config or CNABUObserveConfig()
        self.net, self.meta = load_cnabu("observe", cfg.weights)
        self.classes = model_classes(self.meta.get("classes"), self.net.config.num_classes)
        self._index: NDArray[np.int64] | None = None
        """With a ``class_map``: per class the model takes (the scene's), the trained class it maps to."""
        if cfg.class_map is not None:
            self.trained_classes = self.classes
            self.classes, self._index = mapped_classes(cfg.class_map, self.classes, "cnabu-observe")
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
        _check_grid("observe", self.net, belief, self._index)
        k = self.net.config.num_classes
        if self._index is not None:  # the rays' labels in the mapped classes' slots
            seen = onto_slots(seen, self._index, k, fill=False)
        with _Threads(self.config.threads):
            feats = _features(belief, self._index, k)
            act = torch.from_numpy(observe_channels(free, occ, seen))[None]  # bool: the stem scatters its nonzeros
            region = torch.from_numpy((free | occ) & ~self.walls(belief))[None]
            out = _scene_classes(self.net.predict_flat(feats, None, act, torch.zeros(1, 0), 0.5, region=region),
                                 self._index)
        return _deltas(belief, out)[0].apply(belief)


class _CNABUEffect(EffectModel):
    kind: ClassVar[str] = ""

    def __init__(self, config: CNABUEffectConfig | None = None) -> None:
        self.config = config or CNABUEffectConfig()
        self.net, self.meta = load_cnabu(self.kind, self.config.weights)
        self.classes = model_classes(self.meta.get("classes"), self.net.config.num_classes)
        self._index: NDArray[np.int64] | None = None
        """With a ``class_map``: per class the model takes (the scene's), the trained class it maps to."""
        if self.config.class_map is not None:
            self.trained_classes = self.classes
            self.classes, self._index = mapped_classes(self.config.class_map, self.classes, f"cnabu-{self.kind}")
        self._inside_cache: dict[tuple[Any, tuple[float, ...]], torch.Tensor] = {}

    def _inside(self, grid: Any, interior: tuple[float, ...]) -> torch.Tensor:
        """[X, Y, Z]: the voxels a prediction may change (not the shelf's boards), cached."""
        key = (grid, interior)
        if key not in self._inside_cache:
            self._inside_cache[key] = torch.from_numpy(~wall_mask(grid, interior))
        return self._inside_cache[key]

    def predict(self, belief: EvidentialMap, actions: Sequence[Action], workspace: Workspace) -> Prediction:
        cfg = self.config
        grid = belief.grid
        _check_grid(self.kind, self.net, belief, self._index)
        self._check_actions(actions)
        k_n = len(actions)
        if k_n == 0:
            return Prediction(belief, [], excluded=[] if self.kind == "grasp" else None)
        with _Threads(cfg.threads):
            feats = _features(belief, self._index, self.net.config.num_classes)
            prep = self.net.prepare(feats, None, self._inside(grid, workspace.interior_box)[None])
            ind, scalars, regions = manipulation_indices(self.kind, belief, actions, workspace)
            parts = []
            for start in range(0, k_n, cfg.batch):
                stop = min(start + cfg.batch, k_n)
                vox, nz = sparse_channels(grid, ind[start:stop])
                parts.append(self.net.predict_flat(prep, None, vox, torch.from_numpy(scalars[start:stop]),
                                                   cfg.change_threshold, region=None, nonzero=nz))
        out = _scene_classes(FlatPrediction.cat(parts), self._index)
        deltas = _deltas(belief, out, cfg.change_epsilon)
        if self.kind == "grasp" and cfg.grasped_region == "free" and regions is not None:
            from msmem_grasp.effect import emptied

            deltas = [emptied(belief, d, r, cfg.free_evidence).against(belief)
                      for d, r in zip(deltas, regions, strict=True)]
        if self.kind == "grasp":  # the whole grasped object is the intended removal, not only the region
            return Prediction(belief, deltas, excluded=grasp_removals(belief, actions, workspace))
        return Prediction(belief, deltas, excluded=regions)

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
