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

import json
import math
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.artifacts import atomic_save, atomic_text, sha256_file, sidecar_path
from msmem_core.errors import UserError
from msmem_grasp.datagen import MANIFEST, GraspShard, list_shards, load_shard
from msmem_grasp.fevmf import FEVMF, FEVMFConfig, GraspPrediction
from msmem_grasp.fpp import FEATURES
from msmem_grasp.losses import GraspTargets, LossConfig, total_loss
from msmem_grasp.metrics import angular_error, auroc

WEIGHTS_FORMAT = "msmem-fe-vmf"
WEIGHTS_VERSION = 1


def default_model_config() -> FEVMFConfig:
    """The shipped architecture: the DESIGN.md backbone with the FPP features (normal, occupancy)."""
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
    rng = np.random.default_rng(cfg.seed)
    order = rng.permutation(len(paths))
    n_val = min(len(paths) - 1, math.ceil(cfg.val_fraction * len(paths))) if cfg.val_fraction > 0 else 0
    val_paths = sorted(paths[i] for i in order[:n_val])
    train_paths = sorted(paths[i] for i in order[n_val:])
    train_set = load_shards(train_paths, log)
    val_set = [load_shard(p) for p in val_paths]
    if not val_set:
        log("warning: no validation scenes (--val-fraction 0 or a single scene): the last epoch is kept")

    torch.manual_seed(cfg.seed)
    model = FEVMF(cfg.model)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    steps_per_epoch = math.ceil(len(train_set) / cfg.batch_scenes)
    total_steps = cfg.epochs * steps_per_epoch

    def lr_at(step: int) -> float:
        if step < cfg.warmup_steps:
            return cfg.lr * (step + 1) / cfg.warmup_steps
        t = (step - cfg.warmup_steps) / max(1, total_steps - cfg.warmup_steps)
        return cfg.lr * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * min(1.0, t))))

    ckpt_path = out.with_suffix(".ckpt")
    history: list[dict[str, Any]] = []
    best: dict[str, Any] | None = None
    start_epoch, elapsed_before = 0, 0.0
    if cfg.resume and ckpt_path.exists():
        ck = torch.load(ckpt_path, weights_only=True)
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        history = json.loads(ck["history"])
        best = json.loads(ck["best"]) if ck["best"] else None
        start_epoch = int(ck["epoch"]) + 1
        elapsed_before = float(ck["seconds"])
        log(f"resumed from {ckpt_path} after epoch {start_epoch - 1}")
    manifest = Path(data_dir) / MANIFEST
    data_info = {
        "dir": str(data_dir),
        "train_scenes": [int(s.seed) for s in train_set],
        "val_scenes": [int(s.seed) for s in val_set],
        "manifest": json.loads(manifest.read_text()) if manifest.exists() else None,
    }

    bar = None
    if progress:
        from rich.progress import (
            BarColumn,
            MofNCompleteColumn,
            Progress,
            TextColumn,
            TimeElapsedColumn,
            TimeRemainingColumn,
        )

        bar = Progress(TextColumn("epoch {task.fields[epoch]}"), MofNCompleteColumn(), BarColumn(),
                       TextColumn("loss {task.fields[loss]}"), TimeElapsedColumn(), TimeRemainingColumn())
        bar.start()
        bar_id = bar.add_task("train", total=(cfg.epochs - start_epoch) * steps_per_epoch, epoch=start_epoch, loss="-")
    t_start = time.perf_counter()
    step = start_epoch * steps_per_epoch
    try:
        for epoch in range(start_epoch, cfg.epochs):
            model.train()
            perm = np.random.default_rng([cfg.seed, epoch]).permutation(len(train_set))
            flips = np.random.default_rng([cfg.seed, epoch, 1]).random(len(train_set)) < 0.5
            running: dict[str, float] = {}
            for b in range(steps_per_epoch):
                idx = perm[b * cfg.batch_scenes:(b + 1) * cfg.batch_scenes]
                shards = [mirror_shard(train_set[i]) if cfg.mirror and flips[i] else train_set[i] for i in idx]
                pts, feats, batch, targets = collate(shards)
                for group in opt.param_groups:
                    group["lr"] = lr_at(step)
                terms = total_loss(model(pts, feats, batch), targets, epoch + b / steps_per_epoch, cfg.loss)
                opt.zero_grad(set_to_none=True)
                terms["total"].backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.grad_clip)
                opt.step()
                step += 1
                for k, v in terms.items():
                    running[k] = running.get(k, 0.0) + float(v.detach()) / steps_per_epoch
                if bar is not None:
                    bar.update(bar_id, advance=1, epoch=epoch, loss=f"{float(terms['total'].detach()):.3f}")
            val = validate(model, val_set, epoch + 1, cfg.loss) if val_set else {}
            seconds = elapsed_before + time.perf_counter() - t_start
            rec = {"epoch": epoch, "train": running, "val": val, "seconds": seconds, "lr": lr_at(step - 1)}
            history.append(rec)
            score = val.get("total", running["total"])
            msg = (f"epoch {epoch}: train {running['total']:.4f}"
                   + (f"  val {val['total']:.4f}  AUROC {val['auroc']:.3f}  err a {val['err_a_deg']:.1f} deg"
                      f"  err b {val['err_b_deg']:.1f} deg" if val else "") + f"  ({seconds / 60:.1f} min)")
            if best is None or score < best["score"]:
                best = {"epoch": epoch, "score": score, "val": val, "train": running}
                atomic_save(model.state_dict(), out)
                msg += "  * best"
            if bar is not None:
                bar.console.print(msg)
            else:
                log(msg)
            atomic_save({"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": epoch,
                          "history": json.dumps(history), "best": json.dumps(best), "seconds": seconds}, ckpt_path)
            _write_sidecar(out, cfg, data_info, history, best, seconds)
            if cfg.max_minutes is not None and seconds > 60.0 * cfg.max_minutes:
                log(f"time budget of {cfg.max_minutes} min reached after epoch {epoch}")
                break
    finally:
        if bar is not None:
            bar.stop()
    if best is None:
        raise UserError("no epoch finished; nothing was saved")
    return json.loads(sidecar_path(out).read_text())


def _write_sidecar(out: Path, cfg: TrainConfig, data: dict[str, Any], history: list[dict[str, Any]],
                   best: dict[str, Any], seconds: float) -> None:
    side = {
        "format": WEIGHTS_FORMAT,
        "version": WEIGHTS_VERSION,
        "weights": out.name,
        "sha256": sha256_file(out),
        "bytes": out.stat().st_size,
        "model": cfg.model.model_dump(),
        "features": list(FEATURES),
        "train": cfg.model_dump(exclude={"model"}),
        "data": data,
        "epochs_run": len(history),
        "train_seconds": seconds,
        "best": best,
        "history": history,
        "torch": torch.__version__,
    }
    atomic_text(json.dumps(side, indent=1, default=float), sidecar_path(out))
