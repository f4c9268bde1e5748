"""Recorded view sequences as rollouts see them: the views of an observe shard as ray masks, with the
ground truth when each was taken and the manipulations between them, and the effect models that turn
a rollout's belief into the prediction for such a manipulation (shared by ``maptrain`` and ``mapeval``).

Data: ``observe`` shards of ``msmem datagen cnabu`` made with ``--min-views 0 --max-views 0``: the
episode's start view, then ``--samples`` random views, each stored as its ray masks, plus the ground
truth (objects do not move while only looking). With no random views before the first sample, the
shard's first belief is the analytic update of the empty map by the start view alone, so the start
view's masks are recovered exactly from it (``sequence``), and a rollout starts from the empty map
as an episode does.

Post-manipulation sequences (``msmem datagen cnabu --kind observe ... --manipulate-after K``): after
K recorded views a real push (or, with ``--manipulate-skill grasp``, a grasp) was executed. At that
step of a rollout the belief (the network's current output, or a twin's belief in ``mapeval``) becomes
the effect model's prediction for the recorded action (``Effects``, ``MapTrainConfig.effect_models``,
default ``default_effect_models``: ``push-analytic`` and ``grasp-analytic``; applied as the MSAS loop
applies it), for the network bounded like its own output
(``bounded_map``) and without gradient; the next views' masks then show what really happened, and a
belief is scored against the ground truth after its view (``Sequence_.step_gt_occ``: after the push
for every later view).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray

from msmem_cnabu.classmap import mapped_classes, onto_slots
from msmem_cnabu.features import wall_mask
from msmem_cnabu.learn.datagen import CNABUShard, predicted_belief
from msmem_cnabu.mapnet import MapNet
from msmem_core.errors import UserError
from msmem_core.interfaces import Workspace
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import ComponentRef
from msmem_core.world.scene import CLASS_NAMES


def default_effect_models() -> dict[str, ComponentRef]:
    """The effect models of a post-manipulation sequence's actions unless others are named: the analytic
    ones (``push-analytic``, ``grasp-analytic``), as the data generation applies them."""
    return {"push": ComponentRef(name="push-analytic"), "grasp": ComponentRef(name="grasp-analytic")}


@dataclass
class Sequence_:
    """One scene's views as ray masks, with its ground truth, and the manipulations executed between
    them (post-manipulation sequences)."""

    seed: int
    free: NDArray[np.bool_]  # [T, X, Y, Z]
    occ: NDArray[np.bool_]  # [T, X, Y, Z]
    seen: NDArray[np.bool_]  # [T, C, X, Y, Z]
    step_gt_occ: NDArray[np.bool_]  # [T, X, Y, Z]: the ground truth when view t was taken
    step_gt_cls: NDArray[np.int8]  # [T, X, Y, Z]
    valid: NDArray[np.bool_]
    mirror_ok: bool
    workspace: Workspace
    manipulations: dict[int, Any]
    """View index t -> the action executed (for real) right before view t."""

    def __len__(self) -> int:
        return len(self.free)

    @property
    def gt_occ(self) -> NDArray[np.bool_]:
        """The ground truth at the end (what a final belief is scored against)."""
        return self.step_gt_occ[-1]

    @property
    def gt_cls(self) -> NDArray[np.int8]:
        return self.step_gt_cls[-1]


def start_masks(shard: CNABUShard, w: float = 10.0) -> tuple[NDArray[np.bool_], NDArray[np.bool_], NDArray[np.bool_]]:
    """The start view's (free, occ, seen) masks, recovered from the shard's first belief (the analytic
    update of the empty map by that view alone: ``alpha = 1 + w occ``, ``beta = 1 + w free``,
    ``eta[c] = 1 + w seen[c]`` and ``eta[0] += w free``)."""
    cfg = shard.info.get("config", {})
    if cfg.get("min_views", 1) != 0 or cfg.get("max_views", 1) != 0:
        raise UserError(f"shard of scene {shard.seed}: the rollout data needs `msmem datagen cnabu --kind observe "
                        "--min-views 0 --max-views 0` (the first belief must hold the start view only)")
    s = int(shard.state[0])
    a, b, e = (x.astype(np.float32) for x in (shard.alpha[s], shard.beta[s], shard.eta[s]))
    occ = a > 1 + w / 2
    free = b > 1 + w / 2
    seen = e - 1 > w / 2
    seen[0] = (e[0] - 1 - w * free) > w / 2
    return free, occ, seen


def sequence(shard: CNABUShard, class_map: dict[str, str] | None = None) -> Sequence_:
    """The start view and the recorded views of an observe shard, in order, each with the ground truth
    when it was taken, and the manipulations between them. A shard of other classes than the built-ins
    (``msmem datagen cnabu --generator``; its ``info["classes"]``) needs ``class_map`` (scene class ->
    built-in class, as ``cnabu-map``'s parameter): its masks and labels are moved onto the built-in
    classes it maps to (``remap_classes``), so the network sees them as ``cnabu-map`` with that map
    does in an episode."""
    seq = _sequence(shard)
    classes = tuple(shard.info.get("classes") or CLASS_NAMES)
    if classes == CLASS_NAMES:
        return seq
    if class_map is None:
        raise UserError(f"shard of scene {shard.seed} holds the classes {', '.join(classes[1:])}, not the built-in "
                        "ones: give a class map onto the built-ins (--class-map)")
    mapped, index = mapped_classes(class_map, CLASS_NAMES)
    if mapped != classes:
        raise UserError(f"shard of scene {shard.seed} holds the classes {', '.join(classes[1:])}; the class map "
                        f"names {', '.join(mapped[1:])} (the same classes, in the scene's order, are needed)")
    return remap_classes(seq, index, len(CLASS_NAMES))


def remap_classes(seq: Sequence_, index: NDArray[np.int64], num_classes: int) -> Sequence_:
    """``seq`` with its class ``c`` moved to class ``index[c]`` of ``num_classes``: the class masks (the
    others stay empty), the ground-truth labels and the target class of its manipulations."""
    seen = onto_slots(seq.seen, index, num_classes, fill=False, axis=1)
    lut = index.astype(np.int8)
    manipulations = {t: a.model_copy(update={"target_class": int(index[a.target_class])})
                     if getattr(a, "target_class", None) is not None else a for t, a in seq.manipulations.items()}
    return replace(seq, seen=seen, step_gt_cls=lut[seq.step_gt_cls], manipulations=manipulations)


def _sequence(shard: CNABUShard) -> Sequence_:
    from msmem_cnabu.learn.training import mirror_ok

    f0, o0, s0 = start_masks(shard)
    s = int(shard.state[0])
    frees, occs, seens = [f0], [o0], [s0]
    gts, gcs = [shard.gt_occ_before[s]], [shard.gt_cls_before[s]]
    manipulations: dict[int, Any] = {}
    for i in range(len(shard)):
        action = shard.manipulation(i)
        if action is not None:  # before the next view
            manipulations[len(frees)] = action
            continue
        f, o, seen = shard.masks(i)
        frees.append(f)
        occs.append(o)
        seens.append(seen)
        gts.append(shard.gt_occ[i])
        gcs.append(shard.gt_cls[i])
    return Sequence_(shard.seed, np.stack(frees), np.stack(occs), np.stack(seens), np.stack(gts), np.stack(gcs),
                     ~wall_mask(shard.grid, shard.interior), mirror_ok(shard) and not manipulations,
                     shard.workspace, manipulations)


class Effects:
    """The effect models a rollout applies at manipulation steps, by skill (``MapTrainConfig.effect_models``;
    ``default_effect_models`` if not given), built by the plugin manager."""

    def __init__(self, refs: dict[str, ComponentRef] | None = None) -> None:
        from msmem_core.plugins.manager import get_plugin_manager

        self.refs = dict(refs if refs is not None else default_effect_models())
        pm = get_plugin_manager()
        self.models = {k: pm.build("belief-model", r, where=f"effect_models.{k}") for k, r in self.refs.items()}

    def record(self) -> dict[str, Any]:
        """What the sidecar records."""
        return {k: r.model_dump() for k, r in self.refs.items()}

    def apply(self, belief: EvidentialMap, action: Any, workspace: Workspace) -> EvidentialMap:
        """The belief after ``action``: its skill's effect model's prediction (``datagen.predicted_belief``)."""
        if action.kind not in self.models:
            raise UserError(f"a post-manipulation sequence holds a {action.kind!r} action and no effect model is "
                            f"set for it (effect_models has {sorted(self.models)})")
        return predicted_belief(self.models[action.kind], belief, action, workspace)


def bounded_map(belief: EvidentialMap, s_max: float, t_max: float) -> EvidentialMap:
    """``belief`` in the form of the network's output (``mapnet.bounded_evidence``): expected occupancy
    clipped to ``[1/s_max, 1 - 1/s_max]``, class probabilities mixed with the uniform just enough that
    every ``q_c >= 1/t_max``, and the least committal evidence with those means. A voxel already in that
    form (the network's own output, and what the analytic push effect makes of it: moved, reset to the
    prior or shrunk towards it) keeps its evidence up to rounding."""
    a, b, e = (x.astype(np.float64) for x in (belief.alpha, belief.beta, belief.eta))
    c = e.shape[0]
    p = np.clip(a / (a + b), 1.0 / s_max, 1.0 - 1.0 / s_max)
    q = e / e.sum(0, keepdims=True)
    qmin = q.min(0)
    lam = np.clip((1.0 / t_max - qmin) / np.maximum(1.0 / c - qmin, 1e-12), 0.0, 1.0)
    q = (1 - lam) * q + lam / c
    big_s = 1.0 / np.minimum(p, 1 - p)
    big_t = 1.0 / q.min(0)
    return EvidentialMap(belief.grid, (p * big_s).astype(np.float32), ((1 - p) * big_s).astype(np.float32),
                         (q * big_t).astype(np.float32))


def manipulate(net: MapNet, a: torch.Tensor, b: torch.Tensor, e: torch.Tensor, i: int, action: Any,
               workspace: Workspace, effects: Effects) -> None:
    """Batch element ``i`` of the network's belief (a, b, e) becomes the effect model's prediction for
    ``action``, bounded like the network's output (``bounded_map``); in place, without gradient."""
    with torch.no_grad():
        belief = EvidentialMap(workspace.grid, a[i].numpy(), b[i].numpy(), e[i].numpy())
        out = bounded_map(effects.apply(belief, action, workspace), net.config.s_max, net.config.t_max)
        a[i], b[i], e[i] = torch.from_numpy(out.alpha), torch.from_numpy(out.beta), torch.from_numpy(out.eta)
