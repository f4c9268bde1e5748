"""Loading CNABU weights: a plain state dict (``torch.load(weights_only=True)``) checked against the
sha256, the kind and the architecture recorded in its JSON sidecar (written by ``msmem train cnabu``;
the whole-map network's, ``load_map_net``, by ``msmem train cnabu-map``). Nothing of training.

Shipped weights live in ``msmem_cnabu/weights/cnabu_<kind>.pt`` with ``cnabu_<kind>.json`` beside them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from msmem_cnabu.mapnet import MapNet, MapNetConfig
from msmem_cnabu.network import KINDS, CNABUNet, CNABUNetConfig
from msmem_core.errors import UserError
from msmem_core.util import artifacts

WEIGHTS_FORMAT = "msmem-cnabu"
"""The ``format`` of a CNABU weights sidecar (``msmem_cnabu.learn.training`` writes it)."""
WEIGHTS_VERSION = 1
MAP_WEIGHTS_FORMAT = "msmem-cnabu-map"
"""The ``format`` of a ``cnabu-map`` weights sidecar (``msmem_cnabu.learn.maptrain`` writes it)."""
MAP_WEIGHTS_VERSION = 1
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


class WeightsError(UserError):
    """Weights that are missing, corrupt, of another kind, or not the ones their sidecar describes."""


def shipped_weights(kind: str) -> Path:
    """Where the shipped weights of ``kind`` live (they may not exist yet)."""
    if kind not in KINDS:
        raise ValueError(f"unknown CNABU kind {kind!r}; kinds: {', '.join(KINDS)}")
    return WEIGHTS_DIR / f"cnabu_{kind}.pt"


def resolve_weights(path: str | Path) -> Path:
    """``path`` as given, except that a relative ``msmem_cnabu/weights/NAME`` that does not exist from the
    working directory names the shipped folder (so a config file can pick shipped weights by name). A
    shipped name resolves only inside that folder: one that leads out (``..``, a symlink) is refused."""
    p = Path(path)
    if not p.is_absolute() and not p.exists() and p.parts[:2] == ("msmem_cnabu", "weights"):
        shipped = WEIGHTS_DIR.joinpath(*p.parts[2:])
        real, folder = shipped.resolve(), WEIGHTS_DIR.resolve()
        if not real.is_relative_to(folder) or real == folder:
            raise WeightsError(f"weights {str(path)!r}: a shipped weights name must name a file inside the shipped "
                               f"folder {folder}, this one leads to {real}")
        return shipped
    return p


def how_to_make(kind: str, path: Path) -> str:
    return (f"generate data with `msmem datagen cnabu --kind {kind} --scenes N --out DATA` and train them with "
            f"`msmem train cnabu --kind {kind} --data DATA --out {path}`")


def read_sidecar(path: str | Path, kind: str | None = None) -> dict[str, Any]:
    meta = artifacts.read_sidecar(path, WEIGHTS_FORMAT, "a CNABU", "the expected sha256, the kind and the architecture",
                                  "msmem train cnabu", WeightsError)
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
    path = resolve_weights(path) if path is not None else shipped_weights(kind)
    if not path.exists():
        raise WeightsError(f"cnabu-{kind}: weights file {path} does not exist; {how_to_make(kind, path)} "
                           "(or name another file in the model's `weights` parameter)")
    meta = read_sidecar(path, kind)
    model: CNABUNet = artifacts.load_weights(path, meta, lambda m: CNABUNet(CNABUNetConfig.model_validate(m)), verify,
                                             how_to_make(kind, path), WeightsError)
    return model, meta


def load_map_net(path: str | Path, verify: bool = True) -> tuple[MapNet, dict[str, Any]]:
    """(network in eval mode, sidecar) of map weights (``torch.load(weights_only=True)``)."""
    path = Path(path)
    remedy = ("make them with `msmem datagen cnabu --kind observe --min-views 0 --max-views 0 --samples 12 ...` and "
              "`msmem train cnabu-map`")
    if not path.exists():
        raise WeightsError(f"cnabu-map: weights file {path} does not exist; {remedy}")
    meta = artifacts.read_sidecar(path, MAP_WEIGHTS_FORMAT, "a cnabu-map", "the sha256 and the architecture",
                                  "msmem train cnabu-map", WeightsError)
    net: MapNet = artifacts.load_weights(path, meta, lambda m: MapNet(MapNetConfig.model_validate(m)), verify,
                                         remedy, WeightsError)
    return net, meta
