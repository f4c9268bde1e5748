"""Spans: named, nested stages of a computation, reported to an observer (a ``Tracer``).

MSAS opens a span around each stage of a step (``decide``, and per skill ``track``, ``propose``,
``predict``, ``score`` with its ``term`` and ``refine`` calls, and ``execute``); the IG service and
plugins open their own inside them (``ig.sweep``, ``FPP (frontier points)``, ...). Nothing is
reported unless a tracer is active: ``msas.run_msas`` and ``msas.decide`` activate the one they are
given for their duration (``tracing``). Without one, ``span`` costs a context-variable lookup and
an empty ``with``; no stage is wrapped, patched or timed.

A tracer sees ``begin(span)`` before the stage runs and ``end(span)`` after it, with
``span.result`` (the stage's value, where the code sets it) or ``span.error`` (an exception that left
it). ``msmem perf step`` is a tracer that times the stages; ``examples/diagnose_*.py`` are tracers
that inspect each executed action.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager, nullcontext
from contextvars import ContextVar
from dataclasses import dataclass, field
from typing import Any

__all__ = ["Span", "Tracer", "active_tracer", "span", "tracing"]


@dataclass(slots=True)
class Span:
    """One stage: its name, the skill it runs for (if any), what it works on, and how it ended."""

    stage: str
    """``decide``, ``track``, ``propose``, ``predict``, ``score``, ``term``, ``refine``, ``execute``, or a
    component's own stage (``ig.sweep``, ``FPP (frontier points)``, ...)."""
    skill: str | None = None
    info: dict[str, Any] = field(default_factory=dict)
    """What the stage works on, by name (``ctx``, ``batch``, ``term``, ``sim``, ``decision``, ...; each
    stage's entries are listed where it is opened)."""
    result: Any = None
    """The stage's value, set by the code inside the span before it closes (None where it sets none)."""
    error: BaseException | None = None


class Tracer:
    """Observer of spans. Subclass it and override what you need; both hooks do nothing here."""

    def begin(self, span: Span) -> None:
        """Called before the stage runs."""

    def end(self, span: Span) -> None:
        """Called after it, also when it raised (``span.error``)."""


_ACTIVE: ContextVar[Tracer | None] = ContextVar("msmem_tracer", default=None)
_IDLE: AbstractContextManager[None] = nullcontext()


def active_tracer() -> Tracer | None:
    """The tracer spans are reported to now, if any."""
    return _ACTIVE.get()


def tracing(tracer: Tracer | None) -> AbstractContextManager[None]:
    """Report the spans opened inside the ``with`` block to ``tracer``; None keeps the active one."""
    return _IDLE if tracer is None else _activate(tracer)


@contextmanager
def _activate(tracer: Tracer) -> Iterator[None]:
    token = _ACTIVE.set(tracer)
    try:
        yield
    finally:
        _ACTIVE.reset(token)


def span(stage: str, skill: str | None = None, **info: Any) -> AbstractContextManager[Span | None]:
    """A ``with`` block reported as one stage to the active tracer; it yields the ``Span`` (to set its
    ``result``), or None when no tracer is active."""
    tracer = _ACTIVE.get()
    if tracer is None:
        return _IDLE
    return _reported(tracer, Span(stage, skill, info))


@contextmanager
def _reported(tracer: Tracer, s: Span) -> Iterator[Span]:
    tracer.begin(s)
    try:
        yield s
    except BaseException as e:
        s.error = e
        raise
    finally:
        tracer.end(s)
