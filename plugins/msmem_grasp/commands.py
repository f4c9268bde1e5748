"""The grasp plugin's commands: ``msmem datagen grasp``, ``msmem train fe-vmf``, ``msmem eval fe-vmf`` and
``msmem bench-grasp`` (registered by ``plugin.msmem_commands``).

Importing this module is cheap (typer only); the bodies import ``msmem_grasp.learn`` on use.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from msmem_core.plugins import CommandSpec

SimOpt = Annotated[str, typer.Option("--sim", help="Simulator plugin name (e.g. pybullet, sapien).")]


def datagen_grasp(
    scenes: Annotated[int, typer.Option("--scenes", help="Number of scenes (seeds SEED .. SEED+N-1).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder: one scene_<seed>.npz per scene.")],
    workers: Annotated[int, typer.Option("--workers", help="Parallel processes (or Ray tasks in flight).")] = 1,
    seed: Annotated[int, typer.Option("--seed", help="First scene seed.")] = 0,
    executor: Annotated[str, typer.Option("--executor", help="local (processes) or ray.")] = "local",
    points: Annotated[int, typer.Option("--points", help="FPP points per scene.")] = 4096,
    sim: SimOpt = "pybullet",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """FE-vMF training data: scene -> belief from 3-10 random views -> FPP points -> antipodal labels (resumable)."""
    from msmem_core.learn.datagen import seed_range
    from msmem_core.plugins import ComponentRef
    from msmem_grasp.fpp import FPPConfig
    from msmem_grasp.learn.datagen import GraspDataConfig, generate_dataset

    seeds = seed_range(scenes, seed)
    cfg = GraspDataConfig(fpp=FPPConfig(num_points=points), simulator=ComponentRef(name=sim))
    typer.echo(f"msmem datagen grasp: {scenes} scenes (seeds {seeds[0]}..{seeds[-1]}) -> {out}, "
               f"{workers} worker(s), executor {executor}, simulator {sim}")
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
    data: Annotated[Path, typer.Option("--data", help="Folder of shards from `msmem datagen grasp`.")],
    out: Annotated[Path, typer.Option("--out", help="Weights file (.pt); a .json sidecar is written beside it.")],
    epochs: Annotated[int, typer.Option("--epochs", help="Training epochs.")] = 20,
    val_fraction: Annotated[float, typer.Option("--val-fraction", help="Fraction of scenes for validation.")] = 0.1,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the split, initialisation and batches.")] = 0,
    lr: Annotated[float, typer.Option("--lr", help="AdamW learning rate.")] = 1e-3,
    threads: Annotated[int, typer.Option("--threads", help="torch threads.")] = 2,
    max_minutes: Annotated[float | None, typer.Option("--max-minutes", help="Stop after the epoch past this.")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """Train FE-vMF (AdamW, validation per epoch); keeps the best weights + a JSON sidecar (metrics, sha256)."""
    from msmem_grasp.learn.training import TrainConfig, train

    cfg = TrainConfig(epochs=epochs, val_fraction=val_fraction, seed=seed, lr=lr, threads=threads,
                      max_minutes=max_minutes)
    result = train(data, out, cfg, progress=not quiet, log=typer.echo)
    best = result["best"]
    typer.echo(f"best epoch {best['epoch']}: val loss {best['val']['total']:.4f}, "
               f"affordance AUROC {best['val']['auroc']:.3f}; {result['train_seconds'] / 60:.1f} min -> {out}")


def eval_fe_vmf(
    data: Annotated[Path, typer.Option("--data", help="Folder of held-out shards.")],
    weights: Annotated[Path | None, typer.Option("--weights", help="Weights file (default: the shipped ones).")] = None,
    plot: Annotated[Path | None, typer.Option("--plot", help="Write the kappa calibration plot (PNG) here.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the metrics as JSON here.")] = None,
    threads: Annotated[int, typer.Option("--threads", help="torch threads.")] = 2,
) -> None:
    """Held-out metrics of FE-vMF and of the geometric antipodal heuristic: AUROC, ECE, NLL, angular errors, P/R."""
    from msmem_grasp.learn.evaluation import evaluate, format_table

    metrics = evaluate(data, weights, plot=plot, threads=threads)
    typer.echo(format_table(metrics))
    if plot is not None:
        typer.echo(f"calibration plot: {plot}")
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(metrics, indent=2))
        typer.echo(f"metrics: {json_out}")


def bench_grasp(
    scenes: Annotated[str, typer.Option("--scenes", help="Generated scene seeds, e.g. 0-9.")] = "0-9",
    trials: Annotated[int, typer.Option("--trials", help="Trials per scene (different views).")] = 2,
    views: Annotated[int, typer.Option("--views", help="Observations (one FE-UMGF step each) first.")] = 8,
    random_views: Annotated[bool, typer.Option("--random-views/--nbv", help="Random views, not next-best.")] = False,
    predictor: Annotated[str, typer.Option("--predictor", help="auto, fe-vmf or geometric.")] = "auto",
    hard: Annotated[bool, typer.Option("--hard/--any", help="Hard scenes (as episodes) or random ones.")] = False,
    workers: Annotated[int, typer.Option("--workers", help="Scenes in parallel.")] = 1,
    sim: SimOpt = "pybullet",
    out: Annotated[Path, typer.Option("--out", help="Results folder.")] = Path("runs/bench-grasp"),
) -> None:
    """Top-1 fused grasp executed in the simulator per scene and trial: success rate (grasps from the belief only)."""
    from msmem_core.plugins import ComponentRef
    from msmem_core.run.bench import parse_range
    from msmem_grasp.learn.bench import GraspBenchConfig
    from msmem_grasp.learn.bench import bench_grasp as run_bench_grasp

    cfg = GraspBenchConfig(scene_seeds=parse_range(scenes, 10**6), trials=trials, views=views,
                           view_policy="random" if random_views else "nbv", require_hard=hard,
                           skill={"predictor": predictor}, simulator=ComponentRef(name=sim))
    s = run_bench_grasp(cfg, out, workers=workers)["summary"]
    typer.echo(f"predictor {s['predictor']}: {s['successes']}/{s['executed']} grasps succeeded "
               f"({100 * s['success_rate']:.0f} %), {s['no_candidate']} of {s['trials']} trials had no executable "
               f"grasp; held object of the believed class {s['held_believed_class']}/{s['successes']}; "
               f"mean displacement of the other objects {s['mean_displaced_m']:.3f} m; "
               f"{s['fell_or_left']} trial(s) with an object fallen or out -> {out}")


COMMANDS = (
    CommandSpec(name="grasp", action=datagen_grasp, group="datagen",
                summary="FE-vMF training data: beliefs, FPP points, antipodal labels."),
    CommandSpec(name="fe-vmf", action=train_fe_vmf, group="train",
                summary="Train FE-vMF; keeps the best weights and a JSON sidecar."),
    CommandSpec(name="fe-vmf", action=eval_fe_vmf, group="eval",
                summary="Held-out metrics of FE-vMF and of the geometric heuristic."),
    CommandSpec(name="bench-grasp", action=bench_grasp,
                summary="Success rate of the top-1 fused grasp, executed in the simulator."),
)
