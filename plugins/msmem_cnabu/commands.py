"""The ``msmem datagen cnabu``, ``msmem train cnabu``, ``msmem train cnabu-map``, ``msmem eval belief-models``
and ``msmem eval map`` commands (registered by ``plugin.msmem_commands``).

Importing this module is cheap (typer only); the bodies import ``msmem_cnabu.learn`` (and everything
heavy) on use.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer

from msmem_core.errors import UserError
from msmem_core.plugins import CommandSpec

KIND_HELP = "observe, push or grasp."
SimOpt = Annotated[str, typer.Option("--sim", help="Simulator plugin name (e.g. pybullet, sapien).")]


def _kind(kind: str) -> str:
    kinds = ("observe", "push", "grasp")
    if kind not in kinds:
        raise UserError(f"--kind must be one of {', '.join(kinds)}, got {kind!r}")
    return kind


def datagen_cnabu(
    kind: Annotated[str, typer.Option("--kind", help=KIND_HELP)],
    scenes: Annotated[int, typer.Option("--scenes", help="Number of scenes (seeds SEED .. SEED+N-1).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder: one scene_<seed>.npz per scene.")],
    workers: Annotated[int, typer.Option("--workers", help="Parallel processes (or Ray tasks in flight).")] = 1,
    seed: Annotated[int, typer.Option("--seed", help="First scene seed (every random choice flows from it).")] = 0,
    executor: Annotated[str, typer.Option("--executor", help="local (processes) or ray.")] = "local",
    voxel: Annotated[float, typer.Option("--voxel", help="Voxel edge in metres (the networks are per grid).")] = 0.01,
    states: Annotated[int, typer.Option("--states", help="push/grasp: belief states per scene.")] = 2,
    actions: Annotated[int, typer.Option("--actions", help="push/grasp: candidates executed per state.")] = 4,
    samples: Annotated[int, typer.Option("--samples", help="observe: views recorded per scene.")] = 6,
    min_views: Annotated[int, typer.Option("--min-views", help="Random views before the first sample (min).")] = 1,
    max_views: Annotated[int, typer.Option("--max-views", help="Random views before the first sample (max).")] = 6,
    manipulate_after: Annotated[int | None, typer.Option(
        "--manipulate-after", help="observe: after this many recorded views, execute one push (or grasp) for "
                                   "real (post-manipulation sequences).")] = None,
    manipulate_skill: Annotated[str, typer.Option(
        "--manipulate-skill", help="observe: the skill --manipulate-after executes: push or grasp (a grasp "
                                   "removes the object it holds).")] = "push",
    manipulate_tries: Annotated[int, typer.Option(
        "--manipulate-tries", help="observe: if the skill proposes nothing, ask it again after each next view, "
                                   "up to this many times in all.")] = 1,
    require_hard: Annotated[bool, typer.Option(
        "--require-hard", help="Hard scenes (as the hard25 suite: more hidden objects) instead of random "
                               "30-45 % shelves; slower to generate.")] = False,
    observation: Annotated[str, typer.Option(
        "--observation", help="push/grasp: the observation model the views are integrated with "
                              "(cnabu-map: the completed belief episodes see).")] = "analytic-observation",
    generator: Annotated[Path | None, typer.Option(
        "--generator", help="Scene generator settings (YAML, as `msmem scene generate --generator`), e.g. "
                            "scenes of your own mesh classes; default: the built-in classes.")] = None,
    sim: SimOpt = "pybullet",
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    wait: Annotated[bool, typer.Option(
        "--wait", help="If another msmem process is writing --out, wait for it to finish (default: stop with "
                       "an error).")] = False,
) -> None:
    """CNABU training data: belief before, action, simulator ground truth after (sharded, resumable).
    One writer per --out: another datagen into it is refused, or waits with --wait."""
    from pydantic import ValidationError

    from msmem_cnabu.learn.datagen import CNABUDataConfig, generate_dataset
    from msmem_core.config import load_generator_config
    from msmem_core.learn.datagen import data_folder_lock, seed_range
    from msmem_core.plugins import ComponentRef
    from msmem_core.run.executors import check_workers

    kind = _kind(kind)
    seeds = seed_range(scenes, seed)
    check_workers(workers)
    try:
        cfg = CNABUDataConfig(kind=kind, voxel_m=voxel, states=states, actions_per_state=actions,
                              observe_samples=samples, min_views=min_views, max_views=max_views,
                              manipulate_after=manipulate_after, manipulate_skill=manipulate_skill,
                              manipulate_tries=manipulate_tries, require_hard=require_hard,
                              generator=load_generator_config(generator) if generator else None,
                              observation_model=ComponentRef(name=observation), simulator=ComponentRef(name=sim))
    except ValidationError as e:
        err = e.errors()[0]
        raise UserError(f"invalid option ({'.'.join(str(x) for x in err['loc']) or 'views'}): {err['msg']}") from e
    typer.echo(f"msmem datagen cnabu: {kind}, {scenes} scenes (seeds {seeds[0]}..{seeds[-1]}) -> {out}, "
               f"{workers} worker(s), executor {executor}, simulator {sim}"
               + (f", observation model {observation}" if observation != "analytic-observation" else ""))
    with data_folder_lock(out, wait):  # from before the folder's manifest is checked until the last shard
        summary = generate_dataset(out, seeds, cfg, executor=executor, workers=workers, progress=not quiet,
                                   log=lambda m: typer.echo(m, err=True))
    gen = summary.generated
    line = summary.headline()
    if gen:
        per = sum(g["seconds"] for g in gen) / len(gen)
        n = sum(g["samples"] for g in gen)
        size = sum(g["bytes"] for g in gen) / len(gen)
        line += (f" in {summary.seconds:.0f} s: {n} samples, {per:.1f} s per scene per worker "
                 f"({sum(g['sim_execute_s'] for g in gen) / len(gen):.1f} s of it executing actions), "
                 f"{size / 1e6:.2f} MB per shard")
    typer.echo(line)
    summary.raise_if_failed()


def train_cnabu(
    kind: Annotated[str, typer.Option("--kind", help=KIND_HELP)],
    data: Annotated[Path, typer.Option("--data", help="Folder of shards from `msmem datagen cnabu`.")],
    out: Annotated[Path, typer.Option("--out", help="Weights file (.pt); a .json sidecar is written beside it.")],
    epochs: Annotated[int, typer.Option("--epochs", help="Training epochs.")] = 10,
    val_fraction: Annotated[float, typer.Option("--val-fraction", help="Fraction of scenes for validation.")] = 0.1,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the split, initialisation and batches.")] = 0,
    lr: Annotated[float, typer.Option("--lr", help="AdamW learning rate.")] = 2e-3,
    batch_size: Annotated[int, typer.Option("--batch-size", help="Samples per step.")] = 4,
    width: Annotated[int, typer.Option("--width", help="U-Net width (channels of the first level).")] = 24,
    threads: Annotated[int, typer.Option("--threads", help="torch threads.")] = 2,
    max_minutes: Annotated[float | None, typer.Option("--max-minutes", help="Stop after the epoch past this.")] = None,
    resume: Annotated[bool, typer.Option("--resume", help="Continue from OUT.ckpt.")] = False,
    init: Annotated[Path | None, typer.Option(
        "--init", help="Fine-tune these weights (their architecture; --width is ignored).")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """Train a CNABU network (AdamW, validation per epoch); keeps the best weights + a JSON sidecar (sha256)."""
    from msmem_cnabu.learn.training import TrainConfig, train

    kind = _kind(kind)
    cfg = TrainConfig(epochs=epochs, val_fraction=val_fraction, seed=seed, lr=lr, batch_size=batch_size,
                      width=width, threads=threads, max_minutes=max_minutes, resume=resume,
                      init=str(init) if init is not None else None)
    result = train(kind, data, out, cfg, progress=not quiet, log=typer.echo)
    best = result["best"]
    val = best["val"]
    extra = f", occ NLL {val['occ_nll']:.4f}" if val else ""
    typer.echo(f"best epoch {best['epoch']}: loss {best['score']:.4f}{extra}; {result['train_seconds'] / 60:.1f} min, "
               f"{result['bytes'] / 1e6:.2f} MB -> {out} (sha256 {result['sha256'][:12]}...)")


def eval_belief_models(
    kind: Annotated[str, typer.Option("--kind", help=KIND_HELP)],
    data: Annotated[Path, typer.Option("--data", help="Folder of held-out shards from `msmem datagen cnabu`.")],
    weights: Annotated[Path | None, typer.Option("--weights", help="Weights file (default: the shipped ones).")] = None,
    change_threshold: Annotated[float, typer.Option(
        "--change-threshold", help="p_change threshold (the belief models' default).")] = 0.85,
    change_epsilon: Annotated[float, typer.Option(
        "--change-epsilon", help="Drop changed voxels whose expected probabilities move by at most this (the "
                                 "belief models' change_epsilon; 0: keep every voxel whose evidence differs).")] = 0.0,
    timing: Annotated[bool, typer.Option("--timing/--no-timing", help="Also time predictions vs "
                                                                      "simulate-and-remap.")] = True,
    candidates: Annotated[int, typer.Option("--candidates", help="Candidates per timed prediction.")] = 40,
    repeats: Annotated[int, typer.Option("--repeats", help="Timed repeats (simulate-and-remap: candidates).")] = 3,
    threads: Annotated[int, typer.Option("--threads", help="torch threads.")] = 2,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the metrics as JSON here.")] = None,
    episodes: Annotated[int, typer.Option(
        "--episodes", help="observe: closed-loop view-only episodes on generated scenes 10000, 10001, ... whose "
                           "final-belief NLL decides the better model (0: the rollout of the recorded views).")] = 2,
    episode_steps: Annotated[int, typer.Option("--episode-steps", help="observe: steps per closed-loop episode.")] = 40,
    threshold_check: Annotated[int, typer.Option(
        "--threshold-check", help="push/grasp: also decide on this many mid-episode beliefs with the change "
                                  "threshold and with 0.05 and count different choices (0: skip).")] = 0,
    sim: Annotated[str, typer.Option("--sim", help="Simulator plugin name (e.g. pybullet, sapien) of the "
                                                   "simulate-and-remap timing and the episodes.")] = "pybullet",
) -> None:
    """NLL, Brier, ECE of learned vs analytic vs no-change beliefs against the real ground truth; speed."""
    from msmem_cnabu.learn.evaluation import evaluate, format_table, threshold_agreement

    kind = _kind(kind)
    if threshold_check > 0:  # fail before the metrics, not after them
        from msmem_core.sim.build import check_simulator

        check_simulator(sim)
    r = evaluate(kind, data, weights, change_threshold=change_threshold, timing=timing, candidates=candidates,
                 repeats=repeats, threads=threads, log=typer.echo, episodes=episodes,
                 episode_steps=episode_steps, simulator=sim, change_epsilon=change_epsilon)
    typer.echo(format_table(r))
    if threshold_check > 0:
        r["threshold_agreement"] = threshold_agreement(kind, weights, (change_threshold, 0.05), threshold_check,
                                                       threads=threads, log=typer.echo, simulator=sim,
                                                       epsilon=change_epsilon)
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(r, indent=2))
        typer.echo(f"metrics: {json_out}")


CLASS_MAP_HELP = ("For data of other classes (datagen --generator): a YAML file whose class_map (at the top "
                  "level or under observation_model.params, as in a run config) maps each scene class to a "
                  "built-in class.")


def _class_map(path: Path | None) -> dict[str, str] | None:
    """The ``class_map`` of a YAML file (top level, or a run config's ``observation_model.params``)."""
    if path is None:
        return None
    from msmem_core.config import read_config_file

    data = read_config_file(path)
    found = data.get("class_map", (data.get("observation_model") or {}).get("params", {}).get("class_map"))
    if not isinstance(found, dict) or not all(isinstance(k, str) and isinstance(v, str) for k, v in found.items()):
        raise UserError(f"{path}: no class_map (scene class: built-in class) at the top level or under "
                        "observation_model.params")
    return dict(found)


def train_cnabu_map(
    data: Annotated[list[Path], typer.Option(
        "--data", help="Observe shards made with --min-views 0 --max-views 0; repeat for several folders "
        "(each batch from one folder, folders drawn in proportion to their scenes).")],
    out: Annotated[Path, typer.Option("--out", help="Weights file (.pt); a .json sidecar is written beside it.")],
    heldout: Annotated[Path | None, typer.Option(
        "--heldout", help="Held-out shards (other seeds): rollouts scored against the twins at the end.")] = None,
    epochs: Annotated[float, typer.Option("--epochs", help="Passes over the training scenes.")] = 2.0,
    batches: Annotated[int | None, typer.Option(
        "--batches", help="Train exactly this many batches instead, re-listing a growing data folder.")] = None,
    batch: Annotated[int, typer.Option("--batch", help="Scenes unrolled together.")] = 4,
    lr: Annotated[float, typer.Option("--lr", help="AdamW peak learning rate (one-cycle schedule).")] = 2e-3,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the initialisation, order and mirroring.")] = 0,
    threads: Annotated[int, typer.Option("--threads", help="torch threads.")] = 2,
    max_minutes: Annotated[float | None, typer.Option("--max-minutes", help="Stop (and write) after this.")] = None,
    init: Annotated[Path | None, typer.Option(
        "--init", help="Start from these weights (same architecture, or one whose per-voxel inputs grew).")] = None,
    occupied_class_weight: Annotated[float, typer.Option(
        "--occupied-class-weight", help="Weight of truly occupied voxels in the class NLL.")] = 1.0,
    top_view_weight: Annotated[float, typer.Option(
        "--top-view-weight", help="Weight of the top-view class NLL (the paper's 2-D semantic map).")] = 0.0,
    arch: Annotated[Path | None, typer.Option(
        "--arch", help="YAML file of network settings (MapNetConfig fields, e.g. class_head: object).")] = None,
    class_map: Annotated[Path | None, typer.Option("--class-map", help=CLASS_MAP_HELP)] = None,
) -> None:
    """Train the whole-map observation network (cnabu-map) through rollouts of recorded views."""
    from msmem_cnabu.learn.maptrain import MapTrainConfig, train_map
    from msmem_core.config import read_config_file

    cfg = MapTrainConfig(epochs=epochs, batches=batches, batch=batch, lr=lr, seed=seed, threads=threads,
                         time_limit_s=None if max_minutes is None else 60 * max_minutes,
                         occupied_class_weight=occupied_class_weight, top_view_weight=top_view_weight,
                         class_map=_class_map(class_map))
    side = train_map(data, out, cfg, heldout_dir=heldout, log=typer.echo, init=init,
                     arch=None if arch is None else read_config_file(arch))
    typer.echo(f"{side['data']['scenes']} scenes, {side['seconds'] / 60:.1f} min, stopped by {side['stopped']}, "
               f"{side['bytes'] / 1e6:.2f} MB -> {out} (sha256 {side['sha256'][:12]}...)")


def eval_map(
    data: Annotated[Path, typer.Option("--data", help="Held-out observe shards (--min-views 0 --max-views 0).")],
    weights: Annotated[Path | None, typer.Option("--weights", help="cnabu-map weights (default: the shipped ones).")
                       ] = None,
    scenes: Annotated[int | None, typer.Option("--scenes", help="At most this many shards.")] = None,
    threads: Annotated[int, typer.Option("--threads", help="torch threads.")] = 2,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the results as JSON here.")] = None,
    unseen_class_weight: Annotated[float, typer.Option(
        "--unseen-class-weight", help="cnabu-map's unseen_class_weight (1: off).", min=1e-9, max=1.0)] = 1.0,
    class_map: Annotated[Path | None, typer.Option("--class-map", help=CLASS_MAP_HELP)] = None,
) -> None:
    """Rollouts of recorded views: the cnabu-map network, the default belief it is part of (the network with the
    ray record's authority), analytic-observation and column-fill (paper metrics, NLL, ECE)."""
    import torch

    from msmem_cnabu.configs import CNABUMapConfig
    from msmem_cnabu.learn.mapeval import evaluate_rollouts, twins
    from msmem_cnabu.mapmodel import SHIPPED, CNABUMapObservationModel
    from msmem_cnabu.weights import load_map_net

    torch.set_num_threads(threads)
    net, meta = load_map_net(weights or SHIPPED)
    models = twins()
    # with a class map the shards are moved onto the trained classes, which the belief's class-map rules do not see
    if class_map is None:
        # the observation model an episode uses: the network with the ray record's authority (its defaults)
        default = CNABUMapObservationModel(CNABUMapConfig(weights=weights, unseen_class_weight=unseen_class_weight,
                                                          threads=threads))
        models = {"cnabu-map (default belief)": default.update_masks, **models}
    r = evaluate_rollouts(net, data, models=models, max_scenes=scenes, log=typer.echo,
                          unseen_class_weight=unseen_class_weight, class_map=_class_map(class_map))
    r["weights"], r["weights_sha256"] = str(weights or SHIPPED), meta["sha256"]
    if json_out is not None:
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(r, indent=1, default=float))
        typer.echo(f"results: {json_out}")



COMMANDS = (
    CommandSpec(name="cnabu", action=datagen_cnabu, group="datagen",
                summary="CNABU training data: belief before, action, ground truth after."),
    CommandSpec(name="cnabu", action=train_cnabu, group="train",
                summary="Train a CNABU network; keeps the best weights and a JSON sidecar."),
    CommandSpec(name="belief-models", action=eval_belief_models, group="eval",
                summary="Learned vs analytic vs no-change belief models: NLL, Brier, ECE, speed."),
    CommandSpec(name="cnabu-map", action=train_cnabu_map, group="train",
                summary="Train the whole-map observation network (cnabu-map) through rollouts of recorded views."),
    CommandSpec(name="map", action=eval_map, group="eval",
                summary="Rollouts of recorded views: cnabu-map against analytic-observation and column-fill."),
)
