"""Training the whole-map observation network (``cnabu-map``) through rollouts of recorded views.

Data: ``observe`` shards of ``msmem datagen cnabu`` made with ``--min-views 0 --max-views 0``: the
episode's start view, then ``--samples`` random views, each stored as its ray masks, plus the ground
truth (objects do not move while only looking). With no random views before the first sample, the
shard's first belief is the analytic update of the empty map by the start view alone, so the start
view's masks are recovered exactly from it (``sequence``), and a rollout starts from the empty map
as an episode does.

Rollout training: a batch of scenes starts from the empty map; at every view the network predicts the
next belief from its own previous output (detached: truncated backpropagation of one step), the loss
(``mapnet.map_loss``: NLL of the bounded expected occupancy and class probabilities over every voxel
but the boards) is taken against the ground truth after every step, and the optimiser steps once per
view. Scenes are mirrored left-right at random (the shelf, the grid and the viewpoint sets are
symmetric), except post-manipulation sequences (their actions are not mirrored).

Post-manipulation sequences (``msmem datagen cnabu --kind observe ... --manipulate-after K``): after
K recorded views a real push was executed. At that step of a rollout the belief (the network's
current output, or a twin's belief in ``mapeval``) becomes the effect model's prediction for the
recorded push (``Effects``, ``MapTrainConfig.effect_models``, default ``push-analytic``; applied as the
MSAS loop applies it), for the network bounded like its own output (``bounded_map``) and without
gradient; the next views' masks then show what really happened, and the loss after each view is
taken against the ground truth after that view (``Sequence_.step_gt_occ``: after the push for every
later view). The weights are written (atomically, with their sidecar) after every epoch and at the
end, so a stopped run leaves its last checkpoint.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from msmem_cnabu.datagen import CNABUShard, list_shards, load_shard, predicted_belief
from msmem_cnabu.features import wall_mask
from msmem_cnabu.mapnet import MapNet, MapNetConfig, bounded_evidence, map_loss, parameter_count, top_view_loss
from msmem_core.errors import UserError
from msmem_core.interfaces import Workspace
from msmem_core.map.belief import EvidentialMap
from msmem_core.plugins import ComponentRef
from msmem_core.util.artifacts import atomic_save, load_state, write_sidecar
from msmem_core.util.validation import error_lines
from msmem_core.world.scene import CLASS_NAMES, model_classes

WEIGHTS_FORMAT = "msmem-cnabu-map"
WEIGHTS_VERSION = 1


class MapTrainConfig(BaseModel):
    """How ``msmem train cnabu-map`` trains (recorded in the sidecar)."""

    model_config = ConfigDict(extra="forbid")

    epochs: float = Field(2.0, gt=0.0)
    """Passes over the training scenes (fractions allowed)."""
    batch: int = Field(4, ge=1, le=64)
    """Scenes unrolled together."""
    lr: float = Field(2e-3, gt=0.0)
    weight_decay: float = Field(1e-4, ge=0.0)
    sem_weight: float = Field(1.0, ge=0.0)
    """Weight of the class NLL beside the occupancy NLL."""
    occupied_class_weight: float = Field(1.0, ge=1.0)
    """Weight of truly occupied voxels in the class NLL (``mapnet.map_loss``)."""
    top_view_weight: float = Field(0.0, ge=0.0)
    """Weight of the top-view class NLL (``mapnet.top_view_loss``: the surface the paper's 2-D semantic
    map is scored on) beside the per-voxel NLLs."""
    seed: int = 0
    threads: int = Field(1, ge=1, le=64)
    time_limit_s: float | None = Field(None, gt=0.0)
    """Stop (and write the weights) after this many seconds of training."""
    max_scenes: int | None = Field(None, ge=1)
    """Use at most this many training shards (the first ones, sorted by name)."""
    batches: int | None = Field(None, ge=1)
    """Train exactly this many batches instead of ``epochs``, listing the data folder again at every pass
    (so a folder still being generated contributes its new shards; the sidecar lists the seeds used)."""
    class_map: dict[str, str] | None = None
    """Scene class -> built-in class, for data of other classes (``sequence``); the weights then serve
    such scenes through ``cnabu-map``'s ``class_map`` with the same map. Built-in data is unaffected."""
    effect_models: dict[str, ComponentRef] = Field(
        default_factory=lambda: {"push": ComponentRef(name="push-analytic")})
    """The effect model (a belief-model plugin with the role ``effect``) applied at a post-manipulation
    sequence's manipulation steps, by skill."""


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
    from msmem_cnabu.mapmodel import mapped_classes

    mapped, index = mapped_classes(class_map, CLASS_NAMES)
    if mapped != classes:
        raise UserError(f"shard of scene {shard.seed} holds the classes {', '.join(classes[1:])}; the class map "
                        f"names {', '.join(mapped[1:])} (the same classes, in the scene's order, are needed)")
    return remap_classes(seq, index, len(CLASS_NAMES))


def remap_classes(seq: Sequence_, index: NDArray[np.int64], num_classes: int) -> Sequence_:
    """``seq`` with its class ``c`` moved to class ``index[c]`` of ``num_classes``: the class masks (the
    others stay empty), the ground-truth labels and the target class of its manipulations."""
    from msmem_cnabu.mapmodel import onto_slots

    seen = onto_slots(seq.seen, index, num_classes, fill=False, axis=1)
    lut = index.astype(np.int8)
    manipulations = {t: a.model_copy(update={"target_class": int(index[a.target_class])})
                     if getattr(a, "target_class", None) is not None else a for t, a in seq.manipulations.items()}
    return replace(seq, seen=seen, step_gt_cls=lut[seq.step_gt_cls], manipulations=manipulations)


def _sequence(shard: CNABUShard) -> Sequence_:
    from msmem_cnabu.training import mirror_ok

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
    """The effect models a rollout applies at manipulation steps, by skill (``MapTrainConfig.effect_models``),
    built by the plugin manager."""

    def __init__(self, refs: dict[str, ComponentRef] | None = None) -> None:
        from msmem_core.plugins.manager import get_plugin_manager

        self.refs = dict(refs if refs is not None else MapTrainConfig().effect_models)
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


def _batch(seqs: Sequence[Sequence_], flips: Sequence[bool]) -> dict[str, Any]:
    """Tensors [B, T, ...] of the sequences (``flips``: mirrored in x), and per sequence its manipulations
    (``manipulations``) and ``workspace``."""
    if any(f and s.manipulations for s, f in zip(seqs, flips, strict=True)):
        raise ValueError("post-manipulation sequences are not mirrored (their actions are not)")

    def st(get: Callable[[Sequence_], NDArray[Any]], axis: int) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(np.stack(
            [np.flip(get(s), axis) if f else get(s) for s, f in zip(seqs, flips, strict=True)])))

    # flip x: axis 1 of [T, X, Y, Z], 2 of [T, C, X, Y, Z]
    return {
        "free": st(lambda s: s.free, 1), "occ": st(lambda s: s.occ, 1), "seen": st(lambda s: s.seen, 2),
        "gt_occ": st(lambda s: s.step_gt_occ, 1), "gt_cls": st(lambda s: s.step_gt_cls.astype(np.int64), 1),
        "manipulations": [s.manipulations for s in seqs], "workspace": [s.workspace for s in seqs],
    }


def empty_evidence(bsz: int, shape: Sequence[int], num_classes: int) -> tuple[torch.Tensor, ...]:
    return (torch.ones(bsz, *shape), torch.ones(bsz, *shape), torch.ones(bsz, num_classes, *shape))


def manipulate(net: MapNet, a: torch.Tensor, b: torch.Tensor, e: torch.Tensor, i: int, action: Any,
               workspace: Workspace, effects: Effects) -> None:
    """Batch element ``i`` of the network's belief (a, b, e) becomes the effect model's prediction for
    ``action``, bounded like the network's output (``bounded_map``); in place, without gradient."""
    with torch.no_grad():
        belief = EvidentialMap(workspace.grid, a[i].numpy(), b[i].numpy(), e[i].numpy())
        out = bounded_map(effects.apply(belief, action, workspace), net.config.s_max, net.config.t_max)
        a[i], b[i], e[i] = torch.from_numpy(out.alpha), torch.from_numpy(out.beta), torch.from_numpy(out.eta)


def rollout_loss(net: MapNet, batch: dict[str, Any], valid: torch.Tensor, sem_weight: float = 1.0,
                 opt: torch.optim.Optimizer | None = None, sched: Any = None, occupied_class_weight: float = 1.0,
                 effects: Effects | None = None, trace: list[tuple[torch.Tensor, torch.Tensor]] | None = None,
                 top_view_weight: float = 0.0) -> list[tuple[float, float, float]]:
    """Unroll the batch's views from the empty map, each step on the network's own (detached) output;
    with ``opt``, one optimiser step (and ``sched`` step) per view. Before a view that follows a
    manipulation, the belief becomes ``effects``' prediction for it (``manipulate``; default effect
    models if None). Per view: (occupancy NLL, class NLL, top-view class NLL) against the ground truth
    after that view, the last weighted by ``top_view_weight`` in the optimised loss; ``trace`` collects
    each view's (detached) output logits."""
    cfg = net.config
    bsz = batch["free"].shape[0]
    a, b, e = empty_evidence(bsz, batch["free"].shape[2:], cfg.num_classes)
    out = []
    for t in range(batch["free"].shape[1]):
        for i, manips in enumerate(batch.get("manipulations", [{}] * bsz)):
            if t in manips:
                effects = effects or Effects()
                manipulate(net, a, b, e, i, manips[t], batch["workspace"][i], effects)
        with torch.set_grad_enabled(opt is not None):
            o, c = net(a, b, e, batch["free"][:, t], batch["occ"][:, t], batch["seen"][:, t], valid)
            lo, lc = map_loss(o, c, batch["gt_occ"][:, t], batch["gt_cls"][:, t], valid, cfg.s_max, cfg.t_max,
                              occupied_class_weight, occupied_only=cfg.class_head == "object")
            lt = top_view_loss(o, c, batch["gt_cls"][:, t], valid, cfg.s_max, cfg.t_max)
        if trace is not None:
            trace.append((o.detach(), c.detach()))
        if opt is not None:
            opt.zero_grad(set_to_none=True)
            (lo + sem_weight * lc + top_view_weight * lt).backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
            opt.step()
            if sched is not None:
                sched.step()
        with torch.no_grad():
            a, b, e, _, _ = bounded_evidence(o.detach(), c.detach(), cfg.s_max, cfg.t_max)
        out.append((lo.item(), lc.item(), lt.item()))
    return out


def load_widened(net: MapNet, state: dict[str, torch.Tensor], source: str) -> None:
    """Load ``state`` into ``net``; a weight matrix whose input grew (features appended at the end of
    the per-voxel inputs, e.g. ``nearest_class``) keeps its old columns and gets zeros for the new
    ones, so the widened network starts as the old one's function of the old features."""
    own = net.state_dict()
    for k, v in state.items():
        if k not in own:
            raise UserError(f"--init {source}: parameter {k} is not in this network")
        o = own[k]
        if o.shape == v.shape:
            own[k] = v
        elif v.dim() == 2 and o.dim() == 2 and o.shape[0] == v.shape[0] and o.shape[1] > v.shape[1]:
            own[k] = torch.cat([v, torch.zeros(o.shape[0], o.shape[1] - v.shape[1], dtype=v.dtype)], 1)
        else:
            raise UserError(f"--init {source}: parameter {k} has shape {tuple(v.shape)}, this network's "
                            f"{tuple(o.shape)}")
    net.load_state_dict(own)


def write_weights(net: MapNet, out: Path, record: dict[str, Any]) -> dict[str, Any]:
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_save(net.state_dict(), out)
    head = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "kind": "map",
            "classes": list(model_classes(None, net.config.num_classes) or ())}  # datagen scenes: built-ins
    return write_sidecar(out, head, {"model": net.config.model_dump(), "parameters": parameter_count(net), **record})


def _folders(dirs: Sequence[Path], max_scenes: int | None) -> list[list[Path]]:
    """The observe shards of each data folder (the first ``max_scenes`` of each)."""
    return [list_shards(d, "observe")[:max_scenes] for d in dirs]


def _batches(listing: Sequence[Sequence[Path]], size: int, rng: np.random.Generator) -> list[list[Path]]:
    """One pass: each folder's shards in a random order, cut into batches of ``size`` (a batch never
    mixes folders, whose sequences may differ in length), the batches of all folders shuffled together."""
    out: list[list[Path]] = []
    for paths in listing:
        order = rng.permutation(len(paths))
        out += [[paths[i] for i in order[s:s + size]] for s in range(0, len(order) - size + 1, size)]
    if not out:
        raise UserError(f"no folder holds a batch of {size} scenes")
    if len(listing) == 1:  # one folder: the order of the permutation (as before several folders were allowed)
        return out
    return [out[i] for i in rng.permutation(len(out))]


def train_map(data_dir: str | Path | Sequence[str | Path], out: str | Path, cfg: MapTrainConfig,
              model_cfg: MapNetConfig | None = None, heldout_dir: str | Path | None = None,
              log: Callable[[str], None] = print, init: str | Path | None = None,
              arch: dict[str, Any] | None = None) -> dict[str, Any]:
    """Train on the observe shards of ``data_dir``, one folder or several (see the module docstring);
    returns the sidecar. With several folders (e.g. 40-view hard scenes and post-manipulation
    sequences of 12 views) each batch comes from one folder, and folders are drawn in proportion to
    their number of scenes; they must share the grid and the classes. ``arch``: network settings
    (``MapNetConfig`` fields) when ``model_cfg`` is not given; the grid and the class count come from
    the data."""
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    dirs = [Path(data_dir)] if isinstance(data_dir, str | Path) else [Path(d) for d in data_dir]
    if not dirs:
        raise UserError("no training data folder given")
    listing = _folders(dirs, cfg.max_scenes)
    firsts = [sequence(load_shard(paths[0]), cfg.class_map) for paths in listing]
    first = max(firsts, key=len)
    shape = first.gt_occ.shape
    for d, f in zip(dirs, firsts, strict=True):
        if f.gt_occ.shape != shape or f.seen.shape[1] != first.seen.shape[1]:
            raise UserError(f"{d}: grid {f.gt_occ.shape} with {f.seen.shape[1]} classes, but {dirs[0]} has "
                            f"{shape} with {first.seen.shape[1]}: the folders must share the grid and the classes")
    paths = [p for ps in listing for p in ps]
    if model_cfg is None:
        try:
            model_cfg = MapNetConfig(grid_shape=shape, num_classes=first.seen.shape[1], **(arch or {}))
        except ValidationError as e:
            raise UserError(f"network settings (--arch): {error_lines(e)}") from e
    if tuple(model_cfg.grid_shape) != tuple(shape):
        raise UserError(f"the data's grid is {shape}, the network's {tuple(model_cfg.grid_shape)}")
    net = MapNet(model_cfg)
    if init is not None:
        load_widened(net, load_state(Path(init), UserError, "initial weights"), str(init))
    valid = torch.from_numpy(first.valid)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    total_batches = cfg.batches or max(1, int(cfg.epochs * len(paths) / cfg.batch))
    used: set[Path] = set()
    manipulated: set[int] = set()
    # the schedule steps once per view: sized for the longest sequences (shorter ones end it early)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=total_batches * len(first) + 1,
                                                pct_start=0.05)
    effects = Effects(cfg.effect_models)
    history: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    done = 0
    stopped = "epochs"
    out = Path(out)
    views = " + ".join(f"{len(ps)} scenes x {len(f)} views" for ps, f in zip(listing, firsts, strict=True))
    log(f"train cnabu-map: {views}, {parameter_count(net)} parameters, {total_batches} batches of {cfg.batch}")

    while done < total_batches:
        if cfg.batches is not None and done:  # a growing folder: take its new shards too
            listing = _folders(dirs, cfg.max_scenes)
        for chosen in _batches(listing, cfg.batch, rng):
            used.update(chosen)
            seqs = [sequence(load_shard(p), cfg.class_map) for p in chosen]
            flips = [bool(rng.integers(2)) and q.mirror_ok for q in seqs]
            manipulated.update(q.seed for q in seqs if q.manipulations)
            batch = _batch(seqs, flips)
            net.train()
            losses = rollout_loss(net, batch, valid, cfg.sem_weight, opt, sched, cfg.occupied_class_weight, effects,
                                  top_view_weight=cfg.top_view_weight)
            done += 1
            rec = {"batch": done, "seconds": time.perf_counter() - t0, "occ_nll_last": losses[-1][0],
                   "sem_nll_last": losses[-1][1], "occ_nll_mean": float(np.mean([x[0] for x in losses])),
                   "sem_nll_mean": float(np.mean([x[1] for x in losses])),
                   "top_view_nll_mean": float(np.mean([x[2] for x in losses]))}
            history.append(rec)
            if done % 10 == 0 or done == total_batches:
                log(f"batch {done}/{total_batches} {rec['seconds']:.0f}s occ {rec['occ_nll_mean']:.4f} "
                    f"(last view {rec['occ_nll_last']:.4f}) sem {rec['sem_nll_mean']:.4f} "
                    f"(last {rec['sem_nll_last']:.4f}) top view {rec['top_view_nll_mean']:.4f}")
            if done % 25 == 0:
                rec = _record(cfg, sorted(used), history, time.perf_counter() - t0, "checkpoint", manipulated)
                write_weights(net.eval(), out, rec)
            if cfg.time_limit_s is not None and time.perf_counter() - t0 > cfg.time_limit_s:
                stopped = "time limit"
                break
            if done >= total_batches:
                break
        if stopped == "time limit":
            break
    record = _record(cfg, sorted(used), history, time.perf_counter() - t0, stopped, manipulated)
    net.eval()
    if heldout_dir is not None:
        from msmem_cnabu.mapeval import evaluate_rollouts

        record["heldout"] = evaluate_rollouts(net, heldout_dir, log=log, effects=effects, class_map=cfg.class_map)
    return write_weights(net, out, record)


def _record(cfg: MapTrainConfig, paths: Sequence[Path], history: list[dict[str, Any]], seconds: float,
            stopped: str, manipulated: set[int]) -> dict[str, Any]:
    seeds = sorted(int(p.stem.split("_")[1]) for p in paths)
    folders: dict[str, int] = {}
    for p in paths:
        folders[str(Path(p).parent)] = folders.get(str(Path(p).parent), 0) + 1
    data: dict[str, Any] = {"scenes": len(paths), "seed_min": seeds[0], "seed_max": seeds[-1],
                            "folder": next(iter(folders))}
    if len(folders) > 1:
        data["folders"] = folders
    return {"effect_models": {k: r.model_dump() for k, r in cfg.effect_models.items()},
            "post_manipulation_scenes": len(manipulated),
            "train": cfg.model_dump(), "data": data,
            "seeds": seeds, "seconds": seconds, "stopped": stopped, "history": history[-2000:]}


def load_map_net(path: str | Path, verify: bool = True) -> tuple[MapNet, dict[str, Any]]:
    """(network in eval mode, sidecar) of map weights (``torch.load(weights_only=True)``)."""
    from msmem_cnabu.weights import WeightsError
    from msmem_core.util import artifacts

    path = Path(path)
    remedy = ("make them with `msmem datagen cnabu --kind observe --min-views 0 --max-views 0 --samples 12 ...` and "
              "`msmem train cnabu-map`")
    if not path.exists():
        raise WeightsError(f"cnabu-map: weights file {path} does not exist; {remedy}")
    meta = artifacts.read_sidecar(path, WEIGHTS_FORMAT, "a cnabu-map", "the sha256 and the architecture",
                                  "msmem train cnabu-map", WeightsError)
    net: MapNet = artifacts.load_weights(path, meta, lambda m: MapNet(MapNetConfig.model_validate(m)), verify,
                                         remedy, WeightsError)
    return net, meta
