"""Run independent tasks (benchmark episodes, data-generation shards) on local processes or Ray.

``run_tasks(fn, tasks, executor="local", workers=N)`` calls ``fn(task)`` for every task and returns
the results in task order. ``fn`` must be a module-level function (it is pickled) and should write
its own result file atomically, so a killed run resumes by skipping finished tasks.

- ``local``: a ``ProcessPoolExecutor`` with the *spawn* start method (forking a process whose
  OpenMP / torch thread pools are running can deadlock the child); ``workers=1`` runs in this process.
- ``ray``: ``ray.remote`` tasks (one CPU each), at most ``workers`` in flight; connects to a running
  cluster if ``ray.init`` was called (or ``RAY_ADDRESS`` is set), else starts a local one. A task whose
  worker dies is retried once by Ray (``RAY_RETRIES``), then becomes that task's failure, as locally.

Every worker applies ``configure_threads`` (the OpenMP settings, ``msmem_core.util.threads``) and limits
torch / numba / OpenMP to ``threads`` threads before it runs a task, so results do not depend on where a
task ran (docs/explanation/performance.md). A task that raises does not stop the others: it comes back as
a :class:`TaskFailure` (or, with ``on_error="raise"``, the first one raises).

Local workers are robust: a worker process that dies (killed by the out-of-memory killer, a segfault
in native code) becomes a :class:`TaskFailure` of the task it ran, and the other tasks go on in a new
pool (the tasks that were in flight with it are rerun one at a time, so the failure is pinned on the
task that really killed its worker). Workers exit when the process that started them dies
(``PR_SET_PDEATHSIG`` on Linux, elsewhere a thread watching the parent), so no orphan keeps its memory.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass
from multiprocessing import get_context
from typing import Any, Literal

from msmem_core.errors import UserError
from msmem_core.util.progress import progress_bar
from msmem_core.util.threads import configure_threads

EXECUTORS = ("local", "ray")
ExecutorName = Literal["local", "ray"]


@dataclass(frozen=True)
class TaskFailure:
    """A task whose function raised: the task, ``"ExcType: message"`` and the formatted traceback."""

    index: int
    task: Any
    error: str
    traceback: str
    worker_died: bool = False
    """The task's worker process died (killed, or crashed in native code) rather than the task raising."""


class TaskError(RuntimeError):
    """Raised by ``run_tasks(on_error="raise")`` with the first failure attached."""

    def __init__(self, failure: TaskFailure) -> None:
        super().__init__(f"task {failure.index} ({failure.task!r}) failed: {failure.error}\n{failure.traceback}")
        self.failure = failure


def limit_threads(threads: int) -> None:
    """Cap OpenMP/MKL, numba and torch thread pools of this process at ``threads``."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS"):
        os.environ[var] = str(threads)
    import numba
    import torch

    numba.set_num_threads(max(1, min(threads, int(numba.config.NUMBA_NUM_THREADS))))  # type: ignore[attr-defined]
    torch.set_num_threads(threads)


@contextmanager
def _threads_in_this_process(threads: int | None) -> Iterator[None]:
    """Limit torch/numba threads for a task run in the calling process, then restore them."""
    if threads is None:
        yield
        return
    import numba
    import torch

    before = (torch.get_num_threads(), numba.get_num_threads())
    torch.set_num_threads(threads)
    numba.set_num_threads(max(1, min(threads, before[1])))
    try:
        yield
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])


def _call(fn: Callable[[Any], Any], index: int, task: Any, threads: int | None) -> Any:
    """Run one task; exceptions become a :class:`TaskFailure` (picklable). ``threads`` limits (and
    afterwards restores) this process's pools; workers are limited once, by their initializer."""
    try:
        with _threads_in_this_process(threads):
            return fn(task)
    except Exception as e:
        return TaskFailure(index, task, f"{type(e).__name__}: {e}", traceback.format_exc())


def exit_with_parent(parent: int) -> None:
    """End this process when ``parent`` (the process that started it) dies: ``PR_SET_PDEATHSIG`` on
    Linux, elsewhere a daemon thread that checks ``os.getppid()`` every second."""
    if sys.platform.startswith("linux"):
        import ctypes

        pr_set_pdeathsig = 1
        try:
            ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):
            pass
        else:
            if os.getppid() != parent:  # the parent died before prctl took effect
                os._exit(1)
            return

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="msmem-parent-watch", daemon=True).start()


def _worker_init(threads: int | None, parent: int | None = None) -> None:
    import warnings

    from msmem_core.plugins.manager import show_warning
    from msmem_core.util.malloc import keep_large_allocations

    if parent is not None:
        exit_with_parent(parent)
    warnings.showwarning = show_warning  # plugin warnings once per worker, not once per task
    configure_threads()  # before a task imports torch or numba (also inherited from the parent, if it called it)
    keep_large_allocations()
    if threads is not None:  # before any task imports numba/torch, so the env vars take effect too
        limit_threads(threads)


def _dead_worker(index: int, task: Any, error: BaseException) -> TaskFailure:
    return TaskFailure(index, task, f"worker process died while running this task (killed, e.g. by the "
                       f"out-of-memory killer, or crashed in native code): {type(error).__name__}: {error}",
                       "".join(traceback.format_exception(error)), worker_died=True)


WorkerDeath = Callable[[list[int]], None]
"""Told the indices of the tasks in flight when a local worker died, before they are rerun one at a time."""


def _iter_local(
    fn: Callable[[Any], Any], tasks: Sequence[Any], workers: int, threads: int | None,
    on_worker_death: WorkerDeath | None = None,
) -> Iterator[tuple[int, Any]]:
    if workers <= 1:
        for i, t in enumerate(tasks):
            yield i, _call(fn, i, t, threads)
        return
    queue = list(range(len(tasks)))[::-1]  # popped from the end: task order
    suspects: list[int] = []  # in flight when a worker died: rerun alone, to find which task killed it
    while queue or suspects:
        solo = bool(suspects)
        source, limit = (suspects, 1) if solo else (queue, workers)
        pool = ProcessPoolExecutor(max_workers=limit, mp_context=get_context("spawn"),
                                   initializer=_worker_init, initargs=(threads, os.getpid()))
        try:
            pending: dict[Future[Any], int] = {}
            broken = False
            while (source or pending) and not broken:
                while source and len(pending) < limit:  # a bounded number in flight: a dead worker costs few
                    i = source.pop()
                    try:
                        pending[pool.submit(_call, fn, i, tasks[i], None)] = i
                    except BrokenProcessPool:  # a worker died since the last wait: this task never ran
                        source.append(i)
                        broken = True
                        break
                if not broken:
                    done, _ = wait(pending, return_when=FIRST_COMPLETED)
                    broken = any(isinstance(f.exception(), BrokenProcessPool) for f in done)
                if broken:
                    done = set(wait(pending).done)  # the pool is broken: every future ends now
                    lost = sorted(pending[f] for f in done if isinstance(f.exception(), BrokenProcessPool))
                    if lost and not solo and on_worker_death is not None:
                        on_worker_death(lost)
                for fut in done:
                    i = pending.pop(fut)
                    err = fut.exception()
                    if isinstance(err, BrokenProcessPool):
                        if solo:
                            yield i, _dead_worker(i, tasks[i], err)
                        else:
                            suspects.insert(0, i)
                        continue
                    yield i, fut.result()
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


RAY_RETRIES = 1  # Ray reruns a task whose worker died this often (e.g. memory freed since); then it fails


def _iter_ray(
    fn: Callable[[Any], Any], tasks: Sequence[Any], workers: int, threads: int | None
) -> Iterator[tuple[int, Any]]:
    try:
        import ray
    except ImportError as e:
        raise UserError("executor 'ray' needs Ray: pip install 'msmem[ray]'") from e
    if not ray.is_initialized():
        os.environ.setdefault("RAY_AUTH_MODE", "disabled")  # local runs: no token written to $HOME
        if os.environ.get("RAY_ADDRESS"):
            ray.init(address=os.environ["RAY_ADDRESS"], log_to_driver=False)
        else:
            ray.init(num_cpus=workers, include_dashboard=False, log_to_driver=False)
    # Ray's workers may not share this process's environment (a cluster started elsewhere): pass the settings
    remote = ray.remote(num_cpus=1, max_retries=RAY_RETRIES, runtime_env={"env_vars": configure_threads()})(_call)
    queue = list(enumerate(tasks))[::-1]
    in_flight: dict[Any, int] = {}
    while queue or in_flight:
        while queue and len(in_flight) < max(1, workers):
            i, t = queue.pop()
            in_flight[remote.remote(fn, i, t, threads)] = i
        done, _ = ray.wait(list(in_flight), num_returns=1)
        for ref in done:
            i = in_flight.pop(ref)
            try:
                yield i, ray.get(ref)
            except ray.exceptions.RayError as e:  # the worker died (and its retry too), or Ray lost the task
                yield i, _dead_worker(i, tasks[i], e)


def iter_tasks(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    executor: str = "local",
    workers: int | None = None,
    threads: int | None = 1,
    on_worker_death: WorkerDeath | None = None,
) -> Iterator[tuple[int, Any]]:
    """``(task index, result or TaskFailure)`` in completion order. ``workers`` defaults to the CPU
    count; ``threads`` (per task; None leaves the pools alone) defaults to 1. ``on_worker_death``: see
    :func:`run_tasks`."""
    if executor not in EXECUTORS:
        raise UserError(f"unknown executor {executor!r}; choose one of: {', '.join(EXECUTORS)}")
    n = check_workers(workers) if workers is not None else os.cpu_count() or 1
    if executor == "ray":
        return _iter_ray(fn, tasks, n, threads)
    return _iter_local(fn, tasks, min(n, max(1, len(tasks))), threads, on_worker_death)


def check_workers(workers: int, flag: str = "--workers") -> int:
    """``workers``, or a one-line ``UserError`` naming ``flag`` if it is below 1."""
    if workers < 1:
        raise UserError(f"{flag} must be >= 1, got {workers}")
    return workers


def run_tasks(
    fn: Callable[[Any], Any],
    tasks: Sequence[Any],
    executor: str = "local",
    workers: int | None = None,
    progress: bool = True,
    threads: int | None = 1,
    description: str = "tasks",
    on_error: Literal["collect", "raise"] = "collect",
    on_result: Callable[[int, Any], None] | None = None,
    on_worker_death: WorkerDeath | None = None,
) -> list[Any]:
    """Run ``fn`` over ``tasks``; results (or :class:`TaskFailure` records) in task order.

    ``progress`` shows a rich progress bar with the rate in tasks per minute; ``on_result(index,
    result)`` is called as each task finishes (e.g. to log). ``on_worker_death(indices)`` (local
    executor) is called when a worker process dies with the tasks then in flight, which are rerun one
    at a time; the one that kills its worker again comes back as a ``TaskFailure`` with ``worker_died``.
    """
    tasks = list(tasks)
    results: list[Any] = [None] * len(tasks)
    stream = iter_tasks(fn, tasks, executor, workers, threads, on_worker_death)
    bar = None
    if progress and tasks:
        bar = progress_bar("{task.description}", "{task.fields[rate]}")
        bar_id = bar.add_task(description, total=len(tasks), rate="")
    start = time.perf_counter()
    try:
        for done, (i, res) in enumerate(stream, 1):
            results[i] = res
            if on_result is not None:
                on_result(i, res)
            if bar is not None:
                rate = 60.0 * done / max(time.perf_counter() - start, 1e-9)
                bar.update(bar_id, advance=1, rate=f"{rate:.1f}/min")
            if on_error == "raise" and isinstance(res, TaskFailure):
                raise TaskError(res)
    finally:
        close = getattr(stream, "close", None)
        if close is not None:
            close()
        if bar is not None:
            bar.stop()
    return results
