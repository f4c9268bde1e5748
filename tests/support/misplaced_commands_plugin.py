"""A plugin whose commands cannot join: an unknown group, a clash with a core command, a signature
typer rejects. Each is left out with a warning naming the plugin; ``ok`` still joins."""

from collections.abc import Iterable
from typing import Annotated

import typer

from msmem_core.plugins import CommandSpec, hookimpl


def ok() -> None:
    """A command that works."""
    typer.echo("ok")


def bad_signature(value: Annotated[int, typer.Option("--value")] = typer.Option(1)) -> None:
    """typer refuses an option given both in ``Annotated`` and as the default."""


@hookimpl
def msmem_commands() -> Iterable[CommandSpec]:
    yield CommandSpec(name="nudge", action=ok, summary="In a group that does not exist.", group="nosuchgroup")
    yield CommandSpec(name="run", action=ok, summary="Clashes with `msmem run`.")
    yield CommandSpec(name="bad-signature", action=bad_signature, summary="typer rejects it.")
    yield CommandSpec(name="empty-group", action=typer.Typer(), summary="A group without commands.")
    yield CommandSpec(name="ok", action=ok, summary="Joins.")
