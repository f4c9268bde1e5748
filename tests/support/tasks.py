"""Module-level task functions for executor fault-injection tests (spawned workers import them by name)."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path


def square_or_die(x: int) -> int:
    """``x * x``; for a negative ``x`` the worker process kills itself, as the out-of-memory killer would."""
    if x < 0:
        os.kill(os.getpid(), signal.SIGKILL)
    time.sleep(0.2)
    return x * x


def record_pid_and_sleep(folder: str) -> None:
    """Write this worker's pid into ``folder`` and sleep (until killed)."""
    Path(folder, f"{os.getpid()}.pid").write_text(str(os.getpid()))
    time.sleep(120)
