"""Failures named for the user: a plugin's component that raised while a run used it.

``named_failures`` turns an exception whose traceback runs through a method of a component the plugin
manager built (``msmem_core.plugins.manager.failed_component``) into a
:class:`~msmem_core.errors.ComponentFailure` naming the component's kind and name, its plugin and
distribution, the step underway, the exception, and the partial run folder. msmem's own errors, user
errors and Ctrl-C (also one that surfaced as a ``SystemError`` in compiled code) pass through unchanged.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from msmem_core.errors import ComponentFailure, UserError
from msmem_core.plugins.manager import failed_component
from msmem_core.util.interrupt import caused_by_interrupt


def one_line(error: BaseException) -> str:
    """``Type: message`` with the message's whitespace (newlines included) collapsed."""
    text = " ".join(str(error).split())
    return f"{type(error).__name__}: {text}" if text else type(error).__name__


@contextmanager
def named_failures(step: Callable[[], int], partial: Path | None = None) -> Iterator[None]:
    """Run the block; an exception a component raised becomes a ``ComponentFailure`` naming it, the step
    (``step()``: the one underway when it raised) and the ``partial`` run folder, if any."""
    try:
        yield
    except (ComponentFailure, UserError):
        raise
    except Exception as e:
        component = failed_component(e)
        if component is None or (isinstance(e, SystemError) and caused_by_interrupt(e)):
            raise
        where = f"; partial run in {partial}" if partial is not None else ""
        raise ComponentFailure(f"{component} failed at step {step()}: {one_line(e)}{where}") from e
