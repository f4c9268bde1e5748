"""The `msmem` command line."""

from msmem_core.cli.app import build_app, main

__all__ = ["build_app", "main"]
