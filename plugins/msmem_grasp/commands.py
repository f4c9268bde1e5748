"""Bodies of the ``msmem datagen grasp``, ``msmem train fe-vmf`` and ``msmem eval fe-vmf`` commands.

The typer signatures live in ``msmem_core.cli.app``; everything heavy is imported here, on use.
"""

from __future__ import annotations

import json
from pathlib import Path

import typer


def datagen_grasp(*, scenes: int, out: Path, workers: int, seed: int, executor: str, points: int, quiet: bool) -> None:
    from msmem_core.learn.datagen import seed_range
    from msmem_grasp.datagen import GraspDataConfig, generate_dataset
    from msmem_grasp.fpp import FPPConfig

    seeds = seed_range(scenes, seed)
    cfg = GraspDataConfig(fpp=FPPConfig(num_points=points))
    typer.echo(f"msmem datagen grasp: {scenes} scenes (seeds {seeds[0]}..{seeds[-1]}) -> {out}, "
               f"{workers} worker(s), executor {executor}")
    summary = generate_dataset(out, seeds, cfg, executor=executor, workers=workers, progress=not quiet,
                               log=lambda m: typer.echo(m, err=True))
    gen = summary.generated
    line = summary.headline()
    if gen:
        pos = sum(g["positives"] for g in gen) / max(sum(g["points"] for g in gen), 1)
        per = sum(g["seconds"] for g in gen) / len(gen)
        line += (f" in {summary.seconds:.0f} s: {summary.scenes_per_min:.1f} scenes/min "
                 f"({per:.1f} s per scene per worker), {100 * pos:.1f} % positive points")
    typer.echo(line)
    summary.raise_if_failed()


def train_fe_vmf(
    *, data: Path, out: Path, epochs: int, val_fraction: float, seed: int, lr: float, threads: int,
    max_minutes: float | None, quiet: bool,
) -> None:
    from msmem_grasp.training import TrainConfig, train

    cfg = TrainConfig(epochs=epochs, val_fraction=val_fraction, seed=seed, lr=lr, threads=threads,
                      max_minutes=max_minutes)
    result = train(data, out, cfg, progress=not quiet, log=typer.echo)
    best = result["best"]
    typer.echo(f"best epoch {best['epoch']}: val loss {best['val']['total']:.4f}, "
               f"affordance AUROC {best['val']['auroc']:.3f}; {result['train_seconds'] / 60:.1f} min -> {out}")


def eval_fe_vmf(*, data: Path, weights: Path | None, plot: Path | None, json_out: Path | None, threads: int) -> None:
    from msmem_grasp.evaluation import evaluate, format_table

    metrics = evaluate(data, weights, plot=plot, threads=threads)
    typer.echo(format_table(metrics))
    if plot is not None:
        typer.echo(f"calibration plot: {plot}")
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(metrics, indent=2))
        typer.echo(f"metrics: {json_out}")
