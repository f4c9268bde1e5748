"""Loading CNABU weights: a plain state dict (``torch.load(weights_only=True)``) checked against the
sha256, the kind and the architecture recorded in its JSON sidecar (written by ``msmem train cnabu``).

Shipped weights live in ``msmem_cnabu/weights/cnabu_<kind>.pt`` with ``cnabu_<kind>.json`` beside them.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from msmem_cnabu.network import KINDS, CNABUNet, CNABUNetConfig
from msmem_cnabu.training import WEIGHTS_FORMAT
from msmem_core.artifacts import sha256_file, sidecar_path
from msmem_core.errors import UserError

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


class WeightsError(UserError):
    """Weights that are missing, corrupt, of another kind, or not the ones their sidecar describes."""


def shipped_weights(kind: str) -> Path:
    """Where the shipped weights of ``kind`` live (they may not exist yet)."""
    if kind not in KINDS:
        raise ValueError(f"unknown CNABU kind {kind!r}; kinds: {', '.join(KINDS)}")
    return WEIGHTS_DIR / f"cnabu_{kind}.pt"


def how_to_make(kind: str, path: Path) -> str:
    return (f"generate data with `msmem datagen cnabu --kind {kind} --scenes N --out DATA` and train them with "
            f"`msmem train cnabu --kind {kind} --data DATA --out {path}`")


def read_sidecar(path: str | Path, kind: str | None = None) -> dict[str, Any]:
    side = sidecar_path(path)
    if not side.exists():
        raise WeightsError(f"{path}: no sidecar {side.name} beside the weights (it records the expected sha256, the "
                           "kind and the architecture); weights written by `msmem train cnabu` come with one")
    try:
        meta: dict[str, Any] = json.loads(side.read_text())
    except (OSError, ValueError) as e:
        raise WeightsError(f"{side}: unreadable sidecar ({e})") from e
    if meta.get("format") != WEIGHTS_FORMAT or "sha256" not in meta or "model" not in meta:
        raise WeightsError(f"{side}: not a CNABU weights sidecar (format {meta.get('format')!r})")
    if kind is not None and meta.get("kind") != kind:
        raise WeightsError(f"{path}: these are {meta.get('kind')!r} weights, a {kind!r} model needs its own; "
                           + how_to_make(kind, Path(path)))
    return meta


def load_cnabu(kind: str, path: str | Path | None = None, verify: bool = True) -> tuple[CNABUNet, dict[str, Any]]:
    """(network in eval mode, sidecar) of the ``kind`` weights at ``path`` (default: the shipped ones).

    A missing file names the commands that produce it; a sha256 that differs from the sidecar's or
    tensors that do not fit the recorded architecture raise one :class:`WeightsError` naming the
    file and the hash it should have (``verify=False`` skips the hash, for experiments).
    """
    path = Path(path) if path is not None else shipped_weights(kind)
    if not path.exists():
        raise WeightsError(f"cnabu-{kind}: weights file {path} does not exist; {how_to_make(kind, path)} "
                           "(or name another file in the model's `weights` parameter)")
    meta = read_sidecar(path, kind)
    expected = meta["sha256"]
    hint = (f"{path}: weights are corrupt or not the ones described by {sidecar_path(path).name}: expected"
            f" sha256 {expected}")
    if verify:
        actual = sha256_file(path)
        if actual != expected:
            raise WeightsError(f"{hint}, got {actual}. Restore the file (reinstall msmem / git checkout) or "
                               + how_to_make(kind, path))
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        model = CNABUNet(CNABUNetConfig.model_validate(meta["model"]))
        model.load_state_dict(state)
    except Exception as e:  # unpickling errors, missing/unexpected keys, shape mismatches
        raise WeightsError(f"{hint}; loading failed with {type(e).__name__}: {e}") from e
    return model.eval(), meta
