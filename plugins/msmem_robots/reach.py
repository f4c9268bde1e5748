"""Reachable views, computed once per (robot, shelf, viewpoint set): in memory for the process and, when
asked, on disk in ``$MSMEM_CACHE_DIR/reach`` (``~/.cache/msmem/reach``), keyed by a hash of everything
the answer depends on."""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.util.artifacts import cache_root, tmp_path
from msmem_core.world.scene import ShelfSpec

CACHE_VERSION = 1
"""Bump when the way reachability is computed changes: older cache files are then ignored."""
_MEMO: dict[str, NDArray[np.bool_]] = {}
_MEMO_MAX = 64


@dataclass(frozen=True)
class ReachInfo:
    """Where the last answer came from (``memory``, ``disk`` or ``computed``) and how long it took."""

    source: str
    seconds: float
    key: str


def reach_key(robot: dict[str, Any], viewpoints: NDArray[np.float64], shelf: ShelfSpec) -> str:
    """Hash of the robot's identity (its config, URDF content, library version), the shelf and the views."""
    views = hashlib.sha256(np.ascontiguousarray(viewpoints, dtype=np.float64).tobytes()).hexdigest()
    blob = json.dumps({"v": CACHE_VERSION, "robot": robot, "shelf": shelf.model_dump(mode="json"), "views": views},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def cache_dir() -> Path:
    """``$MSMEM_CACHE_DIR/reach`` or ``~/.cache/msmem/reach``."""
    return cache_root("reach")


def cached_reach(key: str, name: str, compute: Callable[[], NDArray[np.bool_]],
                 disk: bool = True) -> tuple[NDArray[np.bool_], ReachInfo]:
    """The mask for ``key``: from memory, else from the disk cache (``disk``), else ``compute()``d and kept."""
    t0 = time.perf_counter()
    if key in _MEMO:
        return _MEMO[key].copy(), ReachInfo("memory", time.perf_counter() - t0, key)
    path = cache_dir() / f"{name}-{key}.npy"
    mask: NDArray[np.bool_] | None = None
    source = "disk"
    if disk and path.is_file():
        try:
            loaded = np.load(path, allow_pickle=False)
            mask = loaded.astype(bool) if loaded.ndim == 1 else None
        except (OSError, ValueError):
            mask = None  # a damaged file is recomputed and replaced
    if mask is None:
        source = "computed"
        mask = np.asarray(compute(), dtype=bool)
        if disk:
            try:
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = tmp_path(path)
                with open(tmp, "wb") as fh:
                    np.save(fh, mask)
                os.replace(tmp, path)
            except OSError:
                pass  # a read-only cache folder costs time, not correctness
    if len(_MEMO) >= _MEMO_MAX:
        _MEMO.pop(next(iter(_MEMO)))
    _MEMO[key] = mask
    return mask.copy(), ReachInfo(source, time.perf_counter() - t0, key)


def clear_memory() -> None:
    """Forget the in-memory answers (tests; the disk cache stays)."""
    _MEMO.clear()
