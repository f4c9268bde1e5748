"""The training-loop machinery of the plugins that ship learned weights (FE-vMF, CNABU).

Each trainer keeps its own model, batches, loss and validation; the rest is done here one way for
all: the seeded split of the scenes into training and validation, the learning-rate schedule (linear
warm-up, cosine decay), and per epoch (:class:`TrainingRun`) the progress bar, the best epoch's
weights at ``out``, a checkpoint ``<out>.ckpt`` that ``resume`` continues a killed run from, the
trainer's JSON sidecar, and the time budget. Plugins import this module; it imports no plugin.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from msmem_core.errors import UserError
from msmem_core.util.artifacts import atomic_save, load_state, non_finite_tensor, sidecar_path
from msmem_core.util.progress import progress_bar


def split_scenes(n: int, val_fraction: float, seed: int) -> tuple[list[int], list[int]]:
    """(validation, training) indices of ``n`` scenes, each sorted: the first ``ceil(val_fraction * n)``
    (at most ``n - 1``) of a seeded permutation validate, the rest train."""
    order = np.random.default_rng(seed).permutation(n)
    n_val = min(n - 1, math.ceil(val_fraction * n)) if val_fraction > 0 else 0
    return sorted(order[:n_val]), sorted(order[n_val:])


def warmup_cosine(peak_lr: float, warmup_steps: int, total_steps: int) -> Callable[[int], float]:
    """The learning rate at an optimiser step: a linear warm-up to ``peak_lr`` over ``warmup_steps``,
    then a cosine decay to 5 % of it at ``total_steps``."""

    def lr_at(step: int) -> float:
        if step < warmup_steps:
            return peak_lr * (step + 1) / warmup_steps
        t = (step - warmup_steps) / max(1, total_steps - warmup_steps)
        return peak_lr * (0.05 + 0.95 * 0.5 * (1.0 + math.cos(math.pi * min(1.0, t))))

    return lr_at


def optimizer_step(model: Any, opt: Any, loss: Any, lr: float, grad_clip: float) -> None:
    """One optimiser step on ``loss`` at learning rate ``lr``, the gradient norm clipped to ``grad_clip``."""
    import torch

    for group in opt.param_groups:
        group["lr"] = lr
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(model.parameters(), grad_clip)
    opt.step()


def training_record(
    model: dict[str, Any], train: dict[str, Any], data: dict[str, Any], history: list[dict[str, Any]],
    best: dict[str, Any], seconds: float,
) -> dict[str, Any]:
    """The sidecar entries of trained weights after the file's own (``artifacts.write_sidecar``):
    ``model`` (the architecture entries), then the training config, data, epochs run, time, best
    epoch, history and the torch version."""
    import torch

    return {**model, "train": train, "data": data, "epochs_run": len(history), "train_seconds": seconds,
            "best": best, "history": history, "torch": torch.__version__}


class TrainingRun:
    """The per-epoch bookkeeping of one training run that writes its weights to ``out``.

    Created with ``resume`` and an existing ``<out>.ckpt``, it restores the model and optimiser state
    from it, with the history, the best epoch so far, the time spent and (if the checkpoint holds
    one) the optimiser step count; ``start_epoch`` is then the next epoch to run. Use: ``start`` before
    the first epoch, ``advance`` after every batch, ``end_epoch`` after every epoch, ``stop`` in a
    ``finally``, then ``result``.
    """

    def __init__(self, out: Path, model: Any, opt: Any, resume: bool, log: Callable[[str], None]) -> None:
        self.out = out
        self.ckpt_path = out.with_suffix(".ckpt")
        self.history: list[dict[str, Any]] = []
        self.best: dict[str, Any] | None = None
        """``{"epoch", "score", "val", "train"}`` of the epoch with the lowest score so far."""
        self.start_epoch = 0
        self.step: int | None = None
        """The checkpoint's optimiser step count, when resumed from one that records it."""
        self._model, self._opt, self._log = model, opt, log
        self._seconds_before = 0.0
        self._t_start = time.perf_counter()
        self._bar: Any = None
        if resume and self.ckpt_path.exists():
            ck = load_state(self.ckpt_path, UserError, "a training checkpoint")
            bad = non_finite_tensor(ck.get("model") if isinstance(ck, dict) else None)
            if bad:
                raise UserError(f"{self.ckpt_path}: the checkpoint's weights are not finite (NaN or infinite) in "
                                f"tensor {bad}; delete it to train from the start")
            model.load_state_dict(ck["model"])
            opt.load_state_dict(ck["optimizer"])
            self.history = json.loads(ck["history"])
            self.best = json.loads(ck["best"]) if ck["best"] else None
            self.start_epoch = int(ck["epoch"]) + 1
            self._seconds_before = float(ck["seconds"])
            self.step = int(ck["step"]) if "step" in ck else None
            log(f"resumed from {self.ckpt_path} after epoch {self.start_epoch - 1}")

    def start(self, progress: bool, total: int) -> None:
        """Start the clock and, with ``progress``, a bar of ``total`` units (what ``advance`` counts)."""
        if progress:
            self._bar = progress_bar("epoch {task.fields[epoch]}", "loss {task.fields[loss]}")
            self._bar_id = self._bar.add_task("train", total=total, epoch=self.start_epoch, loss="-")
        self._t_start = time.perf_counter()

    def advance(self, units: int, epoch: int, loss: str) -> None:
        """Move the bar on by ``units`` and show the epoch and the batch loss."""
        if self._bar is not None:
            self._bar.update(self._bar_id, advance=units, epoch=epoch, loss=loss)

    def seconds(self) -> float:
        """Training time so far, including the runs this one resumed."""
        return self._seconds_before + time.perf_counter() - self._t_start

    def end_epoch(
        self,
        epoch: int,
        record: dict[str, Any],
        score: float,
        message: str,
        write_sidecar: Callable[[list[dict[str, Any]], dict[str, Any], float], None],
        max_minutes: float | None,
        step: int | None = None,
    ) -> bool:
        """Record a finished epoch and say whether to stop (its end is past ``max_minutes``).

        ``record`` (with ``"train"``, ``"val"`` and ``"seconds"``) joins the history; if ``score`` is
        the lowest so far the weights are saved at ``out`` and ``message`` gets ``"  * best"``.
        ``message`` is shown, the checkpoint written (with ``step`` if given), then
        ``write_sidecar(history, best, seconds)`` is called.
        """
        self.history.append(record)
        if self.best is None or score < self.best["score"]:
            self.best = {"epoch": epoch, "score": score, "val": record["val"], "train": record["train"]}
            atomic_save(self._model.state_dict(), self.out)
            message += "  * best"
        if self._bar is not None:
            self._bar.console.print(message)
        else:
            self._log(message)
        seconds = record["seconds"]
        state: dict[str, Any] = {"model": self._model.state_dict(), "optimizer": self._opt.state_dict(), "epoch": epoch}
        if step is not None:
            state["step"] = step
        state |= {"history": json.dumps(self.history), "best": json.dumps(self.best), "seconds": seconds}
        atomic_save(state, self.ckpt_path)
        write_sidecar(self.history, self.best, seconds)
        if max_minutes is not None and seconds > 60.0 * max_minutes:
            self._log(f"time budget of {max_minutes} min reached after epoch {epoch}")
            return True
        return False

    def stop(self) -> None:
        """Stop the progress bar, if any."""
        if self._bar is not None:
            self._bar.stop()

    def result(self) -> dict[str, Any]:
        """The sidecar's content; raises ``UserError`` if no epoch finished."""
        if self.best is None:
            raise UserError("no epoch finished; nothing was saved")
        return dict(json.loads(sidecar_path(self.out).read_text()))
