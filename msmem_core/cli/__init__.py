"""The `msmem` command line."""

from msmem_core.cli.app import app, main

__all__ = ["app", "main"]
