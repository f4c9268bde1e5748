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
symmetric). The weights are written (atomically, with their sidecar) after every epoch and at the
end, so a stopped run leaves its last checkpoint.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from msmem_cnabu.datagen import CNABUShard, list_shards, load_shard
from msmem_cnabu.features import wall_mask
from msmem_cnabu.mapnet import MapNet, MapNetConfig, bounded_evidence, map_loss, parameter_count
from msmem_core.errors import UserError, validation_summary
from msmem_core.util.artifacts import atomic_save, write_sidecar

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
    seed: int = 0
    threads: int = Field(1, ge=1, le=64)
    time_limit_s: float | None = Field(None, gt=0.0)
    """Stop (and write the weights) after this many seconds of training."""
    max_scenes: int | None = Field(None, ge=1)
    """Use at most this many training shards (the first ones, sorted by name)."""
    batches: int | None = Field(None, ge=1)
    """Train exactly this many batches instead of ``epochs``, listing the data folder again at every pass
    (so a folder still being generated contributes its new shards; the sidecar lists the seeds used)."""


@dataclass
class Sequence_:
    """One scene's views as ray masks, with its ground truth."""

    seed: int
    free: NDArray[np.bool_]  # [T, X, Y, Z]
    occ: NDArray[np.bool_]  # [T, X, Y, Z]
    seen: NDArray[np.bool_]  # [T, C, X, Y, Z]
    gt_occ: NDArray[np.bool_]
    gt_cls: NDArray[np.int8]
    valid: NDArray[np.bool_]
    mirror_ok: bool

    def __len__(self) -> int:
        return len(self.free)


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


def sequence(shard: CNABUShard) -> Sequence_:
    """The start view and the recorded views of an observe shard, in order."""
    from msmem_cnabu.training import mirror_ok

    f0, o0, s0 = start_masks(shard)
    frees, occs, seens = [f0], [o0], [s0]
    for i in range(len(shard)):
        f, o, s = shard.masks(i)
        frees.append(f)
        occs.append(o)
        seens.append(s)
    return Sequence_(shard.seed, np.stack(frees), np.stack(occs), np.stack(seens), shard.gt_occ[0], shard.gt_cls[0],
                     ~wall_mask(shard.grid, shard.interior), mirror_ok(shard))


def _batch(seqs: Sequence[Sequence_], flips: Sequence[bool]) -> dict[str, torch.Tensor]:
    def st(get: Callable[[Sequence_], NDArray[Any]], axis: int) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(np.stack(
            [np.flip(get(s), axis) if f else get(s) for s, f in zip(seqs, flips, strict=True)])))

    # flip x: axis 1 of [T, X, Y, Z], 2 of [T, C, X, Y, Z], 0 of [X, Y, Z]
    return {
        "free": st(lambda s: s.free, 1), "occ": st(lambda s: s.occ, 1), "seen": st(lambda s: s.seen, 2),
        "gt_occ": st(lambda s: s.gt_occ, 0), "gt_cls": st(lambda s: s.gt_cls.astype(np.int64), 0),
    }


def empty_evidence(bsz: int, shape: Sequence[int], num_classes: int) -> tuple[torch.Tensor, ...]:
    return (torch.ones(bsz, *shape), torch.ones(bsz, *shape), torch.ones(bsz, num_classes, *shape))


def rollout_loss(net: MapNet, batch: dict[str, torch.Tensor], valid: torch.Tensor, sem_weight: float = 1.0,
                 opt: torch.optim.Optimizer | None = None, sched: Any = None, occupied_class_weight: float = 1.0
                 ) -> list[tuple[float, float]]:
    """Unroll the batch's views from the empty map, each step on the network's own (detached) output;
    with ``opt``, one optimiser step (and ``sched`` step) per view. Per view: (occupancy NLL, class NLL)."""
    cfg = net.config
    bsz = batch["free"].shape[0]
    a, b, e = empty_evidence(bsz, batch["free"].shape[2:], cfg.num_classes)
    out = []
    for t in range(batch["free"].shape[1]):
        with torch.set_grad_enabled(opt is not None):
            o, c = net(a, b, e, batch["free"][:, t], batch["occ"][:, t], batch["seen"][:, t], valid)
            lo, lc = map_loss(o, c, batch["gt_occ"], batch["gt_cls"], valid, cfg.s_max, cfg.t_max,
                              occupied_class_weight, occupied_only=cfg.class_head == "object")
        if opt is not None:
            opt.zero_grad(set_to_none=True)
            (lo + sem_weight * lc).backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 5.0)
            opt.step()
            if sched is not None:
                sched.step()
        with torch.no_grad():
            a, b, e, _, _ = bounded_evidence(o.detach(), c.detach(), cfg.s_max, cfg.t_max)
        out.append((lo.item(), lc.item()))
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
    head = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "kind": "map"}
    return write_sidecar(out, head, {"model": net.config.model_dump(), "parameters": parameter_count(net), **record})


def train_map(data_dir: str | Path, out: str | Path, cfg: MapTrainConfig, model_cfg: MapNetConfig | None = None,
              heldout_dir: str | Path | None = None, log: Callable[[str], None] = print,
              init: str | Path | None = None, arch: dict[str, Any] | None = None) -> dict[str, Any]:
    """Train on the observe shards of ``data_dir`` (see the module docstring); returns the sidecar.
    ``arch``: network settings (``MapNetConfig`` fields) when ``model_cfg`` is not given; the grid and
    the class count come from the data."""
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    paths = list_shards(data_dir, "observe")
    if cfg.max_scenes is not None:
        paths = paths[: cfg.max_scenes]
    first = sequence(load_shard(paths[0]))
    shape = first.gt_occ.shape
    if model_cfg is None:
        try:
            model_cfg = MapNetConfig(grid_shape=shape, num_classes=first.seen.shape[1], **(arch or {}))
        except (ValidationError, TypeError) as e:
            raise UserError(f"network settings (--arch): {validation_summary(e)}") from e
    if tuple(model_cfg.grid_shape) != tuple(shape):
        raise UserError(f"the data's grid is {shape}, the network's {tuple(model_cfg.grid_shape)}")
    net = MapNet(model_cfg)
    if init is not None:
        load_widened(net, torch.load(init, map_location="cpu", weights_only=True), str(init))
    valid = torch.from_numpy(first.valid)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    total_batches = cfg.batches or max(1, int(cfg.epochs * len(paths) / cfg.batch))
    used: set[Path] = set()
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=cfg.lr, total_steps=total_batches * len(first) + 1,
                                                pct_start=0.05)
    history: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    done = 0
    stopped = "epochs"
    out = Path(out)
    log(f"train cnabu-map: {len(paths)} scenes x {len(first)} views, {parameter_count(net)} parameters, "
        f"{total_batches} batches of {cfg.batch}")

    while done < total_batches:
        if cfg.batches is not None and done:  # a growing folder: take its new shards too
            paths = list_shards(data_dir, "observe")[: cfg.max_scenes]
        order = rng.permutation(len(paths))
        for s in range(0, len(order) - cfg.batch + 1, cfg.batch):
            used.update(paths[i] for i in order[s:s + cfg.batch])
            seqs = [sequence(load_shard(paths[i])) for i in order[s:s + cfg.batch]]
            flips = [bool(rng.integers(2)) and q.mirror_ok for q in seqs]
            batch = _batch(seqs, flips)
            net.train()
            losses = rollout_loss(net, batch, valid, cfg.sem_weight, opt, sched, cfg.occupied_class_weight)
            done += 1
            rec = {"batch": done, "seconds": time.perf_counter() - t0, "occ_nll_last": losses[-1][0],
                   "sem_nll_last": losses[-1][1], "occ_nll_mean": float(np.mean([x[0] for x in losses])),
                   "sem_nll_mean": float(np.mean([x[1] for x in losses]))}
            history.append(rec)
            if done % 10 == 0 or done == total_batches:
                log(f"batch {done}/{total_batches} {rec['seconds']:.0f}s occ {rec['occ_nll_mean']:.4f} "
                    f"(last view {rec['occ_nll_last']:.4f}) sem {rec['sem_nll_mean']:.4f} "
                    f"(last {rec['sem_nll_last']:.4f})")
            if done % 25 == 0:
                rec = _record(cfg, sorted(used), history, time.perf_counter() - t0, "checkpoint")
                write_weights(net.eval(), out, rec)
            if cfg.time_limit_s is not None and time.perf_counter() - t0 > cfg.time_limit_s:
                stopped = "time limit"
                break
            if done >= total_batches:
                break
        if stopped == "time limit":
            break
    record = _record(cfg, sorted(used), history, time.perf_counter() - t0, stopped)
    net.eval()
    if heldout_dir is not None:
        from msmem_cnabu.mapeval import evaluate_rollouts

        record["heldout"] = evaluate_rollouts(net, heldout_dir, log=log)
    return write_weights(net, out, record)


def _record(cfg: MapTrainConfig, paths: Sequence[Path], history: list[dict[str, Any]], seconds: float,
            stopped: str) -> dict[str, Any]:
    seeds = sorted(int(p.stem.split("_")[1]) for p in paths)
    return {"train": cfg.model_dump(), "data": {"scenes": len(paths), "seed_min": seeds[0], "seed_max": seeds[-1],
                                                "folder": str(Path(paths[0]).parent)},
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
