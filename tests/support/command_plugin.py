"""A third-party-style plugin that adds commands: ``msmem hello``, ``msmem eval echo`` and a group
``msmem tools`` with ``msmem tools shout`` (registered with MSMEM_PLUGINS in tests/test_commands.py)."""

from collections.abc import Iterable
from typing import Annotated

import typer

from msmem_core.plugins import CommandSpec, hookimpl


def hello(name: Annotated[str, typer.Option("--name", help="Who to greet.")] = "world") -> None:
    """Greet someone (a test command)."""
    typer.echo(f"hello, {name}")


def echo(text: Annotated[str, typer.Argument(help="Text to print.")]) -> None:
    """Print the text back (a test command in the eval group)."""
    typer.echo(f"echo: {text}")


tools = typer.Typer(no_args_is_help=True, help="A plugin's own command group.")


@tools.command("shout")
def shout(text: Annotated[str, typer.Argument(help="Text to shout.")]) -> None:
    """Print the text in capitals."""
    typer.echo(text.upper())


@hookimpl
def msmem_commands() -> Iterable[CommandSpec]:
    yield CommandSpec(name="hello", action=hello, summary="Greet someone (test plugin).")
    yield CommandSpec(name="echo", action=echo, summary="Print the text back (test plugin).", group="eval")
    yield CommandSpec(name="tools", action=tools, summary="The test plugin's own group.")
