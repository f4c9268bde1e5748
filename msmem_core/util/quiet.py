"""Silence C-level output (pybullet prints its build time on import)."""

from __future__ import annotations

import contextlib
import ctypes
import os
import sys
from collections.abc import Iterator


@contextlib.contextmanager
def quiet_stdio() -> Iterator[None]:
    """Send file descriptors 1 and 2 to /dev/null for the duration (no-op where they are not real fds)."""
    streams = [s for s in (sys.stdout, sys.stderr) if s is not None]
    try:
        fds = [s.fileno() for s in streams]
    except (AttributeError, OSError, ValueError):  # captured by pytest: nothing to hide at fd level
        yield
        return
    for s in streams:
        s.flush()
    saved = [os.dup(fd) for fd in fds]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        for fd in fds:
            os.dup2(devnull, fd)
        yield
    finally:
        with contextlib.suppress(Exception):
            ctypes.CDLL(None).fflush(None)  # flush C stdio buffers before the fds come back
        for fd, s in zip(fds, saved, strict=True):
            os.dup2(s, fd)
            os.close(s)
        os.close(devnull)
