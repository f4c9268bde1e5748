"""The run folder's files: write and read belief snapshots and ground truth, and read a whole run folder.

The runner writes ``belief_step{N}.npz`` (``save_snapshot``: float16 belief and ground truth after a
step) and ``gt_final.npz`` (``save_ground_truth``); ``load_run`` reads a run folder (``config.json``,
``scene.json``, ``steps.jsonl``, ``metrics.json``, the snapshots, ``belief_final.npz`` and
``gt_final.npz``) into a :class:`RunData` for the report (``msmem_core.run.report``) or your own analysis.

``msmem run`` writes a run folder atomically: into a temporary sibling (``stage_run_dir``, named
``OUT.partial-XXXX``) that ``commit_run_dir`` renames into place once the run and its report are
complete, so ``--out`` holds one whole run or nothing new. An interrupted or failed run leaves the
partial folder where the error message says.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import UserError
from msmem_core.map.belief import EvidentialMap
from msmem_core.run.failures import one_line
from msmem_core.util.jsonable import nan_from_null
from msmem_core.world.grid import GridSpec

if TYPE_CHECKING:
    from msmem_core.config import RunConfig
    from msmem_core.world.scene import SceneSpec


def stage_run_dir(out: Path, overwrite: bool = False) -> Path:
    """Check ``out`` (not a file; empty or absent unless ``overwrite``; its parent writable) and create
    the temporary sibling folder the run writes into. ``UserError`` naming the path otherwise."""
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise UserError(f"--out {out} is a file, not a folder")
        if any(out.iterdir()) and not overwrite:
            raise UserError(f"--out {out} exists and is not empty; give --overwrite to replace it whole, "
                            "or another --out")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=f"{out.name}.partial-", dir=out.parent))
    except OSError as e:
        raise UserError(f"cannot write the run folder {out}: {e.strerror or e}"
                        + (f": {e.filename}" if e.filename else "")) from e


class OutputError(UserError):
    """A file of the run folder could not be written (a full disk, a quota): the message names the file
    and the partial run folder."""


@contextmanager
def writing(path: Path, partial: Path | None = None) -> Iterator[None]:
    """Run the block that writes ``path``; an ``OSError`` in it becomes an :class:`OutputError` naming
    the file (the error's own, else ``path``) and the ``partial`` run folder (a full disk's error names
    neither: a write to an open file has no file name)."""
    try:
        yield
    except OSError as e:
        where = f"; partial run in {partial}" if partial is not None else ""
        raise OutputError(f"cannot write {e.filename or path}: {e.strerror or one_line(e)}{where}") from e


def commit_run_dir(staged: Path, out: Path) -> None:
    """Rename the complete ``staged`` folder to ``out``; an existing ``out`` is replaced whole."""
    old = None
    if out.exists():
        old = out.with_name(f"{out.name}.old-{os.getpid()}")
        os.replace(out, old)
    os.replace(staged, out)
    if old is not None:
        shutil.rmtree(old)


def save_snapshot(
    path: str | Path, belief: EvidentialMap, gt_occ: NDArray[np.bool_], gt_cls: NDArray[np.integer]
) -> None:
    """Belief (float16 evidence, readable by ``EvidentialMap.load``) and ground truth after one step.
    Evidence above float16's largest value (65504, reached by ``cnabu-observe`` over long episodes) is
    stored as that value: the expected probabilities it implies differ by less than 1e-4."""
    def half(x: NDArray[np.floating]) -> NDArray[np.float16]:
        return np.minimum(x, np.finfo(np.float16).max).astype(np.float16)

    np.savez_compressed(
        path, grid=np.array(belief.grid.model_dump_json()), alpha=half(belief.alpha),
        beta=half(belief.beta), eta=half(belief.eta),
        gt_occ=np.asarray(gt_occ, dtype=bool), gt_cls=np.asarray(gt_cls, dtype=np.int8),
    )


def save_ground_truth(path: str | Path, grid: GridSpec, occ: NDArray[np.bool_], cls: NDArray[np.integer]) -> None:
    """Ground-truth occupancy (bool) and class id (int8, 0 = free) per voxel."""
    np.savez_compressed(path, grid=np.array(grid.model_dump_json()), occupancy=np.asarray(occ, dtype=bool),
                        classes=np.asarray(cls, dtype=np.int8))


def load_ground_truth(path: str | Path) -> tuple[GridSpec, NDArray[np.bool_], NDArray[np.int8]]:
    with np.load(path) as f:
        return GridSpec.model_validate(json.loads(str(f["grid"]))), f["occupancy"], f["classes"]


@dataclass
class Snapshot:
    """The belief and ground truth after one step."""

    step: int
    belief: EvidentialMap
    gt_occ: NDArray[np.bool_]
    gt_cls: NDArray[np.integer]
    label: str = ""


@dataclass
class RunData:
    """A run folder, read."""

    run_dir: Path
    config: RunConfig
    scene: SceneSpec
    steps: list[dict[str, Any]]
    metrics: dict[str, Any]
    snapshots: list[Snapshot] = field(default_factory=list)

    @property
    def final(self) -> Snapshot:
        return self.snapshots[-1]


def load_run(run_dir: str | Path) -> RunData:
    """Read a run folder; a missing snapshot falls back to the final belief and ground truth."""
    from msmem_core.config import RunConfig
    from msmem_core.world.scene import SceneSpec

    d = Path(run_dir)
    for name in ("config.json", "scene.json", "steps.jsonl", "belief_final.npz"):
        if not (d / name).is_file():
            raise UserError(f"{d} is not a complete run folder: {name} is missing")
    config = RunConfig.model_validate_json((d / "config.json").read_text())
    scene = SceneSpec.from_json(d / "scene.json")
    steps = [json.loads(line) for line in (d / "steps.jsonl").read_text().splitlines() if line.strip()]
    for rec in steps:  # metrics written as null (non-finite) back to NaN
        rec["metrics"] = nan_from_null(rec.get("metrics", {}))
    metrics = json.loads((d / "metrics.json").read_text()) if (d / "metrics.json").is_file() else {}
    metrics = nan_from_null(metrics) | ({"initial": nan_from_null(metrics["initial"])} if "initial" in metrics else {})
    snaps: list[Snapshot] = []
    for p in sorted(d.glob("belief_step*.npz"), key=lambda q: int(q.stem.removeprefix("belief_step"))):
        step = int(p.stem.removeprefix("belief_step"))
        with np.load(p) as f:
            gt_occ, gt_cls = f["gt_occ"], f["gt_cls"]
        snaps.append(Snapshot(step, EvidentialMap.load(p), gt_occ, gt_cls, f"after step {step}"))
    last = len(steps) - 1
    if problems := _mixed(config, scene, steps, metrics, snaps):
        raise UserError(f"{d} mixes files of different runs ({'; '.join(problems)}); rerun into it with "
                        "--overwrite, or into an empty --out")
    if not snaps or snaps[-1].step != last:
        final = EvidentialMap.load(d / "belief_final.npz")
        if (d / "gt_final.npz").is_file():
            _, occ, cls = load_ground_truth(d / "gt_final.npz")
        else:
            occ, cls = np.zeros(final.grid.shape, bool), np.zeros(final.grid.shape, np.int8)
        snaps.append(Snapshot(last, final, occ, cls, f"final (after step {last})"))
    return RunData(d, config, scene, steps, metrics, snaps)


def _mixed(config: RunConfig, scene: SceneSpec, steps: list[dict[str, Any]], metrics: dict[str, Any],
           snaps: list[Snapshot]) -> list[str]:
    """What shows that a run folder's files come from more than one run (empty if nothing does):
    metrics.json's step count, scene, method or final metrics disagree with steps.jsonl, scene.json or
    config.json, or a snapshot is of a step the steps file does not hold."""
    problems = []
    if metrics:
        if metrics.get("steps", len(steps)) != len(steps):
            problems.append(f"metrics.json counts {metrics['steps']} steps, steps.jsonl holds {len(steps)}")
        if metrics.get("scene", scene.name) != scene.name:
            problems.append(f"metrics.json is of scene {metrics['scene']!r}, scene.json of {scene.name!r}")
        if metrics.get("method", config.method) != config.method:
            problems.append(f"metrics.json is of method {metrics['method']!r}, config.json of {config.method!r}")
        if steps:
            last = steps[-1].get("metrics", {})
            differ = sorted(k for k, v in last.items() if isinstance(v, (int, float)) and k in metrics
                            and not (v == metrics[k] or (v != v and metrics[k] != metrics[k])))
            if differ:
                problems.append(f"metrics.json's final {', '.join(differ[:3])} differ from the last step's")
    late = [s.step for s in snaps if s.step >= len(steps)]
    if late:
        problems.append(f"belief_step{late[0]}.npz is of a step steps.jsonl does not hold ({len(steps)} steps)")
    return problems
