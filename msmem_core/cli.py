"""The ``msmem`` command line. User errors print one line and exit 2; ``--debug`` shows the traceback."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from msmem_core.errors import UserError

app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False,
                  help="Multi-Skill Manipulation-Enhanced Mapping: map a cluttered shelf by looking, pushing and grasping.")
config_app = typer.Typer(no_args_is_help=True, help="Inspect configuration.")
perf_app = typer.Typer(no_args_is_help=True, help="Speed benchmarks.")
scene_app = typer.Typer(no_args_is_help=True, help="Generate and inspect scenes.")
app.add_typer(config_app, name="config")
app.add_typer(perf_app, name="perf")
app.add_typer(scene_app, name="scene")

MethodOpt = Annotated[str | None, typer.Option("--method", "-m", help="Method preset: view-only, push-only, grasp-only, no-cdc, ours.")]
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
    out: Annotated[Path | None, typer.Option("--out", help="Run folder (default runs/<method>-scene<N>-seed<S>).")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
) -> None:
    """Run one mapping episode and write config.json, steps.jsonl and metrics.json to the run folder."""
    from msmem_core.config import load_config
    from msmem_core.runner import build_episode, run_episode

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


@scene_app.command("generate")
def scene_generate(
    seed: Annotated[int, typer.Option("--seed", help="Scene seed.")] = 0,
    out: Annotated[Path, typer.Option("--out", help="Output SceneSpec JSON.")] = Path("scene.json"),
) -> None:
    """Generate a hard shelf scene from a seed and write it as SceneSpec JSON."""
    from msmem_core.scenegen import SceneGenConfig, generate_scene

    spec = generate_scene(seed, SceneGenConfig())
    spec.to_json(out)
    typer.echo(f"{out}: {len(spec.objects)} objects, floor occupancy {spec.occupancy_fraction:.2f}, "
               f"{spec.hidden_objects} hidden from all viewpoints")


@perf_app.command("ig")
def perf_ig(repeats: Annotated[int, typer.Option("--repeats", help="Timed repeats per figure.")] = 3) -> None:
    """Time 300-view IG sweeps (1 and 16 beliefs, 1 cm and 5 mm grids) against the brute-force reference."""
    from msmem_core.perf import perf_ig as run_perf

    run_perf(repeats=repeats)


def main() -> None:
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
