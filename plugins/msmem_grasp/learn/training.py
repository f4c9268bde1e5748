"""Training of FE-vMF on shards from ``msmem datagen grasp`` (paper eq. fevmf_loss, AdamW).

Scenes are split (seeded) into train and validation; each step runs ``batch_scenes`` clouds as one
batch (they share no attention patch). Augmentation: mirroring about the shelf's x = 0 plane (a
symmetry of the shelf; points, normals, approaches and baselines flip their x). The learning rate
follows a linear warm-up and a cosine decay. After every epoch the validation loss terms and the
affordance AUROC are computed; the weights of the best epoch (lowest validation loss) are written as a
plain state dict, with a JSON sidecar (configs, data, history, best metrics, sha256 of the weights).
A checkpoint (model + optimiser + history) is written every epoch, so ``resume=True`` continues a
killed run.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.learn.datagen import read_manifest
from msmem_core.learn.training import TrainingRun, optimizer_step, split_scenes, training_record, warmup_cosine
from msmem_core.util.artifacts import sha256_file as sha256_file  # re-exported: callers import it from here
from msmem_core.util.artifacts import sidecar_path as sidecar_path
from msmem_core.util.artifacts import write_sidecar
from msmem_grasp.fevmf import FEVMF, FEVMFConfig, GraspPrediction
from msmem_grasp.fpp import FEATURES
from msmem_grasp.learn.datagen import GraspShard, list_shards, load_shard
from msmem_grasp.learn.losses import GraspTargets, LossConfig, total_loss
from msmem_grasp.metrics import angular_error, auroc
from msmem_grasp.weights import WEIGHTS_FORMAT as WEIGHTS_FORMAT  # re-exported: the format this module writes
from msmem_grasp.weights import WEIGHTS_VERSION


def default_model_config() -> FEVMFConfig:
    """The shipped architecture: ``FEVMFConfig``'s backbone with the FPP features (normal, occupancy)."""
    return FEVMFConfig(in_features=len(FEATURES))


class TrainConfig(BaseModel):
    """Optimisation of FE-vMF."""

    model_config = ConfigDict(extra="forbid")

    epochs: int = Field(20, ge=1)
    val_fraction: float = Field(0.1, ge=0.0, lt=1.0)
    seed: int = 0
    lr: float = Field(1e-3, gt=0.0)
    """Peak AdamW learning rate (the paper's 1e-5 is for a far larger GPU batch; this small CPU model
    trains at 1e-3 with warm-up and cosine decay)."""
    weight_decay: float = Field(0.01, ge=0.0)
    warmup_steps: int = Field(100, ge=0)
    batch_scenes: int = Field(2, ge=1)
    grad_clip: float = Field(1.0, gt=0.0)
    mirror: bool = True
    """Augment by mirroring about x = 0."""
    threads: int = Field(2, ge=1)
    max_minutes: float | None = Field(None, gt=0.0)
    """Stop after the first epoch that ends past this budget."""
    resume: bool = False
    """Continue from ``<out>.ckpt`` if it exists."""
    model: FEVMFConfig = Field(default_factory=default_model_config)
    loss: LossConfig = LossConfig()


# ---------------------------------------------------------------------------------------- batching
def mirror_shard(s: GraspShard) -> GraspShard:
    """The shard mirrored about x = 0 (x of every point and vector negated)."""
    f = np.array([-1.0, 1.0, 1.0], np.float32)
    return GraspShard(s.points * f, s.normals * f, s.occupancy, s.positive_index, s.approach * f, s.baseline * f,
                      s.width, s.mask, s.seed, s.views)


def collate(shards: Sequence[GraspShard]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, GraspTargets]:
    """(points [N, 3], feats [N, F], batch [N], targets) of several clouds as one batch."""
    pts = torch.from_numpy(np.concatenate([s.points for s in shards]))
    feats = torch.from_numpy(np.concatenate([s.features() for s in shards]))
    sizes = [len(s) for s in shards]
    batch = torch.repeat_interleave(torch.arange(len(shards)), torch.tensor(sizes))
    offsets = np.cumsum([0, *sizes[:-1]])
    g = max((s.mask.shape[1] for s in shards), default=1)

    def pad(a: np.ndarray) -> np.ndarray:
        return np.pad(a, [(0, 0), (0, g - a.shape[1])] + [(0, 0)] * (a.ndim - 2))

    targets = GraspTargets(
        num_points=len(pts),
        positive_index=torch.from_numpy(
            np.concatenate([s.positive_index + o for s, o in zip(shards, offsets, strict=True)])
        ),
        approach=torch.from_numpy(np.concatenate([pad(s.approach) for s in shards])),
        baseline=torch.from_numpy(np.concatenate([pad(s.baseline) for s in shards])),
        width=torch.from_numpy(np.concatenate([pad(s.width) for s in shards])),
        mask=torch.from_numpy(np.concatenate([pad(s.mask) for s in shards])),
    )
    return pts, feats, batch, targets


def predict_shard(model: FEVMF, shard: GraspShard) -> GraspPrediction:
    with torch.no_grad():
        return model(torch.from_numpy(shard.points), torch.from_numpy(shard.features())).detach()


# -------------------------------------------------------------------------------------- validation
def validate(model: FEVMF, shards: Sequence[GraspShard], epoch: float, loss_cfg: LossConfig) -> dict[str, float]:
    """Mean loss terms over the scenes, affordance AUROC over all points, and median angular errors
    (deg) of the projected approach and of the baseline on positives."""
    model.eval()
    sums: dict[str, float] = {}
    scores, labels, err_a, err_b = [], [], [], []
    for s in shards:
        out = predict_shard(model, s)
        terms = total_loss(out, s.targets(), epoch, loss_cfg)
        for k, v in terms.items():
            sums[k] = sums.get(k, 0.0) + float(v) / len(shards)
        scores.append(out.affordance.numpy())
        labels.append(s.label)
        if len(s.positive_index):
            idx = torch.from_numpy(s.positive_index)
            mu_a, _ = out.approach()
            err_a.append(angular_error(mu_a[idx].double().numpy(), s.approach, s.mask))
            err_b.append(angular_error(out.mu_b[idx].double().numpy(), s.baseline, s.mask))
    sums["auroc"] = auroc(np.concatenate(scores), np.concatenate(labels)) if shards else float("nan")
    sums["err_a_deg"] = float(np.degrees(np.median(np.concatenate(err_a)))) if err_a else float("nan")
    sums["err_b_deg"] = float(np.degrees(np.median(np.concatenate(err_b)))) if err_b else float("nan")
    return sums


# ------------------------------------------------------------------------------------------- files
def load_shards(paths: Sequence[Path], log: Callable[[str], None] = print) -> list[GraspShard]:
    """All shards, validated (a bad one raises a ``ShardError`` naming its file)."""
    shards = [load_shard(p) for p in paths]
    log(f"loaded {len(shards)} scenes, {sum(len(s) for s in shards)} points, "
        f"{sum(len(s.positive_index) for s in shards)} positives")
    return shards


# ------------------------------------------------------------------------------------------- train
def train(
    data_dir: str | Path,
    out: str | Path,
    config: TrainConfig | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Train, keep the best weights at ``out`` (+ sidecar) and return the sidecar's content."""
    cfg = config or TrainConfig()
    torch.set_num_threads(cfg.threads)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    paths = list_shards(data_dir)
    val_idx, train_idx = split_scenes(len(paths), cfg.val_fraction, cfg.seed)
    train_set = load_shards([paths[i] for i in train_idx], log)
    val_set = [load_shard(paths[i]) for i in val_idx]
    if not val_set:
        log("warning: no validation scenes (--val-fraction 0 or a single scene): the last epoch is kept")

    torch.manual_seed(cfg.seed)
    model = FEVMF(cfg.model)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps_per_epoch = math.ceil(len(train_set) / cfg.batch_scenes)
    lr_at = warmup_cosine(cfg.lr, cfg.warmup_steps, cfg.epochs * steps_per_epoch)
    run = TrainingRun(out, model, opt, cfg.resume, log)
    data_info = {
        "dir": str(data_dir),
        "train_scenes": [int(s.seed) for s in train_set],
        "val_scenes": [int(s.seed) for s in val_set],
        "manifest": read_manifest(data_dir),
    }

    def write_sidecar(history: list[dict[str, Any]], best: dict[str, Any], seconds: float) -> None:
        _write_sidecar(out, cfg, data_info, history, best, seconds)

    run.start(progress, total=(cfg.epochs - run.start_epoch) * steps_per_epoch)
    step = run.start_epoch * steps_per_epoch
    try:
        for epoch in range(run.start_epoch, cfg.epochs):
            model.train()
            perm = np.random.default_rng([cfg.seed, epoch]).permutation(len(train_set))
            flips = np.random.default_rng([cfg.seed, epoch, 1]).random(len(train_set)) < 0.5
            running: dict[str, float] = {}
            for b in range(steps_per_epoch):
                idx = perm[b * cfg.batch_scenes:(b + 1) * cfg.batch_scenes]
                shards = [mirror_shard(train_set[i]) if cfg.mirror and flips[i] else train_set[i] for i in idx]
                pts, feats, batch, targets = collate(shards)
                terms = total_loss(model(pts, feats, batch), targets, epoch + b / steps_per_epoch, cfg.loss)
                optimizer_step(model, opt, terms["total"], lr_at(step), cfg.grad_clip)
                step += 1
                for k, v in terms.items():
                    running[k] = running.get(k, 0.0) + float(v.detach()) / steps_per_epoch
                run.advance(1, epoch, f"{float(terms['total'].detach()):.3f}")
            val = validate(model, val_set, epoch + 1, cfg.loss) if val_set else {}
            seconds = run.seconds()
            rec = {"epoch": epoch, "train": running, "val": val, "seconds": seconds, "lr": lr_at(step - 1)}
            msg = (f"epoch {epoch}: train {running['total']:.4f}"
                   + (f"  val {val['total']:.4f}  AUROC {val['auroc']:.3f}  err a {val['err_a_deg']:.1f} deg"
                      f"  err b {val['err_b_deg']:.1f} deg" if val else "") + f"  ({seconds / 60:.1f} min)")
            if run.end_epoch(epoch, rec, val.get("total", running["total"]), msg, write_sidecar, cfg.max_minutes):
                break
    finally:
        run.stop()
    return run.result()


def _write_sidecar(out: Path, cfg: TrainConfig, data: dict[str, Any], history: list[dict[str, Any]],
                   best: dict[str, Any], seconds: float) -> None:
    head = {"format": WEIGHTS_FORMAT, "version": WEIGHTS_VERSION}
    model = {"model": cfg.model.model_dump(), "features": list(FEATURES)}
    write_sidecar(out, head, training_record(model, cfg.model_dump(exclude={"model"}), data, history, best, seconds))
