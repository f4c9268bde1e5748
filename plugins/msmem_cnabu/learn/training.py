"""Training of a CNABU network on shards from ``msmem datagen cnabu`` (AdamW, validation per epoch).

Scenes are split (seeded) into train and validation. Shards are streamed ``buffer_shards`` at a time
(shuffled within the buffer), so memory stays bounded however much data there is. Augmentation:
mirroring about the shelf's x = 0 plane (a symmetry of the shelf and the grid; x of the action's
direction flips). The learning rate follows a linear warm-up and a cosine decay. After every epoch
the validation loss terms (at the final KL weight), occupancy NLL / Brier and (push, grasp) the change map's IoU at the
threshold are computed; the weights of the best epoch (lowest validation loss) are written as a
plain state dict with a JSON sidecar (format, kind, architecture, sha256, data, history, best
metrics). A checkpoint is written every epoch, so ``resume=True`` continues a killed run.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from msmem_cnabu.features import belief_features, dilate, prior_evidence, wall_mask
from msmem_cnabu.learn.datagen import CNABUShard, list_shards, load_shard
from msmem_cnabu.learn.losses import CNABULossConfig, blend, cnabu_loss
from msmem_cnabu.network import CNABUNet, CNABUNetConfig, parameter_bytes
from msmem_cnabu.weights import WEIGHTS_FORMAT as WEIGHTS_FORMAT  # re-exported: the format this module writes
from msmem_cnabu.weights import WEIGHTS_VERSION, load_cnabu
from msmem_core.errors import UserError
from msmem_core.learn.datagen import read_manifest
from msmem_core.learn.training import TrainingRun, optimizer_step, split_scenes, training_record, warmup_cosine
from msmem_core.util.artifacts import atomic_save, write_sidecar
from msmem_core.util.artifacts import sha256_file as sha256_file  # re-exported: callers import it from here
from msmem_core.world.scene import model_classes


class TrainConfig(BaseModel):
    """Optimisation of one CNABU network."""

    model_config = ConfigDict(extra="forbid")

    epochs: int = Field(10, ge=1)
    val_fraction: float = Field(0.1, ge=0.0, lt=1.0)
    seed: int = 0
    lr: float = Field(2e-3, gt=0.0)
    weight_decay: float = Field(0.01, ge=0.0)
    warmup_steps: int = Field(50, ge=0)
    batch_size: int = Field(4, ge=1)
    grad_clip: float = Field(1.0, gt=0.0)
    mirror: bool = True
    """Augment by mirroring about x = 0 (when the grid is symmetric)."""
    buffer_shards: int = Field(16, ge=1)
    """Shards held in memory at once (samples are shuffled within them)."""
    change_dilate: int = Field(1, ge=0, le=5)
    """The GT change map is dilated by this many voxels."""
    change_threshold: float = Field(0.5, gt=0.0, lt=1.0)
    """Threshold of the change map for the validation IoU (the belief models have their own)."""
    threads: int = Field(2, ge=1)
    max_minutes: float | None = Field(None, gt=0.0)
    """Stop after the first epoch that ends past this budget."""
    resume: bool = False
    """Continue from ``<out>.ckpt`` if it exists."""
    width: int = Field(24, ge=4, le=512)
    """U-Net width (``CNABUNetConfig.width``)."""
    levels: int = Field(3, ge=1, le=5)
    init: str | None = None
    """Start from these weights (fine-tuning): the architecture is theirs (``width`` and ``levels`` are
    ignored); their kind, grid and class count must match the data."""
    loss: CNABULossConfig = CNABULossConfig()


# ------------------------------------------------------------------------------------------ batches
def sample_arrays(shard: CNABUShard, i: int, change_dilate: int = 1, mirror: bool = False) -> dict[str, np.ndarray]:
    """Inputs and targets of sample ``i`` as float32 / bool arrays (mirrored about x = 0 if asked)."""
    s = int(shard.state[i])
    walls = wall_mask(shard.grid, shard.interior)
    before_occ, before_cls = shard.gt_occ_before[s], shard.gt_cls_before[s]
    change = dilate((shard.gt_occ[i] != before_occ) | (shard.gt_cls[i] != before_cls), change_dilate)
    act = shard.act_vox[i]
    out = {
        "alpha": shard.alpha[s].astype(np.float32), "beta": shard.beta[s].astype(np.float32),
        "eta": shard.eta[s].astype(np.float32), "act_vox": act.astype(np.float32),
        "act_scalars": shard.act_scalars[i].astype(np.float32).copy(), "gt_occ": shard.gt_occ[i],
        "gt_cls": shard.gt_cls[i].astype(np.int64), "change": change, "valid": ~walls,
        "focus": shard.gt_occ[i] | change | act.any(0),
    }
    if mirror:
        for k, v in out.items():
            if k != "act_scalars":
                out[k] = np.ascontiguousarray(np.flip(v, axis=-3))
        if shard.kind in ("push", "grasp"):
            out["act_scalars"][0] *= -1.0  # x of the push direction / approach axis
    return out


def collate(items: Sequence[dict[str, np.ndarray]]) -> dict[str, torch.Tensor]:
    return {k: torch.from_numpy(np.stack([it[k] for it in items])) for k in items[0]}


def mirror_ok(shard: CNABUShard) -> bool:
    g = shard.grid
    return abs(g.origin[0] + g.upper_m[0]) < 1e-6 and abs(shard.interior[0] + shard.interior[3]) < 1e-6


def forward_loss(model: CNABUNet, batch: dict[str, torch.Tensor], epoch: float, loss_cfg: CNABULossConfig
                 ) -> tuple[dict[str, torch.Tensor], Any]:
    feats = belief_features(batch["alpha"], batch["beta"], batch["eta"])
    prior = prior_evidence(batch["alpha"], batch["beta"], batch["eta"])
    out = model(feats, prior, batch["act_vox"], batch["act_scalars"])
    terms = cnabu_loss(out.alpha, out.beta, out.eta, out.change_logit, batch["alpha"], batch["beta"], batch["eta"],
                       batch["gt_occ"], batch["gt_cls"], batch["change"] if out.change_logit is not None else None,
                       batch["valid"], batch["focus"], epoch, loss_cfg)
    return terms, out


def count_samples(path: Path) -> int:
    """Samples in a shard (reads one small member only; a bad shard raises ``ShardError`` naming it)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            return int(f["state"].shape[0])
    except Exception:
        return len(load_shard(path))  # raises the ShardError that names the file, or loads after all


def stream_batches(paths: Sequence[Path], batch_size: int, rng: np.random.Generator | None, change_dilate: int,
                   buffer_shards: int, mirror: bool) -> Iterator[tuple[list[dict[str, np.ndarray]], int]]:
    """(items, samples so far) batches: shards in random order (``rng``; None keeps the order),
    ``buffer_shards`` at a time, samples shuffled within the buffer; mirrored at random."""
    order = list(rng.permutation(len(paths))) if rng is not None else list(range(len(paths)))
    for c in range(0, len(order), buffer_shards):
        shards = [load_shard(paths[i]) for i in order[c:c + buffer_shards]]
        items = [(si, i) for si, sh in enumerate(shards) for i in range(len(sh))
                 if sh.manipulation(i) is None]  # a post-manipulation shard's push is no view to learn
        if rng is not None:
            items = [items[j] for j in rng.permutation(len(items))]
        for b in range(0, len(items), batch_size):
            chunk = items[b:b + batch_size]
            flips = rng.random(len(chunk)) < 0.5 if (rng is not None and mirror) else np.zeros(len(chunk), bool)
            yield [sample_arrays(shards[si], i, change_dilate, bool(f) and mirror_ok(shards[si]))
                   for (si, i), f in zip(chunk, flips, strict=True)], len(chunk)


# -------------------------------------------------------------------------------------- validation
def validate(model: CNABUNet, paths: Sequence[Path], epoch: float, cfg: TrainConfig) -> dict[str, float]:
    """Mean loss terms per sample, occupancy NLL and Brier (blended output, valid voxels) and the
    change map's IoU at ``change_threshold`` against the GT change."""
    model.eval()
    sums: dict[str, float] = {}
    n = 0
    inter = union = 0.0
    nll = brier = count = 0.0
    with torch.no_grad():
        for items, k in stream_batches(paths, cfg.batch_size, None, cfg.change_dilate, cfg.buffer_shards, False):
            batch = collate(items)
            terms, out = forward_loss(model, batch, epoch, cfg.loss)
            for key, v in terms.items():
                sums[key] = sums.get(key, 0.0) + float(v) * k
            n += k
            a, b = out.alpha, out.beta
            if out.change_logit is not None:
                p = torch.sigmoid(out.change_logit)
                a, b = blend(batch["alpha"], a, p), blend(batch["beta"], b, p)
                pred = (p > cfg.change_threshold) & batch["valid"]
                gt = batch["change"] & batch["valid"]
                inter += float((pred & gt).sum())
                union += float((pred | gt).sum())
            q = (a / (a + b)).double().clamp(1e-6, 1 - 1e-6)
            y = batch["gt_occ"].double()
            v = batch["valid"]
            nll += float((-(y * q.log() + (1 - y) * (1 - q).log()))[v].sum())
            brier += float(((q - y) ** 2)[v].sum())
            count += float(v.sum())
    out_m = {k: v / max(n, 1) for k, v in sums.items()}
    out_m["occ_nll"] = nll / max(count, 1.0)
    out_m["occ_brier"] = brier / max(count, 1.0)
    if union > 0:
        out_m["change_iou"] = inter / union
    return out_m


# ------------------------------------------------------------------------------------------- train
def train(
    kind: str,
    data_dir: str | Path,
    out: str | Path,
    config: TrainConfig | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Train a ``kind`` network, keep the best weights at ``out`` (+ sidecar) and return the sidecar."""
    cfg = config or TrainConfig()
    torch.set_num_threads(cfg.threads)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    paths = list_shards(data_dir, kind)
    first = load_shard(paths[0])
    if first.kind != kind:
        raise UserError(f"{paths[0]} holds {first.kind!r} samples, not {kind!r}")
    sizes = [count_samples(p) for p in paths]
    keep = [i for i, s in enumerate(sizes) if s > 0]
    if not keep:
        raise UserError(f"the shards in {data_dir} hold no samples (a scene's skill found no candidate); "
                        "generate more scenes with `msmem datagen cnabu`")
    paths, sizes = [paths[i] for i in keep], [sizes[i] for i in keep]
    val_idx, train_idx = split_scenes(len(paths), cfg.val_fraction, cfg.seed)
    val_paths, train_paths = [paths[i] for i in val_idx], [paths[i] for i in train_idx]
    n_train = sum(sizes[i] for i in train_idx)
    log(f"{kind}: {len(train_paths)} training scenes ({n_train} samples), {len(val_paths)} validation scenes "
        f"({sum(sizes[i] for i in val_idx)} samples)")
    if not val_paths:
        log("warning: no validation scenes (--val-fraction 0 or a single scene): the last epoch is kept")

    torch.manual_seed(cfg.seed)
    model_cfg = CNABUNetConfig(kind=kind, grid_shape=tuple(first.grid.shape), num_classes=int(first.eta.shape[1]),
                               width=cfg.width, levels=cfg.levels)
    model = CNABUNet(model_cfg)
    if cfg.init is not None:
        model = initial_network(kind, cfg.init, model_cfg)
        model_cfg = model.config
        log(f"fine-tuning {cfg.init} (width {model_cfg.width}, {model_cfg.levels} levels)")
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps_per_epoch = sum(math.ceil(sizes[i] / cfg.batch_size) for i in train_idx)  # upper bound
    lr_at = warmup_cosine(cfg.lr, cfg.warmup_steps, cfg.epochs * steps_per_epoch)
    run = TrainingRun(out, model, opt, cfg.resume, log)
    step = run.step or 0
    data_info = {
        "dir": str(data_dir),
        "train_scenes": [p.stem for p in train_paths],
        "val_scenes": [p.stem for p in val_paths],
        "train_samples": n_train,
        "manifest": read_manifest(data_dir),
    }
    if cfg.init is not None:
        data_info["init"] = {"path": cfg.init, "sha256": sha256_file(cfg.init)}

    def write_sidecar(history: list[dict[str, Any]], best: dict[str, Any], seconds: float) -> None:
        _write_sidecar(out, kind, model_cfg, cfg, data_info, history, best, seconds)

    run.start(progress, total=(cfg.epochs - run.start_epoch) * n_train)
    try:
        for epoch in range(run.start_epoch, cfg.epochs):
            model.train()
            t_epoch = time.perf_counter()
            running: dict[str, float] = {}
            seen = 0
            erng = np.random.default_rng([cfg.seed, epoch])
            for items, k in stream_batches(train_paths, cfg.batch_size, erng, cfg.change_dilate, cfg.buffer_shards,
                                           cfg.mirror):
                batch = collate(items)
                terms, _ = forward_loss(model, batch, epoch + seen / max(n_train, 1), cfg.loss)
                total = float(terms["total"].detach())
                if not math.isfinite(total):
                    raise UserError(f"the loss became {total} at epoch {epoch}; lower --lr")
                optimizer_step(model, opt, terms["total"], lr_at(step), cfg.grad_clip)
                step += 1
                seen += k
                for key, v in terms.items():
                    running[key] = running.get(key, 0.0) + float(v.detach()) * k
                run.advance(k, epoch, f"{total:.4f}")
            running = {key: v / max(seen, 1) for key, v in running.items()}
            train_s = time.perf_counter() - t_epoch
            # at the final KL weight, so that epochs compare on one objective
            val = validate(model, val_paths, cfg.loss.anneal_epochs, cfg) if val_paths else {}
            seconds = run.seconds()
            rec = {"epoch": epoch, "train": running, "val": val, "seconds": seconds, "epoch_train_seconds": train_s,
                   "lr": lr_at(step - 1)}
            msg = (f"epoch {epoch}: train {running['total']:.4f}"
                   + (f"  val {val['total']:.4f}  occ NLL {val['occ_nll']:.4f}  Brier {val['occ_brier']:.4f}"
                      + (f"  change IoU {val['change_iou']:.3f}" if "change_iou" in val else "") if val else "")
                   + f"  ({train_s:.1f} s train, {seconds / 60:.1f} min)")
            if run.end_epoch(epoch, rec, val.get("total", running["total"]), msg, write_sidecar, cfg.max_minutes, step):
                break
    finally:
        run.stop()
    return run.result()


def initial_network(kind: str, path: str | Path, data_cfg: CNABUNetConfig) -> CNABUNet:
    """The network of the ``kind`` weights at ``path`` in training mode, refused in one line when its
    grid or class count is not the data's (``data_cfg``)."""
    net, _ = load_cnabu(kind, path)
    have, want = net.config, data_cfg
    if tuple(have.grid_shape) != tuple(want.grid_shape) or have.num_classes != want.num_classes:
        raise UserError(f"--init {path}: trained on a {tuple(have.grid_shape)} grid with {have.num_classes} classes, "
                        f"the data has {tuple(want.grid_shape)} and {want.num_classes}")
    net.train()
    return net


def write_weights(model: CNABUNet, out: str | Path, **meta: Any) -> dict[str, Any]:
    """Save a network's state dict with a minimal sidecar (format, kind, architecture, sha256, ``meta``)
    that ``load_cnabu`` accepts; for experiments and tests (``train`` writes the full sidecar)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_save(model.state_dict(), out)
    head = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "kind": model.config.kind}
    return write_sidecar(out, head, {"model": model.config.model_dump(), **meta})


def _write_sidecar(out: Path, kind: str, model_cfg: CNABUNetConfig, cfg: TrainConfig, data: dict[str, Any],
                   history: list[dict[str, Any]], best: dict[str, Any], seconds: float) -> None:
    head = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION, "kind": kind,
            "classes": list(model_classes(None, model_cfg.num_classes) or ())}  # datagen scenes: built-ins
    model = {"parameter_bytes": parameter_bytes(CNABUNet(model_cfg)), "model": model_cfg.model_dump()}
    write_sidecar(out, head, training_record(model, cfg.model_dump(), data, history, best, seconds))
