"""The ``msmem`` command line. User errors print one line and exit 2; ``--debug`` shows the traceback."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from msmem_core.errors import UserError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Multi-Skill Manipulation-Enhanced Mapping: map a cluttered shelf by looking, pushing "
                       "and grasping.")
config_app = typer.Typer(no_args_is_help=True, help="Inspect configuration.")
perf_app = typer.Typer(no_args_is_help=True, help="Speed benchmarks.")
scene_app = typer.Typer(no_args_is_help=True, help="Generate and inspect scenes.")
app.add_typer(config_app, name="config")
app.add_typer(perf_app, name="perf")
app.add_typer(scene_app, name="scene")
docs_app = typer.Typer(no_args_is_help=True, help="Generate reference documentation (docs/*.md).")
app.add_typer(docs_app, name="docs")
datagen_app = typer.Typer(no_args_is_help=True, help="Generate training data for the learned models.")
train_app = typer.Typer(no_args_is_help=True, help="Train the learned models.")
eval_app = typer.Typer(no_args_is_help=True, help="Evaluate the learned models on held-out data.")
app.add_typer(datagen_app, name="datagen")
app.add_typer(train_app, name="train")
app.add_typer(eval_app, name="eval")

MethodOpt = Annotated[str | None, typer.Option(
    "--method", "-m", help="Method preset: view-only, push-only, grasp-only, no-cdc, ours.")]
ConfigOpt = Annotated[Path | None, typer.Option("--config", "-c", help="YAML/JSON config file overriding the preset.")]


@app.callback()
def _root(debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks for errors.")] = False) -> None:
    """msmem: see `msmem COMMAND --help`."""


def _pm() -> Any:
    from msmem_core.plugins import get_plugin_manager

    return get_plugin_manager()


@app.command()
def plugins(as_json: Annotated[bool, typer.Option("--json", help="Machine-readable output.")] = False) -> None:
    """List every registered component: kind, name, distribution, description, config fields."""
    pm = _pm()
    rows = pm.listing()
    if as_json:
        typer.echo(json.dumps({"components": rows, "load_errors": pm.load_errors}, indent=2, default=str))
        return
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    table = Table("kind", "name", "distribution", "description", "config fields")
    for r in rows:
        table.add_row(r["kind"], r["name"], r["distribution"], escape(r["description"]),
                      ", ".join(r["config"]) or "-")
    Console().print(table)
    for name, err in pm.load_errors.items():
        typer.echo(f"warning: plugin {name!r} failed to load: {err}", err=True)


@config_app.command("show")
def config_show(method: MethodOpt = None, config: ConfigOpt = None) -> None:
    """Print the resolved configuration (preset < --config file) as YAML."""
    import yaml

    from msmem_core.config import load_config

    cfg = load_config(method, config)
    typer.echo(yaml.safe_dump(json.loads(cfg.model_dump_json()), sort_keys=False))


@app.command()
def run(
    method: MethodOpt = None,
    config: ConfigOpt = None,
    sim: Annotated[str | None, typer.Option("--sim", help="Simulator plugin name (e.g. pybullet, sapien).")] = None,
    scene: Annotated[Path | None, typer.Option("--scene", help="SceneSpec JSON file.")] = None,
    scene_seed: Annotated[int | None, typer.Option("--scene-seed", help="Generate the scene from this seed.")] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="T_max: number of actions.")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Root seed of the episode.")] = None,
    out: Annotated[Path | None,
                   typer.Option("--out", help="Run folder (default runs/<method>-scene<N>-seed<S>).")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    report: Annotated[bool, typer.Option("--report/--no-report",
                                         help="Write report.html and PNGs to the run folder.")] = True,
) -> None:
    """Run one mapping episode and write config.json, steps.jsonl, metrics.json and the report to the run folder."""
    from msmem_core.config import load_config
    from msmem_core.run.runner import build_episode, run_episode

    if scene is not None and scene_seed is not None:
        raise UserError("give either --scene or --scene-seed, not both")
    over: dict[str, Any] = {}
    if sim:
        over["simulator"] = {"name": sim, "params": {}}
    if scene is not None:
        over["scene"] = {"file": str(scene)}
    if scene_seed is not None:
        over["scene"] = {"seed": scene_seed, "file": None}
    if steps is not None:
        over["steps"] = steps
    if seed is not None:
        over["seed"] = seed
    cfg = load_config(method, config, over)
    ep = build_episode(cfg, _pm())
    out_dir = out or Path("runs") / f"{cfg.method}-{ep.scene.name}-seed{cfg.seed}"
    typer.echo(f"msmem run: method {cfg.method}, scene {ep.scene.name} ({len(ep.scene.objects)} objects, "
               f"{ep.scene.hidden_objects} hidden), simulator {cfg.simulator.name}, {cfg.steps} steps -> {out_dir}")
    if quiet:
        final = run_episode(ep, out_dir)
    else:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        with Progress(TextColumn("step"), MofNCompleteColumn(), BarColumn(), TextColumn("{task.fields[info]}"),
                      TimeElapsedColumn()) as bar:
            task = bar.add_task("run", total=cfg.steps, info="")

            def tick(rec: dict[str, Any]) -> None:
                info = (f"{rec['skill']:<6} obj {rec['objective']:8.2f}  "
                        f"occ IoU {rec['metrics']['occupancy_iou']:.3f}")
                bar.update(task, advance=1, info=info)

            final = run_episode(ep, out_dir, progress=tick)
    keys = ("occupancy_iou", "observable_iou", "semantic_miou", "semantic_miou_bev", "position_change_m")
    typer.echo("final: " + ", ".join(f"{k} {final[k]:.3f}" for k in keys))
    typer.echo(f"actions: {final['actions']}  seconds/step: {final['seconds_per_step']:.2f}")
    if report:
        from msmem_core.run.report import write_report

        typer.echo(f"report: {write_report(out_dir)[0]}")


@app.command()
def bench(
    methods: Annotated[str, typer.Option("--methods", help="Comma-separated method presets.")] = "view-only,push-only",
    suite: Annotated[str, typer.Option("--suite", help="Scene suite shipped with msmem.")] = "hard25",
    scenes: Annotated[str | None, typer.Option("--scenes", help="Scene indices, e.g. 0-4,7 (default: all).")] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="T_max per episode.")] = None,
    sim: Annotated[str | None, typer.Option("--sim", help="Simulator plugin name.")] = None,
    config: ConfigOpt = None,
    executor: Annotated[str, typer.Option("--executor", help="local or ray.")] = "local",
    workers: Annotated[int, typer.Option("--workers", help="Episodes in parallel.")] = 2,
    threads: Annotated[int, typer.Option("--threads", help="Threads per episode (numba, torch).")] = 1,
    address: Annotated[str | None, typer.Option("--address", help="Ray cluster address (executor ray).")] = None,
    out: Annotated[Path, typer.Option("--out", help="Results folder (rerun to resume).")] = Path("runs/bench"),
) -> None:
    """Run methods x scenes episodes; writes episodes/*.json, table.md, results.json and curves.png."""
    import os

    from msmem_core.config import preset
    from msmem_core.run.bench import parse_range, run_bench, suite_scenes

    method_list = [m.strip() for m in methods.split(",") if m.strip()]
    for m in method_list:
        preset(m)  # unknown methods fail before any episode starts
    suite_list = suite_scenes(suite)
    over: dict[str, Any] = {}
    if steps is not None:
        over["steps"] = steps
    if sim:
        over["simulator"] = {"name": sim, "params": {}}
    if address:
        os.environ["RAY_ADDRESS"] = address
    summary = run_bench(method_list, suite_list, parse_range(scenes, len(suite_list)), out, over,
                        str(config) if config else None, executor, workers, threads)
    typer.echo((out / "table.md").read_text())
    if summary["errors"]:
        typer.echo(f"{len(summary['errors'])} episode(s) crashed; see {out / 'results.json'}", err=True)


@app.command("report")
def report_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run folder written by `msmem run`.")],
    png: Annotated[bool, typer.Option("--png/--no-png",
                                      help="Also write report_metrics.png and report_belief.png.")] = True,
) -> None:
    """(Re)write a run folder's report: report.html (interactive 3-D belief, opens offline) and PNG snapshots."""
    from msmem_core.run.report import write_report

    for path in write_report(run_dir, png=png):
        typer.echo(str(path))


@scene_app.command("generate")
def scene_generate(
    seed: Annotated[int, typer.Option("--seed", help="Scene seed.")] = 0,
    out: Annotated[Path, typer.Option("--out", help="Output SceneSpec JSON.")] = Path("scene.json"),
) -> None:
    """Generate a hard shelf scene from a seed and write it as SceneSpec JSON."""
    from msmem_core.world.scenegen import SceneGenConfig, generate_scene

    spec = generate_scene(seed, SceneGenConfig())
    spec.to_json(out)
    typer.echo(f"{out}: {len(spec.objects)} objects, floor occupancy {spec.occupancy_fraction:.2f}, "
               f"{spec.hidden_objects} hidden from all viewpoints")


@perf_app.command("ig")
def perf_ig(repeats: Annotated[int, typer.Option("--repeats", help="Timed repeats per figure.")] = 3) -> None:
    """Time 300-view IG sweeps (1 and 16 beliefs, 1 cm and 5 mm grids) against the brute-force reference."""
    from msmem_core.perf.ig import perf_ig as run_perf

    run_perf(repeats=repeats)


@perf_app.command("push")
def perf_push(
    repeats: Annotated[int, typer.Option("--repeats", help="Timed repeats per stage (best is reported).")] = 3,
    samples: Annotated[int, typer.Option("--samples", help="Push candidates (UPS max_samples).")] = 80,
    scene_seed: Annotated[int, typer.Option("--scene-seed", help="Generated scene of the belief.")] = 0,
    reference: Annotated[bool, typer.Option("--reference/--no-reference", help="Also time the full re-score.")] = True,
    effect_model: Annotated[str | None, typer.Option("--effect-model", help="Push effect model (default: the push "
                                                                           "skill's, cnabu-push).")] = None,
) -> None:
    """Time sampling, effect prediction and scoring of push candidates on all 300 views (mid-episode belief)."""
    from msmem_core.perf.push import perf_push as run_perf

    run_perf(repeats=repeats, samples=samples, scene_seed=scene_seed, reference=reference, effect_model=effect_model)


@perf_app.command("step")
def perf_step(
    repeats: Annotated[int, typer.Option("--repeats", help="Timed decisions (the median is reported).")] = 5,
    scene_seed: Annotated[int, typer.Option("--scene-seed", help="Generated scene.")] = 1,
    scene: Annotated[Path | None, typer.Option("--scene", help="SceneSpec JSON file instead of --scene-seed.")] = None,
    views: Annotated[int, typer.Option("--views", help="Views integrated into the mid-episode belief.")] = 10,
    view_seed: Annotated[int, typer.Option("--view-seed", help="Seed of the random views.")] = 0,
    reference: Annotated[bool, typer.Option("--reference/--no-reference",
                                            help="Also time the brute-force references.")] = True,
    beliefs: Annotated[int, typer.Option("--beliefs", help="Beliefs on which screened and exact choices "
                                                           "are compared (0: none).")] = 3,
    method: MethodOpt = "ours",
    config: ConfigOpt = None,
) -> None:
    """Time one full MSAS decision (all skills, effect models, objective) on a mid-episode belief, by stage."""
    from msmem_core.perf.step import perf_step as run_perf

    run_perf(repeats=repeats, scene_seed=scene_seed, views=views, view_seed=view_seed, reference=reference,
             beliefs=beliefs, method=method or "ours", config=config, scene=scene)


@docs_app.command("config")
def docs_config() -> None:
    """Print the configuration reference (docs/config-reference.md), generated from the pydantic models."""
    from msmem_core.cli.docgen import config_reference

    typer.echo(config_reference(), nl=False)


@docs_app.command("cli")
def docs_cli() -> None:
    """Print the command-line reference (docs/cli.md), generated from the commands' help."""
    from msmem_core.cli.docgen import cli_reference

    typer.echo(cli_reference(), nl=False)


# Grasp learning (msmem_grasp). Imported inside the commands only, so the core CLI loads without it.
@datagen_app.command("grasp")
def datagen_grasp(
    scenes: Annotated[int, typer.Option("--scenes", help="Number of scenes (seeds SEED .. SEED+N-1).")],
    out: Annotated[Path, typer.Option("--out", help="Output folder: one scene_<seed>.npz per scene.")],
    workers: Annotated[int, typer.Option("--workers", help="Parallel processes (or Ray tasks in flight).")] = 1,
    seed: Annotated[int, typer.Option("--seed", help="First scene seed.")] = 0,
    executor: Annotated[str, typer.Option("--executor", help="local (processes) or ray.")] = "local",
    points: Annotated[int, typer.Option("--points", help="FPP points per scene.")] = 4096,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """FE-vMF training data: scene -> belief from 3-10 random views -> FPP points -> antipodal labels (resumable)."""
    from msmem_grasp.commands import datagen_grasp as run_datagen

    run_datagen(scenes=scenes, out=out, workers=workers, seed=seed, executor=executor, points=points, quiet=quiet)


@train_app.command("fe-vmf")
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
    from msmem_grasp.commands import train_fe_vmf as run_train

    run_train(data=data, out=out, epochs=epochs, val_fraction=val_fraction, seed=seed, lr=lr, threads=threads,
              max_minutes=max_minutes, quiet=quiet)


@eval_app.command("fe-vmf")
def eval_fe_vmf(
    data: Annotated[Path, typer.Option("--data", help="Folder of held-out shards.")],
    weights: Annotated[Path | None, typer.Option("--weights", help="Weights file (default: the shipped ones).")] = None,
    plot: Annotated[Path | None, typer.Option("--plot", help="Write the kappa calibration plot (PNG) here.")] = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the metrics as JSON here.")] = None,
    threads: Annotated[int, typer.Option("--threads", help="torch threads.")] = 2,
) -> None:
    """Held-out metrics of FE-vMF and of the geometric antipodal heuristic: AUROC, ECE, NLL, angular errors, P/R."""
    from msmem_grasp.commands import eval_fe_vmf as run_eval

    run_eval(data=data, weights=weights, plot=plot, json_out=json_out, threads=threads)


@app.command("bench-grasp")
def bench_grasp(
    scenes: Annotated[str, typer.Option("--scenes", help="Generated scene seeds, e.g. 0-9.")] = "0-9",
    trials: Annotated[int, typer.Option("--trials", help="Trials per scene (different views).")] = 2,
    views: Annotated[int, typer.Option("--views", help="Observations (one FE-UMGF step each) first.")] = 8,
    random_views: Annotated[bool, typer.Option("--random-views/--nbv", help="Random views, not next-best.")] = False,
    predictor: Annotated[str, typer.Option("--predictor", help="auto, fe-vmf or geometric.")] = "auto",
    hard: Annotated[bool, typer.Option("--hard/--any", help="Hard scenes (as episodes) or random ones.")] = False,
    workers: Annotated[int, typer.Option("--workers", help="Scenes in parallel.")] = 1,
    out: Annotated[Path, typer.Option("--out", help="Results folder.")] = Path("runs/bench-grasp"),
) -> None:
    """Top-1 fused grasp executed in PyBullet per scene and trial: success rate (grasps from the belief only)."""
    from msmem_grasp.bench import GraspBenchConfig
    from msmem_grasp.bench import bench_grasp as run_bench_grasp

    from msmem_core.run.bench import parse_range

    cfg = GraspBenchConfig(scene_seeds=parse_range(scenes, 10**6), trials=trials, views=views,
                           view_policy="random" if random_views else "nbv", require_hard=hard,
                           skill={"predictor": predictor})
    s = run_bench_grasp(cfg, out, workers=workers)["summary"]
    typer.echo(f"predictor {s['predictor']}: {s['successes']}/{s['executed']} grasps succeeded "
               f"({100 * s['success_rate']:.0f} %), {s['no_candidate']} of {s['trials']} trials had no executable "
               f"grasp; held object of the believed class {s['held_believed_class']}/{s['successes']}; "
               f"mean displacement of the other objects {s['mean_displaced_m']:.3f} m; "
               f"{s['fell_or_left']} trial(s) with an object fallen or out -> {out}")


# Learned CNABU (msmem_cnabu) adds `datagen cnabu`, `train cnabu` and `eval belief-models` (bodies imported on use).
try:
    from msmem_cnabu.commands import register as _register_cnabu
except ImportError:  # the plugin package is not installed
    pass
else:
    _register_cnabu(datagen_app, train_app, eval_app)


def main() -> None:
    from msmem_core.util.malloc import keep_large_allocations
    from msmem_core.util.threads import configure_threads

    configure_threads()  # before any command imports torch or numba
    keep_large_allocations()
    debug = "--debug" in sys.argv
    try:
        app()
    except UserError as e:
        if debug:
            raise
        typer.echo(f"msmem: error: {e}", err=True)
        sys.exit(2)
    except KeyboardInterrupt:
        typer.echo("msmem: interrupted", err=True)
        sys.exit(130)


if __name__ == "__main__":
    main()
