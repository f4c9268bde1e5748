"""Files of learned models: content hashes, the JSON sidecar beside a weights file, atomic writes.

Shared by every plugin that trains and ships weights (FE-vMF, CNABU), so the hash a model card
quotes and the one a loader checks are computed one way.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def sidecar_path(weights: str | Path) -> Path:
    """The JSON sidecar of a weights file: same name, ``.json``."""
    return Path(weights).with_suffix(".json")


def _tmp(path: Path) -> Path:
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def atomic_save(obj: Any, path: Path) -> None:
    """``torch.save`` to a temporary file, then rename: a reader never sees a half-written file."""
    import torch

    tmp = _tmp(path)
    torch.save(obj, tmp)
    os.replace(tmp, path)


def atomic_text(text: str, path: Path) -> None:
    """Write text to a temporary file, then rename."""
    tmp = _tmp(path)
    tmp.write_text(text)
    os.replace(tmp, path)
