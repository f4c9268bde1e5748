"""Ctrl-C around compiled kernels: ``deferred_interrupt`` holds a SIGINT back while a numba kernel
runs and raises ``KeyboardInterrupt`` right after it returns.

With Python's default handler a Ctrl-C landing inside a numba kernel raises in the middle of numba's
own glue code (for example while it unpickles a constant), which can end in ``SystemError: ...
returned a result with an exception set``; between kernel calls the interrupt is an ordinary
``KeyboardInterrupt`` that msmem reports (``interrupted at step N; partial run in DIR``).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType


def caused_by_interrupt(error: BaseException) -> bool:
    """``error`` is, or was raised from, a ``KeyboardInterrupt`` (a Ctrl-C that landed in a compiled
    extension's glue code surfaces as ``SystemError: ... returned a result with an exception set``)."""
    seen: set[int] = set()
    e: BaseException | None = error
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


@contextmanager
def deferred_interrupt() -> Iterator[None]:
    """Run the block with SIGINT recorded instead of raised; raise ``KeyboardInterrupt`` after it if
    one came. Only in the main thread and only over Python's default handler (else a no-op)."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    hit: list[int] = []

    def record(signum: int, frame: FrameType | None) -> None:
        hit.append(signum)

    signal.signal(signal.SIGINT, record)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if hit:
        raise KeyboardInterrupt
