"""The terminal progress bar of msmem's long loops (parallel tasks, training epochs)."""

from __future__ import annotations

from typing import Any


def progress_bar(head: str, tail: str) -> Any:
    """A started ``rich.progress.Progress``: ``head``, done / total, the bar, ``tail``, elapsed and
    remaining time. ``head`` and ``tail`` are rich format strings over the task (e.g.
    ``"{task.description}"``, ``"loss {task.fields[loss]}"``); stop the bar with ``.stop()``."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    bar = Progress(TextColumn(head), MofNCompleteColumn(), BarColumn(), TextColumn(tail), TimeElapsedColumn(),
                   TimeRemainingColumn())
    bar.start()
    return bar
