"""One writer per output folder: an advisory lock (``fcntl.flock``) on a lock file.

``msmem bench`` and ``msmem datagen`` lock ``OUT/.msmem.lock`` inside their output folder; ``msmem run``,
whose folder is written elsewhere and renamed into place whole, locks ``.NAME.msmem.lock`` beside it
(:func:`run_lock_file`). The holder writes its pid, start time and command line into the file, so a
second writer is refused in one line naming them (:class:`FolderLocked`), or waits (``wait=True``:
the commands' ``--wait``).

The kernel releases a ``flock`` when its holder dies, however it dies (``kill -9`` included), so a lock
is never held by a dead process. A lock file that still names a process when it is taken was left by
a holder that died before removing it: it is taken over, with a note naming that process. A holder
that ends normally removes its lock file (a folder made only for the lock is removed as well).

Locks are re-entrant within a process: a command that locks its folder and then calls a library
function that locks the same folder (``msmem_core.learn.datagen.generate_shards``) holds it once.
"""

from __future__ import annotations

import fcntl
import os
import shlex
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

from msmem_core.errors import UserError

LOCK_NAME = ".msmem.lock"
"""The lock file inside a bench or datagen output folder."""
_held: dict[Path, int] = {}
"""Lock files this process holds (resolved path -> depth of re-entry)."""


class FolderLocked(UserError):
    """Another process is writing the folder (the message names its pid and command)."""


def run_lock_file(out: Path) -> Path:
    """The lock file of a ``msmem run`` folder: beside it, as the ``OUT.partial-XXXX`` folder the run is
    written into (the run folder itself is replaced whole when the run completes)."""
    return out.parent / f".{out.name}.msmem.lock"


def command_line() -> str:
    """This process's command line as a shell would show it (``msmem bench --out ...``)."""
    argv = list(sys.argv) or ["python"]
    argv[0] = Path(argv[0]).name or argv[0]
    return shlex.join(argv)


def holder(lock_file: Path) -> str:
    """Who a lock file names: ``process PID (COMMAND; since HH:MM:SS)``, or ``another process`` when it
    names none (it is being written, or was written by hand)."""
    for _ in range(20):  # the holder writes it right after taking the lock: give it a moment
        try:
            lines = lock_file.read_text().splitlines()
        except OSError:
            lines = []
        fields = dict(line.split("=", 1) for line in lines if "=" in line)
        if fields.get("pid", "").isdigit():
            since = ""
            if fields.get("since", "").replace(".", "", 1).isdigit():
                since = time.strftime("; since %H:%M:%S", time.localtime(float(fields["since"])))
            return f"process {fields['pid']} ({fields.get('command') or '?'}{since})"
        time.sleep(0.05)
    return "another process"


def _take(lock_file: Path, folder: Path, wait: bool, on_wait: Callable[[str], None]) -> tuple[int, bool]:
    """Open, lock and return the descriptor of ``lock_file`` (an existing one, or created), and whether its
    folder was created here (removed again, if empty, when the lock is not taken). Retries when the file
    it locked was removed meanwhile (its holder released it, and removed the folder if it had made it
    and left it empty)."""
    made = False
    try:
        for attempt in range(100):
            if not lock_file.parent.exists():
                lock_file.parent.mkdir(parents=True, exist_ok=True)
                made = True
            try:
                fd = os.open(lock_file, os.O_RDWR | os.O_CREAT, 0o644)
            except FileNotFoundError:  # the folder was removed between the check and the open
                continue
            try:
                if _lock(fd, lock_file, folder, wait, on_wait if attempt == 0 else lambda _: None):
                    return fd, made
            except BaseException:
                os.close(fd)
                raise
            os.close(fd)  # the holder removed the file while we waited on it: lock the new one
        raise OSError(f"{lock_file} keeps disappearing")
    except BaseException:
        _remove_if_made(lock_file.parent, made)
        raise


def _lock(fd: int, lock_file: Path, folder: Path, wait: bool, on_wait: Callable[[str], None]) -> bool:
    """Lock ``fd`` (waiting if ``wait``); whether ``lock_file`` still is the file locked."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        who = holder(lock_file)
        if not wait:
            raise FolderLocked(f"{folder} is being written by {who}; rerun when it has finished (or with --wait), "
                               "or use another --out") from None
        on_wait(f"waiting for {who} to finish writing {folder} (lock {lock_file})")
        fcntl.flock(fd, fcntl.LOCK_EX)
    try:
        return os.fstat(fd).st_ino == os.stat(lock_file).st_ino
    except FileNotFoundError:
        return False


@contextmanager
def folder_lock(folder: Path, lock_file: Path | None = None, wait: bool = False,
                log: Callable[[str], None] | None = None) -> Iterator[Path]:
    """Hold the lock of ``folder`` (``folder / LOCK_NAME`` unless ``lock_file`` is given) while the block
    runs; yields the lock file. The folder of the lock file is created if needed, and removed on exit if
    it was made here and is empty then.

    A lock held by another process raises :class:`FolderLocked` naming its pid and command, or with
    ``wait`` blocks until it is released (``log`` is told once that it waits). An ``OSError`` (the
    folder cannot be created, a path below a file) propagates, for the caller to name its folder."""
    say = log or (lambda m: print(f"msmem: {m}", file=sys.stderr))
    path = Path(lock_file) if lock_file is not None else Path(folder) / LOCK_NAME
    key = path.parent.resolve() / path.name
    if key in _held:  # re-entered in this process
        _held[key] += 1
        try:
            yield path
        finally:
            _held[key] -= 1
        return
    fd, made = _take(path, Path(folder), wait, say)
    try:
        left = os.read(fd, 4096).decode(errors="replace")
        if "pid=" in left:  # its holder died without removing it (the kernel released its flock)
            say(f"taking over the lock {path} left by {holder(path)}, which is no longer running")
        record = f"pid={os.getpid()}\nsince={time.time():.0f}\ncommand={command_line()}\n".encode()
        os.lseek(fd, 0, os.SEEK_SET)
        os.ftruncate(fd, 0)
        os.write(fd, record)
        _held[key] = 1
        yield path
    finally:
        _held.pop(key, None)
        try:
            path.unlink()  # before unlocking: a waiter then finds the file gone and locks a new one
        except FileNotFoundError:
            pass
        os.close(fd)
        _remove_if_made(path.parent, made)


def _remove_if_made(folder: Path, made: bool) -> None:
    if made:
        try:
            folder.rmdir()
        except OSError:  # not empty: something was written
            pass
