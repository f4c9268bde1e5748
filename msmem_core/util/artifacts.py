"""Files of learned models: content hashes, the JSON sidecar beside a weights file, atomic writes, and
loading weights checked against their sidecar.

Shared by every plugin that trains and ships weights (FE-vMF, CNABU), so the hash a model card
quotes and the one a loader checks are computed one way; ``msmem_core.learn.datagen`` writes its shards
and manifests atomically the same way.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any


def cache_root(name: str) -> Path:
    """``$MSMEM_CACHE_DIR/<name>``, by default ``~/.cache/msmem/<name>``: where msmem caches derived
    files (antipodal grasps, mesh decompositions, ...)."""
    root = os.environ.get("MSMEM_CACHE_DIR")
    return (Path(root) if root else Path.home() / ".cache" / "msmem") / name


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


def tmp_path(path: Path) -> Path:
    """The temporary file an atomic write of ``path`` goes through (same folder, hidden, per process)."""
    return path.with_name(f".{path.name}.{os.getpid()}.tmp")


def atomic_save(obj: Any, path: Path) -> None:
    """``torch.save`` to a temporary file, then rename: a reader never sees a half-written file."""
    import torch

    tmp = tmp_path(path)
    torch.save(obj, tmp)
    os.replace(tmp, path)


def atomic_text(text: str, path: Path) -> None:
    """Write text to a temporary file, then rename."""
    tmp = tmp_path(path)
    tmp.write_text(text)
    os.replace(tmp, path)


def write_sidecar(weights: Path, head: dict[str, Any], tail: dict[str, Any]) -> dict[str, Any]:
    """Write the JSON sidecar of a weights file and return it: ``head`` (format, version, ...), the
    file's name, sha256 and size, then ``tail`` (architecture, training record, ...)."""
    side = {**head, "weights": weights.name, "sha256": sha256_file(weights), "bytes": weights.stat().st_size, **tail}
    atomic_text(json.dumps(side, indent=1, default=float), sidecar_path(weights))
    return side


def read_sidecar(
    weights: str | Path, fmt: str, what: str, records: str, command: str, error: Callable[[str], Exception]
) -> dict[str, Any]:
    """The sidecar of a weights file, checked to be a ``fmt`` sidecar (``what``, e.g. "an FE-vMF") with
    the weights' sha256 and architecture (``model``). Problems raise ``error(message)``; the message
    of a missing sidecar says what it ``records`` and that ``command`` writes one."""
    side = sidecar_path(weights)
    if not side.exists():
        raise error(f"{weights}: no sidecar {side.name} beside the weights (it records {records}); weights written "
                    f"by `{command}` come with one")
    try:
        meta: dict[str, Any] = json.loads(side.read_text())
    except (OSError, ValueError) as e:
        raise error(f"{side}: unreadable sidecar ({e})") from e
    if meta.get("format") != fmt or "sha256" not in meta or "model" not in meta:
        raise error(f"{side}: not {what} weights sidecar (format {meta.get('format')!r})")
    return meta


def non_finite_tensor(state: Any) -> str | None:
    """The name of the first floating-point tensor of a state dict holding a NaN or an infinity, with
    how many of its values do, or None when every tensor is finite."""
    import torch

    items = state.items() if isinstance(state, dict) else ()
    for name, t in items:
        if isinstance(t, torch.Tensor) and (t.is_floating_point() or t.is_complex()):
            bad = int((~torch.isfinite(t)).sum())
            if bad:
                return f"{name} ({bad} of {t.numel()} values)"
    return None


def load_state(weights: Path, error: Callable[[str], Exception], what: str = "weights") -> Any:
    """A state dict read with ``torch.load(weights_only=True)`` (no code runs), every tensor finite;
    problems raise ``error(message)`` naming the file."""
    import pickle
    import warnings

    import torch

    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols before it refuses: the line below says it
            warnings.simplefilter("ignore", UserWarning)
            state = torch.load(weights, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:
        raise error(f"{weights}: not readable as {what}: not a plain state dict (the safe loader, weights_only, "
                    "refused it: a corrupt file, or one holding code or objects that are not tensors)") from e
    except Exception as e:  # truncated files, not a torch file at all
        first = (str(e).strip().splitlines() or [""])[0]
        raise error(f"{weights}: not readable as {what} ({type(e).__name__}: {first})") from e
    bad = non_finite_tensor(state)
    if bad:
        raise error(f"{weights}: {what} with values that are not finite (NaN or infinite) in tensor {bad}")
    return state


def load_weights(
    weights: Path, meta: dict[str, Any], build: Callable[[dict[str, Any]], Any], verify: bool, remedy: str,
    error: Callable[[str], Exception],
) -> Any:
    """``build(meta["model"])`` (a torch module) with the state dict at ``weights``, in eval mode.

    With ``verify`` the file's sha256 must equal the sidecar's. A mismatch, an unreadable file,
    tensors that are not finite or that do not fit raise ``error(message)`` naming the file (and the
    hash it should have); a mismatch's message ends with what to do: "... Restore the file (reinstall
    msmem / git checkout) or " + ``remedy``.
    """
    expected = meta["sha256"]
    hint = (f"{weights}: weights are corrupt or not the ones described by {sidecar_path(weights).name}: expected"
            f" sha256 {expected}")
    if verify:
        actual = sha256_file(weights)
        if actual != expected:
            raise error(f"{hint}, got {actual}. Restore the file (reinstall msmem / git checkout) or {remedy}")
    state = load_state(weights, error)
    try:
        model = build(meta["model"])
        model.load_state_dict(state)
    except Exception as e:  # missing/unexpected keys, shape mismatches, an architecture the sidecar cannot build
        raise error(f"{hint}; loading failed with {type(e).__name__}: {e}") from e
    return model.eval()
