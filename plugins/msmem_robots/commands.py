"""The robot plugin's commands: ``msmem robot reach`` (registered by ``plugin.msmem_commands``).

Importing this module is cheap (typer only); the body builds the robot through the plugin manager.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated, Any

import typer

from msmem_core.plugins import CommandSpec

app = typer.Typer(help="The robot that carries the camera and the gripper (docs/explanation/robots.md).",
                  no_args_is_help=True)


@app.command("reach")
def reach(
    robot: Annotated[str | None, typer.Option("--robot", help="Robot name (default: the config's robot if it "
                                                              "names one, else panda).")] = None,
    config: Annotated[Path | None, typer.Option("--config", "-c", help="A run config (YAML or JSON): its robot "
                                                "and params, viewpoints and scene file.")] = None,
    cache: Annotated[bool, typer.Option("--cache/--no-cache", help="Use the reachability caches (--no-cache: "
                                        "compute every view again, to time it).")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="Print JSON, with the reachable view indices.")] = False,
) -> None:
    """How many candidate views the robot's wrist camera reaches without touching the shelf."""
    from msmem_core.config import load_config, read_config_file
    from msmem_core.interfaces import Robot
    from msmem_core.plugins import get_plugin_manager
    from msmem_core.plugins.manager import ComponentRef
    from msmem_core.run.runner import run_wide
    from msmem_core.world.placement import load_scene
    from msmem_core.world.viewpoints import default_start_view, generate_viewpoints

    cfg = load_config(None, config)
    named = config is not None and "robot" in read_config_file(config)
    ref = cfg.robot if robot is None and named else ComponentRef(name=robot or "panda")
    pm = get_plugin_manager()
    bot = pm.build("robot", ref, where="robot", **run_wide(cfg))
    shelf = load_scene(str(cfg.scene.file)).shelf if cfg.scene.file is not None else cfg.scene.generator.shelf
    views = generate_viewpoints(cfg.viewpoints, shelf)
    t0 = time.perf_counter()
    mask = bot.reachable_views(views, shelf) if cache else Robot.reachable_views(bot, views, shelf)
    seconds = time.perf_counter() - t0
    info = getattr(bot, "last_reach", None)
    source = info.source if cache and info is not None else "computed"
    start = cfg.msas.start_view if cfg.msas.start_view is not None else default_start_view(cfg.viewpoints)
    out: dict[str, Any] = {
        "robot": ref.name, "reachable": int(mask.sum()), "views": len(mask), "seconds": round(seconds, 3),
        "source": source, "start_view": start, "start_view_reachable": bool(mask[start]),
        "shelf_m": [shelf.width_m, shelf.depth_m, shelf.height_m],
    }
    groups = []
    if cfg.viewpoints.poses_file is None and len(cfg.viewpoints.targets_x_m) == 3:
        per = cfg.viewpoints.grid ** 2
        groups = [(name, int(mask[g * per:(g + 1) * per].sum()), per)
                  for g, name in enumerate(("left", "middle", "right"))]
        out["per_grid"] = {name: n for name, n, _ in groups}
    bot.close()
    if as_json:
        typer.echo(json.dumps(out | {"reachable_views": [int(i) for i in mask.nonzero()[0]]}))
        return
    typer.echo(f"robot {ref.name}: {out['reachable']} of {out['views']} viewpoints reachable "
               f"(shelf {shelf.width_m:g} x {shelf.depth_m:g} x {shelf.height_m:g} m); "
               f"{seconds:.2f} s ({source})")
    if groups:
        typer.echo("per grid: " + ", ".join(f"{name} {n}/{per}" for name, n, per in groups))
    typer.echo(f"start view {start}: {'reachable' if out['start_view_reachable'] else 'NOT reachable'}")


COMMANDS = (
    CommandSpec(name="robot", action=app, summary="The robot: which candidate views its wrist camera reaches."),
)
