"""The push plugin's command ``msmem perf push`` (registered by ``plugin.msmem_commands``).

Importing this module is cheap (typer only); the body imports ``msmem_push.perf`` on use.
"""

from __future__ import annotations

from typing import Annotated

import typer

from msmem_core.plugins import CommandSpec


def perf_push(
    repeats: Annotated[int, typer.Option("--repeats", help="Timed repeats per stage (best is reported).")] = 3,
    samples: Annotated[int, typer.Option("--samples", help="Push candidates (UPS max_samples).")] = 80,
    scene_seed: Annotated[int, typer.Option("--scene-seed", help="Generated scene of the belief.")] = 0,
    reference: Annotated[bool, typer.Option("--reference/--no-reference", help="Also time the full re-score.")] = True,
    effect_model: Annotated[str | None, typer.Option("--effect-model", help="Push effect model (default: the push "
                                                                           "skill's, cnabu-push).")] = None,
) -> None:
    """Time sampling, effect prediction and scoring of push candidates on all 300 views (mid-episode belief)."""
    from msmem_push.perf import perf_push as run_perf

    run_perf(repeats=repeats, samples=samples, scene_seed=scene_seed, reference=reference, effect_model=effect_model)


COMMANDS = (
    CommandSpec(name="push", action=perf_push, group="perf",
                summary="Time sampling, effect prediction and scoring of push candidates."),
)
