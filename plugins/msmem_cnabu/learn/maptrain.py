"""Training the whole-map observation network (``cnabu-map``) through rollouts of recorded views.

Data: ``observe`` shards of ``msmem datagen cnabu`` made with ``--min-views 0 --max-views 0``, read as
view sequences (``rollouts.sequence``: the start view and the recorded views as ray masks, with the
ground truth when each was taken); a rollout starts from the empty map as an episode does.

Rollout training: a batch of scenes starts from the empty map; at every view the network predicts the
next belief from its own previous output (detached: truncated backpropagation of one step), the loss
(``maploss.map_loss``: NLL of the bounded expected occupancy and class probabilities over every voxel
but the boards) is taken against the ground truth after every step, and the optimiser steps once per
view. Scenes are mirrored left-right at random (the shelf, the grid and the viewpoint sets are
symmetric), except post-manipulation sequences (their actions are not mirrored).

Post-manipulation sequences (``msmem datagen cnabu --kind observe ... --manipulate-after K``): after
K recorded views a real push or grasp was executed. At that step of a rollout the network's current
output becomes the effect model's prediction for the recorded action (``rollouts.Effects``,
``MapTrainConfig.effect_models``, default ``push-analytic`` and ``grasp-analytic``; bounded like the
network's own output, ``rollouts.manipulate``, without gradient); the loss after each view is taken
against the ground truth after that view. The weights are written (atomically, with their sidecar)
after every epoch and at the end, so a stopped run leaves its last checkpoint.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from msmem_cnabu.learn.datagen import list_shards, load_shard
from msmem_cnabu.learn.maploss import map_loss, top_view_loss
from msmem_cnabu.learn.rollouts import Effects, Sequence_, default_effect_models, manipulate, sequence
from msmem_cnabu.mapnet import MapNet, MapNetConfig, bounded_evidence, parameter_count
from msmem_cnabu.weights import MAP_WEIGHTS_FORMAT, MAP_WEIGHTS_VERSION
from msmem_core.errors import UserError
from msmem_core.plugins import ComponentRef
from msmem_core.util.artifacts import atomic_save, load_state, write_sidecar
from msmem_core.util.validation import error_lines
from msmem_core.world.scene import model_classes


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
    """Weight of truly occupied voxels in the class NLL (``maploss.map_loss``)."""
    top_view_weight: float = Field(0.0, ge=0.0)
    """Weight of the top-view class NLL (``maploss.top_view_loss``: the surface the paper's 2-D semantic
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
    effect_models: dict[str, ComponentRef] = Field(default_factory=default_effect_models)
    """The effect model (a belief-model plugin with the role ``effect``) applied at a post-manipulation
    sequence's manipulation steps, by skill."""


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
    head = {"format": MAP_WEIGHTS_FORMAT, "version": MAP_WEIGHTS_VERSION, "kind": "map",
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
        from msmem_cnabu.learn.mapeval import evaluate_rollouts

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

