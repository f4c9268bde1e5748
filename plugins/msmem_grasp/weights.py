"""Loading FE-vMF weights: a plain state dict (``torch.load(weights_only=True)``) checked against the
sha256 and the architecture recorded in its JSON sidecar (written by ``msmem train fe-vmf``).

The shipped weights are ``weights/fe_vmf.pt`` with ``weights/fe_vmf.json`` beside them; how they were
trained and what they score is in ``weights/MODEL_CARD.md``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from msmem_core.errors import UserError
from msmem_core.util import artifacts
from msmem_grasp.fevmf import FEVMF, FEVMFConfig, GraspPrediction
from msmem_grasp.fpp import SurfaceCloud

WEIGHTS_FORMAT = "msmem-fe-vmf"
"""The ``format`` of an FE-vMF weights sidecar (``msmem_grasp.learn.training`` writes it)."""
WEIGHTS_VERSION = 1
SHIPPED_WEIGHTS = Path(__file__).resolve().parent / "weights" / "fe_vmf.pt"


class WeightsError(UserError):
    """Weights that are missing, corrupt, or not the ones their sidecar describes."""


def read_sidecar(path: str | Path) -> dict[str, Any]:
    return artifacts.read_sidecar(path, WEIGHTS_FORMAT, "an FE-vMF", "the expected sha256 and the architecture",
                                  "msmem train fe-vmf", WeightsError)


def load_fe_vmf(path: str | Path | None = None, verify: bool = True) -> FEVMF:
    """FE-vMF with the weights at ``path`` (default: the shipped weights), in eval mode.

    The file's sha256 must equal the sidecar's (``verify=False`` skips the check, for experiments);
    any mismatch or unreadable file raises one :class:`WeightsError` naming the file and the hash it
    should have.
    """
    path = Path(path) if path is not None else SHIPPED_WEIGHTS
    if not path.exists():
        raise WeightsError(f"weights file {path} does not exist")
    meta = read_sidecar(path)
    model: FEVMF = artifacts.load_weights(path, meta, lambda m: FEVMF(FEVMFConfig.model_validate(m)), verify,
                                          "retrain with `msmem train fe-vmf`", WeightsError)
    return model


def predict_cloud(model: FEVMF, cloud: SurfaceCloud) -> GraspPrediction:
    """FE-vMF outputs for an FPP cloud (empty cloud -> empty prediction)."""
    with torch.no_grad():
        pts = torch.from_numpy(np.ascontiguousarray(cloud.points, dtype=np.float32))
        feats = torch.from_numpy(cloud.features()) if model.config.in_features else None
        return model(pts, feats).detach()
