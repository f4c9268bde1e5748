"""Sharded training-data generation, shared by the plugins that train networks (FE-vMF, CNABU).

A data folder holds one compressed ``scene_<seed>.npz`` shard per scene seed, each written atomically
(a temporary file, then a rename), and a ``dataset.json`` manifest. :func:`generate_shards` makes the
shards of a list of seeds in parallel (``msmem_core.run.executors``); a rerun skips the shards that exist
and pass the plugin's check and regenerates corrupt ones, so a killed run resumes. The plugin
supplies what a shard holds: the task function that makes and writes one, and the check. Every
shard has a ``version`` array.
"""

from __future__ import annotations

import json
import time
import zipfile
import zlib
from collections.abc import Callable, Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from msmem_core.errors import UserError
from msmem_core.plugins.manager import ComponentRef
from msmem_core.util.artifacts import atomic_text, tmp_path

SHARD_GLOB = "scene_*.npz"
MANIFEST = "dataset.json"


class ShardError(UserError):
    """A shard file is missing fields, has inconsistent shapes or cannot be read (the message names it)."""


@dataclass(frozen=True)
class ShardTask:
    """One unit of work for the executor (picklable)."""

    seed: int
    out: str
    config_json: str


@dataclass
class DatagenSummary:
    generated: list[dict[str, Any]]
    skipped: list[int]
    corrupt: list[str]
    failed: list[str]
    seconds: float

    @property
    def scenes_per_min(self) -> float:
        return 60.0 * len(self.generated) / max(self.seconds, 1e-9)

    def headline(self) -> str:
        """``generated N, skipped M (already done)``, and how many corrupt shards were regenerated."""
        line = f"generated {len(self.generated)}, skipped {len(self.skipped)} (already done)"
        if self.corrupt:
            line += f", regenerated {len(self.corrupt)} corrupt"
        return line

    def raise_if_failed(self) -> None:
        """A ``UserError`` if any scene failed (their errors were logged)."""
        if self.failed:
            raise UserError(f"{len(self.failed)} scene(s) failed (see above); rerun the same command to retry them")


def seed_range(scenes: int, seed: int) -> list[int]:
    """The scene seeds of a ``msmem datagen`` command: ``scenes`` of them from ``seed`` (both checked)."""
    if scenes < 1:
        raise UserError(f"--scenes must be >= 1, got {scenes}")
    if seed < 0:
        raise UserError(f"--seed must be >= 0, got {seed}")
    return list(range(seed, seed + scenes))


def shard_path(out_dir: str | Path, seed: int) -> Path:
    return Path(out_dir) / f"scene_{seed:06d}.npz"


def list_shards(data_dir: str | Path, how: str) -> list[Path]:
    """The shards of a data folder, sorted; a missing or empty folder is a clear error that says
    ``how`` to make them (a command)."""
    d = Path(data_dir)
    if not d.is_dir():
        raise UserError(f"data folder {d} does not exist; create it with {how}")
    paths = sorted(d.glob(SHARD_GLOB))
    if not paths:
        raise UserError(f"no {SHARD_GLOB} shards in {d}; create them with {how}")
    return paths


def read_npz(path: Path, names: Sequence[str], what: str, fail: Callable[[str], ShardError]) -> dict[str, Any]:
    """Every array of a shard file. Raises ``fail(reason)`` when the file lacks one of ``names`` or
    ``version`` (it is "not a ``what`` shard") or cannot be read (a corrupt shard)."""
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as f:
            missing = [k for k in [*names, "version"] if k not in f.files]
            if missing:
                raise fail(f"not a {what} shard (missing {', '.join(missing)})")
            return {k: f[k] for k in f.files}
    except ShardError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, KeyError) as e:
        raise fail(f"corrupt shard ({type(e).__name__}: {e})") from e


def save_npz(path: str | Path, arrays: dict[str, Any]) -> None:
    """Write a compressed ``.npz`` atomically: a temporary file in the same folder, then rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = tmp_path(path)
    with open(tmp, "wb") as fh:
        np.savez_compressed(fh, **arrays)
    tmp.replace(path)


def read_manifest(data_dir: str | Path) -> dict[str, Any] | None:
    """The data folder's ``dataset.json``, None if it has none."""
    path = Path(data_dir) / MANIFEST
    return json.loads(path.read_text()) if path.exists() else None


def check_same_simulator(out_dir: str | Path, manifest: dict[str, Any] | None, simulator: ComponentRef) -> None:
    """Refuse to add shards simulated by another backend to a data folder. ``manifest`` is the folder's
    ``dataset.json`` (None: a new folder); one without a ``config.simulator`` was made in PyBullet,
    the only backend before ``--sim``."""
    if manifest is None:
        return
    have = {"params": {}, **manifest.get("config", {}).get("simulator", {"name": "pybullet"})}
    want = simulator.model_dump(mode="json")
    if have != want:
        def text(ref: dict[str, Any]) -> str:
            return repr(ref["name"]) + (f" (params {json.dumps(ref['params'])})" if ref["params"] else "")

        out = Path(out_dir)
        raise UserError(f"{out} holds data simulated in {text(have)} (see {out / MANIFEST}), not in {text(want)}; "
                        "use another --out")


@contextmanager
def data_folder_lock(out_dir: str | Path, wait: bool = False) -> Iterator[None]:
    """Hold the lock of a data folder (``OUT/.msmem.lock``, ``msmem_core.run.lock``): one writer per
    folder. Another process writing it is a one-line ``UserError`` naming it, or with ``wait`` is waited
    for; a folder that cannot be created is a ``UserError`` naming it. Re-entrant in a process."""
    from msmem_core.run.lock import FolderLocked, folder_lock

    with ExitStack() as held:
        try:
            held.enter_context(folder_lock(Path(out_dir), wait=wait))
        except FolderLocked:
            raise
        except OSError as e:
            raise UserError(f"cannot write data to {out_dir}: {e.strerror or e}") from e
        yield


def generate_shards(
    out_dir: str | Path,
    seeds: Sequence[int],
    task_fn: Callable[[ShardTask], dict[str, Any]],
    config_json: str,
    check: Callable[[Path], object],
    manifest: dict[str, Any],
    executor: str,
    workers: int,
    progress: bool,
    log: Callable[[str], None],
    description: str,
) -> DatagenSummary:
    """Make the shards of ``seeds`` in ``out_dir`` that are missing (or corrupt), in parallel.

    A shard that exists is kept if ``check(path)`` passes; a :class:`ShardError` from it is logged as
    a warning and the shard regenerated. ``manifest`` is written to ``dataset.json``, then
    ``task_fn(ShardTask(seed, out_dir, config_json))`` (a module-level function: it is pickled) makes
    and writes each missing shard on ``msmem_core.run.executors`` (one thread per task). Its results are
    ``generated``; the tasks that raised are logged and listed in ``failed``. The folder is locked
    meanwhile (:func:`data_folder_lock`): another process writing it is refused.
    """
    from msmem_core.run.executors import check_workers

    out = Path(out_dir)
    check_workers(workers)
    with data_folder_lock(out):  # one writer per folder (a command may hold it already: re-entrant)
        return _generate_shards(out, seeds, task_fn, config_json, check, manifest, executor, workers, progress, log,
                                description)


def _generate_shards(out: Path, seeds: Sequence[int], task_fn: Callable[[ShardTask], dict[str, Any]],
                     config_json: str, check: Callable[[Path], object], manifest: dict[str, Any], executor: str,
                     workers: int, progress: bool, log: Callable[[str], None], description: str) -> DatagenSummary:
    from msmem_core.run.executors import TaskFailure, run_tasks

    out.mkdir(parents=True, exist_ok=True)
    todo, skipped, corrupt = [], [], []
    for s in seeds:
        path = shard_path(out, s)
        if path.exists():
            try:
                check(path)
                skipped.append(int(s))
                continue
            except ShardError as e:
                corrupt.append(str(e))
                log(f"warning: {e}; regenerating it")
        todo.append(ShardTask(int(s), str(out), config_json))
    atomic_text(json.dumps(manifest, indent=1), out / MANIFEST)
    t0 = time.perf_counter()
    results = run_tasks(task_fn, todo, executor=executor, workers=workers, progress=progress, threads=1,
                        description=description)
    seconds = time.perf_counter() - t0
    failed = [f"seed {r.task.seed}: {r.error}" for r in results if isinstance(r, TaskFailure)]
    for f in failed:
        log(f"error: {f}")
    generated = [r for r in results if not isinstance(r, TaskFailure)]
    return DatagenSummary(generated, skipped, corrupt, failed, seconds)
