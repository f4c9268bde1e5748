"""The ``msmem`` command line. User errors print one line and exit 2; ``--debug`` shows the traceback.

``build_app`` makes the command line: the core's commands and groups, then every plugin's commands
(hook ``msmem_commands``, records ``CommandSpec``). This module imports no plugin package.
"""

from __future__ import annotations

import functools
import json
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer

from msmem_core.errors import ComponentFailure, IncompleteError, Interrupted, UserError
from msmem_core.util.interrupt import caused_by_interrupt

if TYPE_CHECKING:
    from msmem_core.plugins.manager import MsmemPluginManager

HELP = "Multi-Skill Manipulation-Enhanced Mapping: map a cluttered shelf by looking, pushing and grasping."
GROUPS: dict[str, str] = {  # the core's command groups (plugins add commands to them): name -> help
    "config": "Inspect configuration.",
    "perf": "Speed benchmarks.",
    "scene": "Generate and inspect scenes.",
    "docs": "Generate reference documentation (docs/reference/*.md, docs/results.md).",
    "datagen": "Generate training data for the learned models.",
    "train": "Train the learned models.",
    "eval": "Evaluate the learned models on held-out data.",
}

MethodOpt = Annotated[str | None, typer.Option(
    "--method", "-m", help="Method preset: view-only, push-only, grasp-only, no-cdc, ours.")]
ConfigOpt = Annotated[Path | None, typer.Option("--config", "-c", help="YAML/JSON config file overriding the preset.")]
WaitOpt = Annotated[bool, typer.Option(
    "--wait", help="If another msmem process is writing --out, wait for it to finish (default: stop with an error).")]


def _root(debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks for errors.")] = False) -> None:
    """msmem: see `msmem COMMAND --help`."""


def _pm() -> Any:
    from msmem_core.plugins import get_plugin_manager

    return get_plugin_manager()


def plugins(as_json: Annotated[bool, typer.Option("--json", help="Machine-readable output.")] = False) -> None:
    """List every registered component (kind, name, distribution, description, config fields) and the
    commands plugins add."""
    pm = _pm()
    rows = pm.listing()
    commands = [{"command": f"msmem {r.spec.path}", "distribution": r.distribution, "plugin": r.plugin,
                 "summary": r.spec.summary} for r in pm.commands()]
    if as_json:
        typer.echo(json.dumps({"components": rows, "commands": commands, "load_errors": pm.load_errors},
                              indent=2, default=str))
        return
    from rich.console import Console
    from rich.markup import escape
    from rich.table import Table

    table = Table("kind", "name", "distribution", "description", "config fields")
    for r in rows:
        table.add_row(r["kind"], r["name"], r["distribution"], escape(r["description"]),
                      ", ".join(r["config"]) or "-")
    Console().print(table)
    if commands:
        table = Table("command", "distribution", "summary")
        for c in commands:
            table.add_row(c["command"], c["distribution"], escape(c["summary"]))
        Console().print(table)
    for name, err in pm.load_errors.items():
        typer.echo(f"failed plugin {name!r} (from {pm.failed_distributions.get(name, '?')}): {err}", err=True)


def config_show(method: MethodOpt = None, config: ConfigOpt = None) -> None:
    """Print the resolved configuration (preset < --config file) as YAML, once every component it names
    is checked registered and its params valid."""
    import yaml

    from msmem_core.config import load_config
    from msmem_core.run.runner import check_params

    cfg = load_config(method, config)
    check_params(cfg, _pm())  # every component registered and its params valid, as `msmem run` checks them
    typer.echo(yaml.safe_dump(json.loads(cfg.model_dump_json()), sort_keys=False))


def run(
    method: MethodOpt = None,
    config: ConfigOpt = None,
    sim: Annotated[str | None, typer.Option("--sim", help="Simulator plugin name (e.g. pybullet, sapien).")] = None,
    robot: Annotated[str | None, typer.Option("--robot", help="Robot plugin name (e.g. floating, panda).")] = None,
    scene: Annotated[Path | None, typer.Option("--scene", help="SceneSpec JSON file.")] = None,
    scene_seed: Annotated[int | None, typer.Option("--scene-seed", help="Generate the scene from this seed.")] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="T_max: number of actions.")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Root seed of the episode.")] = None,
    out: Annotated[Path | None,
                   typer.Option("--out", help="Run folder (default runs/<method>-scene<N>-seed<S>).")] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress bar.")] = False,
    report: Annotated[bool, typer.Option("--report/--no-report",
                                         help="Write report.html and PNGs to the run folder.")] = True,
    overwrite: Annotated[bool, typer.Option("--overwrite",
                                            help="Replace an existing non-empty --out folder whole.")] = False,
    wait: WaitOpt = False,
) -> None:
    """Run one mapping episode and write config.json, steps.jsonl, metrics.json and the report to the run folder.

    The run is written into OUT.partial-XXXX beside --out and renamed to --out when complete; Ctrl-C, or a
    plugin's component that fails (exit code 3), leaves the partial folder and names it. One writer per
    --out: another run into it is refused, or waits with --wait (docs/explanation/reliability.md)."""
    from contextlib import ExitStack

    with ExitStack() as held:  # the lock of --out, from before it is checked until the run is renamed into it
        _run(held, method, config, sim, robot, scene, scene_seed, steps, seed, out, quiet, report, overwrite, wait)


def _lock_run(held: Any, out: Path, wait: bool) -> None:
    """Hold the lock of run folder ``out`` until ``held`` closes (``UserError`` naming it if it cannot be taken)."""
    from msmem_core.run.lock import FolderLocked, folder_lock, run_lock_file

    try:
        held.enter_context(folder_lock(out, run_lock_file(out), wait))
    except FolderLocked:
        raise
    except OSError as e:
        raise UserError(f"cannot write the run folder {out}: {e.strerror or e}"
                        + (f": {e.filename}" if e.filename else "")) from e


def _run(held: Any, method: str | None, config: Path | None, sim: str | None, robot: str | None,
         scene: Path | None, scene_seed: int | None, steps: int | None, seed: int | None, out: Path | None,
         quiet: bool, report: bool, overwrite: bool, wait: bool) -> None:
    import shutil

    from msmem_core.config import RunConfig, load_config
    from msmem_core.run.runfolder import commit_run_dir, stage_run_dir, writing
    from msmem_core.run.runner import build_episode, run_episode

    if scene is not None and scene_seed is not None:
        raise UserError("give either --scene or --scene-seed, not both")
    over: dict[str, Any] = {}
    if sim:
        over["simulator"] = {"name": sim, "params": {}}
    if robot:
        over["robot"] = {"name": robot, "params": {}}
    if scene is not None:
        over["scene"] = {"file": str(scene)}
    if scene_seed is not None:
        over["scene"] = {"seed": scene_seed, "file": None}
    if steps is not None:
        over["steps"] = steps
    if seed is not None:
        over["seed"] = seed
    cfg = load_config(method, config, over)
    if out is not None:
        _lock_run(held, out, wait)
    staged = stage_run_dir(out, overwrite) if out is not None else None  # checked before any work
    try:
        ep = build_episode(cfg, _pm())  # plugin names are checked before the scene is generated (seconds)
        out_dir = out or Path("runs") / f"{cfg.method}-{ep.scene.name}-seed{cfg.seed}"
        if staged is None:
            _lock_run(held, out_dir, wait)
            staged = stage_run_dir(out_dir, overwrite)
    except BaseException:
        if staged is not None:
            shutil.rmtree(staged, ignore_errors=True)
        raise
    hidden = f", {ep.scene.hidden_objects} hidden" if ep.scene.hidden_objects is not None else ""
    typer.echo(f"msmem run: method {cfg.method}, scene {ep.scene.name} ({len(ep.scene.objects)} objects{hidden}), "
               f"simulator {cfg.simulator.name}, {cfg.steps} steps -> {out_dir}")
    if ep.robot is not None and cfg.robot != RunConfig.model_fields["robot"].default:  # not the floating gripper
        reach = ep.robot.reachable_views(ep.viewpoints, ep.scene.shelf)
        typer.echo(f"robot {cfg.robot.name}: {int(reach.sum())} of {len(reach)} viewpoints reachable")
    if quiet:
        final = run_episode(ep, staged)
    else:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        with Progress(TextColumn("step"), MofNCompleteColumn(), BarColumn(), TextColumn("{task.fields[info]}"),
                      TimeElapsedColumn()) as bar:
            task = bar.add_task("run", total=cfg.steps, info="")

            def tick(rec: dict[str, Any]) -> None:
                info = (f"{rec['skill']:<6} obj {rec['objective']:8.2f}  "
                        f"occ IoU {rec['metrics']['occupancy_iou']:.3f}")
                bar.update(task, advance=1, info=info)

            final = run_episode(ep, staged, progress=tick)
    report_file = None
    if report:
        from msmem_core.run.report import write_report

        with writing(staged / "report.html", staged):  # a full disk names the folder (PNGs are named by their error)
            report_file = out_dir / write_report(staged)[0].name
    commit_run_dir(staged, out_dir)
    keys = ("occupancy_iou", "observable_iou", "semantic_miou", "semantic_miou_bev", "position_change_m")
    typer.echo("final: " + ", ".join(f"{k} {final[k]:.3f}" for k in keys))
    paper = ("occupancy_miou", "semantic_miou_2d", "occupancy_ece", "semantic_ece")
    typer.echo("paper's metrics: " + ", ".join(f"{k} {final[k]:.3f}" for k in paper))
    typer.echo(f"actions: {final['actions']}  seconds/step: {final['seconds_per_step']:.2f}")
    if report_file is not None:
        typer.echo(f"report: {report_file}")


def bench(
    methods: Annotated[str, typer.Option("--methods", help="Comma-separated method presets.")] = "view-only,push-only",
    suite: Annotated[str, typer.Option("--suite", help="A shipped scene suite (hard25, tune10, mesh25), a folder of "
                                       "scene JSON files, or a suite file (YAML, `scenes:` listing scene files).")
                     ] = "hard25",
    scenes: Annotated[str | None, typer.Option("--scenes", help="Scene indices, e.g. 0-4,7 (default: all).")] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="T_max per episode.")] = None,
    sim: Annotated[str | None, typer.Option("--sim", help="Simulator plugin name.")] = None,
    config: ConfigOpt = None,
    executor: Annotated[str, typer.Option("--executor", help="local or ray.")] = "local",
    workers: Annotated[int, typer.Option("--workers", help="Episodes in parallel.")] = 2,
    threads: Annotated[int, typer.Option("--threads", help="Threads per episode (numba, torch).")] = 1,
    address: Annotated[str | None, typer.Option("--address", help="Ray cluster address (executor ray).")] = None,
    out: Annotated[Path, typer.Option("--out", help="Results folder (rerun to resume).")] = Path("runs/bench"),
    retry_crashed: Annotated[bool, typer.Option("--retry-crashed/--no-retry-crashed",
                                                help="Rerun episodes that crashed in an earlier run.")] = True,
    rerun_mismatched: Annotated[bool, typer.Option(
        "--rerun-mismatched", help="Rerun episodes whose files were made with another method, suite, scene, "
                                   "steps, config or plugin versions (default: stop with an error).")] = False,
    wait: WaitOpt = False,
) -> None:
    """Run methods x scenes episodes; writes episodes/*.json, table.md, results.json and curves.png.

    Rerun into the same --out to resume: finished episodes are reused only if their fingerprint matches
    (docs/explanation/reliability.md); crashed ones are retried. One writer per --out: another bench into it is
    refused, or waits with --wait."""
    import os

    from msmem_core.run.bench import parse_methods, parse_range, run_bench, suite_scenes

    method_list = parse_methods(methods)  # unknown methods fail before any episode starts
    suite_list = suite_scenes(suite)
    over: dict[str, Any] = {}
    if steps is not None:
        over["steps"] = steps
    if sim:
        over["simulator"] = {"name": sim, "params": {}}
    if address:
        os.environ["RAY_ADDRESS"] = address
    try:
        summary = run_bench(method_list, suite_list, parse_range(scenes, len(suite_list)), out, over,
                            str(config) if config else None, executor, workers, threads, suite=suite,
                            retry_crashed=retry_crashed, rerun_mismatched=rerun_mismatched, wait=wait)
    except (KeyboardInterrupt, Interrupted) as e:
        raise Interrupted(f"interrupted; finished episodes are kept in {out / 'episodes'}: rerun the same "
                          "command to resume") from e
    typer.echo((out / "table.md").read_text())
    if summary["errors"]:
        typer.echo(f"{len(summary['errors'])} episode(s) crashed; see {out / 'results.json'}", err=True)


def eval_ceiling(
    suite: Annotated[str, typer.Option("--suite", help="A shipped scene suite (hard25, tune10, mesh25), a folder of "
                                       "scene JSON files, or a suite file (YAML, `scenes:` listing scene files).")
                     ] = "hard25",
    scenes: Annotated[str | None, typer.Option("--scenes", help="Scene indices, e.g. 0-4,7 (default: all).")] = "0-4",
    views: Annotated[int, typer.Option("--views", help="Evenly spaced views integrated per scene.")] = 100,
    observe: Annotated[list[str] | None, typer.Option(
        "--observe", help="Observation model to compare (repeat; 'default': the config's).")] = None,
    variants: Annotated[str, typer.Option(
        "--variants", help="Comma-separated: scene, front-occluder, all-occluders.")
    ] = "scene,front-occluder,all-occluders",
    method: MethodOpt = None,
    config: ConfigOpt = None,
    out: Annotated[Path | None, typer.Option("--out", help="Also write the rows and summary as JSON here.")] = None,
) -> None:
    """What views alone can map, and what removing occluders is worth: the paper's map metrics of N evenly
    spaced views on each scene and its oracle variants, per observation model (docs/explanation/map-prediction.md)."""
    import json

    from msmem_core.config import load_config
    from msmem_core.run.bench import parse_range, suite_scenes
    from msmem_core.run.ceiling import ceiling, format_table, summary

    cfg = load_config(method or "view-only", str(config) if config else None, {"threads": 1})
    suite_list = suite_scenes(suite)
    picked = [(i, suite_list[i]) for i in parse_range(scenes, len(suite_list))]
    names = [v.strip() for v in variants.split(",") if v.strip()]
    rows = ceiling(cfg, _pm(), picked, views, observe or ["default", "analytic-observation"], names)
    typer.echo(format_table(rows))
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"suite": suite, "views": views, "rows": [r.as_dict() for r in rows],
                                   "summary": summary(rows)}, indent=1) + "\n")


def report_cmd(
    run_dir: Annotated[Path, typer.Argument(help="Run folder written by `msmem run`.")],
    png: Annotated[bool, typer.Option("--png/--no-png",
                                      help="Also write report_metrics.png and report_belief.png.")] = True,
) -> None:
    """(Re)write a run folder's report: report.html (interactive 3-D belief, opens offline) and PNG snapshots."""
    from msmem_core.run.report import write_report

    for path in write_report(run_dir, png=png):
        typer.echo(str(path))


def scene_generate(
    seed: Annotated[int, typer.Option("--seed", help="Scene seed (the first one with --count).")] = 0,
    out: Annotated[Path, typer.Option(
        "--out", help="Output SceneSpec JSON; with --count, a folder for scene_00.json, scene_01.json, ...")
    ] = Path("scene.json"),
    generator: Annotated[Path | None, typer.Option(
        "--generator", help="YAML or JSON of generator settings (SceneGenConfig: classes, builtin_classes, "
        "occupancy_range, ...); mesh paths are relative to the file.")] = None,
    count: Annotated[int | None, typer.Option(
        "--count", min=1, help="Generate this many scenes, seeds --seed, --seed + 1, ... (a suite).")] = None,
    name: Annotated[str | None, typer.Option(
        "--name", help="Scene names: NAME-00, NAME-01, ... (default gen-<seed>).")] = None,
) -> None:
    """Generate hard shelf scenes from seeds and write them as SceneSpec JSON."""
    from msmem_core.config import load_generator_config
    from msmem_core.world.scenegen import generate_scene

    cfg = load_generator_config(generator)
    if count is not None and out.exists() and not out.is_dir():
        raise UserError(f"--out {out}: with --count it must be a folder")
    for i in range(count or 1):  # each scene is written as soon as it is made
        spec = generate_scene(seed + i, cfg)
        path = out if count is None else out / f"scene_{i:02d}.json"
        if name is not None:
            spec = spec.model_copy(update={"name": name if count is None else f"{name}-{i:02d}"})
        path.parent.mkdir(parents=True, exist_ok=True)
        spec.to_json(path)
        typer.echo(f"{path}: {len(spec.objects)} objects, floor occupancy {spec.occupancy_fraction:.2f}, "
                   f"{spec.hidden_objects} hidden from all viewpoints")


def perf_ig(repeats: Annotated[int, typer.Option("--repeats", help="Timed repeats per figure.")] = 3) -> None:
    """Time 300-view IG sweeps (1 and 16 beliefs, 1 cm and 5 mm grids) against the brute-force reference."""
    from msmem_core.perf.ig import perf_ig as run_perf

    run_perf(repeats=repeats)


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


def docs_config() -> None:
    """Print the configuration reference (docs/reference/config.md), generated from the pydantic models."""
    from msmem_core.cli.docgen import config_reference

    typer.echo(config_reference(), nl=False)


def docs_cli() -> None:
    """Print the command-line reference (docs/reference/cli.md), generated from the commands' help."""
    from msmem_core.cli.docgen import cli_reference

    typer.echo(cli_reference(build_app(builtin_only=True)), nl=False)


def docs_api() -> None:
    """Print the API reference for plugin authors (docs/reference/api.md), generated from docstrings and signatures."""
    from msmem_core.cli.docgen import api_reference

    typer.echo(api_reference(), nl=False)


def docs_results(
    folder: Annotated[Path, typer.Option("--folder", help="The committed result folders.")] = Path("docs/results"),
) -> None:
    """Print the current results page (docs/results.md), generated from the committed result folders."""
    from msmem_core.run.results import results_page

    if not folder.is_dir():
        raise UserError(f"--folder {folder}: no such folder (run from the repository root)")
    typer.echo(results_page(folder), nl=False)


# ------------------------------------------------------------------------------------ the app
CORE_COMMANDS: dict[str | None, dict[str, Callable[..., Any]]] = {  # group (None: top level) -> name -> command
    None: {"plugins": plugins, "run": run, "bench": bench, "report": report_cmd},
    "config": {"show": config_show},
    "perf": {"ig": perf_ig, "step": perf_step},
    "scene": {"generate": scene_generate},
    "docs": {"config": docs_config, "cli": docs_cli, "api": docs_api, "results": docs_results},
    "eval": {"ceiling": eval_ceiling},
}


def _warn(message: str) -> None:
    from msmem_core.plugins.manager import PluginLoadWarning

    warnings.warn(message, PluginLoadWarning, stacklevel=3)


def build_app(pm: MsmemPluginManager | None = None, builtin_only: bool = False) -> typer.Typer:
    """The ``msmem`` command line: the core's groups and commands, then every plugin's commands.

    ``pm``: the plugin manager to take the commands from (default: a fresh one with every installed
    plugin). ``builtin_only``: only commands of msmem's own distribution (the documented ones).
    A plugin command that cannot join (its hook raised, an unknown group, a name the core uses, a
    signature typer cannot turn into a command) is left out with a warning naming the plugin.
    """
    app = typer.Typer(add_completion=False, no_args_is_help=True, pretty_exceptions_enable=False, help=HELP)
    app.callback()(_root)
    for name, fn in CORE_COMMANDS[None].items():
        app.command(name)(interruptible(fn))
    groups = {name: typer.Typer(no_args_is_help=True, help=text) for name, text in GROUPS.items()}
    for name, group in groups.items():
        for cmd, fn in CORE_COMMANDS.get(name, {}).items():
            group.command(cmd)(interruptible(fn))
        app.add_typer(group, name=name)
    if pm is None:
        try:
            pm = _pm()
        except UserError as e:  # e.g. a plugin with a misspelt hook: the core's commands still work
            _warn(f"plugins' commands are left out: {e}")
            return app
    add_plugin_commands(app, groups, pm, builtin_only)
    return app


def add_plugin_commands(app: typer.Typer, groups: dict[str, typer.Typer], pm: MsmemPluginManager,
                        builtin_only: bool = False) -> None:
    """Add the commands of ``pm.commands()`` to ``app`` (top level) and the core ``groups``, sorted by
    group and name so that the order does not depend on the order plugins load in."""
    import typer.main

    from msmem_core.plugins.manager import BUILTIN_DISTRIBUTION

    taken = {group: set(names) for group, names in CORE_COMMANDS.items()}
    taken[None] |= set(groups)
    for reg in sorted(pm.commands(), key=lambda r: (r.spec.group or "", r.spec.name)):
        spec = reg.spec
        if builtin_only and reg.distribution != BUILTIN_DISTRIBUTION:
            continue
        who = f"msmem plugin {reg.plugin!r} (from {reg.distribution})"
        if spec.group is not None and spec.group not in groups:
            _warn(f"{who}: command {spec.name!r} names the group {spec.group!r}, which does not exist "
                  f"(groups: {', '.join(groups)}); it is left out")
            continue
        if spec.name in taken.setdefault(spec.group, set()):
            _warn(f"{who}: command 'msmem {spec.path}' clashes with one of msmem's own; it is left out")
            continue
        if isinstance(spec.action, typer.Typer):
            sub = spec.action
        else:
            sub = typer.Typer()
            sub.command(spec.name, short_help=spec.summary)(spec.action)
        try:
            typer.main.get_command(sub)  # typer checks the parameters here: fail now, not when msmem starts
        except Exception as e:
            _warn(f"{who}: command 'msmem {spec.path}' is not a valid typer command, it is left out: "
                  f"{type(e).__name__}: {e}")
            continue
        target = app if spec.group is None else groups[spec.group]
        if isinstance(spec.action, typer.Typer):
            target.add_typer(spec.action, name=spec.name, short_help=spec.summary)
        else:
            target.command(spec.name, short_help=spec.summary)(interruptible(spec.action))
        taken[spec.group].add(spec.name)


def interruptible(fn: Callable[..., Any]) -> Callable[..., Any]:
    """``fn`` with Ctrl-C raised as :class:`Interrupted`. Typer ends a ``KeyboardInterrupt`` as a
    silent exit 130 (``typer.core._main``) before ``main`` could say anything; ``Interrupted`` is not a
    ``KeyboardInterrupt`` and reaches ``main``, which prints its message."""
    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except KeyboardInterrupt as e:
            raise Interrupted("interrupted") from e
        except SystemError as e:
            if caused_by_interrupt(e):
                raise Interrupted("interrupted") from e
            raise

    return wrapper


EXIT_INCOMPLETE = 1
"""A command ran but could not deliver all it planned (``IncompleteError``)."""
EXIT_USER_ERROR = 2
"""Bad input, or the machine refused (a config, a path, a plugin name, a full disk, out of memory)."""
EXIT_PLUGIN_FAILURE = 3
"""A plugin's component raised while msmem ran it (``ComponentFailure``)."""
EXIT_INTERRUPTED = 130
"""Ctrl-C."""


def main() -> None:
    from msmem_core.plugins.manager import show_warning
    from msmem_core.util.malloc import keep_large_allocations
    from msmem_core.util.threads import configure_threads

    configure_threads()  # before any command imports torch or numba
    keep_large_allocations()
    debug = "--debug" in sys.argv
    warnings.showwarning = show_warning  # plugin warnings: one line each, once per process
    try:
        build_app()()
    except (UserError, IncompleteError, OSError, MemoryError) as e:
        if debug:
            raise
        if isinstance(e, MemoryError):
            message = f"out of memory: {e}" if str(e) else "out of memory"
        elif isinstance(e, OSError):
            message = f"{e.strerror or type(e).__name__}: {e.filename}" if e.filename else f"{type(e).__name__}: {e}"
        else:
            message = str(e)
        typer.echo(f"msmem: error: {message}", err=True)
        sys.exit(EXIT_INCOMPLETE if isinstance(e, IncompleteError) else EXIT_USER_ERROR)
    except ComponentFailure as e:
        if debug:
            raise
        typer.echo(f"msmem: error: {e} (--debug shows the traceback)", err=True)
        sys.exit(EXIT_PLUGIN_FAILURE)
    except Interrupted as e:
        typer.echo(f"msmem: {e}", err=True)
        sys.exit(EXIT_INTERRUPTED)
    except KeyboardInterrupt:
        typer.echo("msmem: interrupted", err=True)
        sys.exit(EXIT_INTERRUPTED)


if __name__ == "__main__":
    main()
