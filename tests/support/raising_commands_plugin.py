"""A plugin whose ``msmem_commands`` hook raises: the command line must report it and keep working."""

from collections.abc import Iterable

from msmem_core.plugins import CommandSpec, hookimpl


@hookimpl
def msmem_commands() -> Iterable[CommandSpec]:
    raise RuntimeError("this command hook is broken on purpose")
