"""The CNABU loss: evidential (digamma expected cross-entropy + annealed KL to the uniform Dirichlet /
Beta of the misleading evidence) on occupancy and semantics against the simulator's ground truth
after the action, plus a binary cross-entropy on the change map (push, grasp).

Per voxel (valid voxels only: the shelf's boards are excluded):

- occupancy: ``msmem_grasp.learn.losses.evidential_beta_loss`` (the FE-vMF affordance loss) on
  (alpha, beta) against GT occupancy;
- semantics: the Dirichlet version, E[-log q_y] = psi(S) - psi(eta_y) and
  KL(Dir(eta~) || Dir(1)) with eta~ = y + (1 - y) * eta (the true class's evidence reset to 1);
- change (push, grasp): BCE of the change logit against the GT change (occupancy or class differs
  before and after the action), dilated by ``change_dilate`` voxels; the evidential terms see the
  blended belief ``old * (1 - p) + pred * p`` with p detached, so the evidence head learns where
  the change head says the action acts, and the change head learns only from the GT change.

The KL weight grows linearly to ``kl_max`` over ``anneal_epochs``. Voxels are weighted
``1 + focus_weight`` where something is (GT occupied) or happens (GT change, the action's own
voxels), 1 elsewhere: most of a shelf is air the prior already gets right.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from msmem_grasp.learn.losses import beta_expected_ce, beta_kl_uniform, evidential_beta_loss
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor

__all__ = [
    "CNABULossConfig",
    "beta_expected_ce",
    "beta_kl_uniform",
    "blend",
    "cnabu_loss",
    "dirichlet_expected_ce",
    "dirichlet_kl_uniform",
    "evidential_dirichlet_loss",
]


class CNABULossConfig(BaseModel):
    """Weights of the CNABU loss terms and the KL annealing."""

    model_config = ConfigDict(extra="forbid")

    w_occupancy: float = Field(1.0, ge=0.0)
    w_semantic: float = Field(1.0, ge=0.0)
    w_change: float = Field(1.0, ge=0.0)
    change_pos_weight: float = Field(2.0, gt=0.0)
    """BCE weight of changed voxels (they are a few percent of the grid). With weight w the change
    head's p = 0.5 sits where the true change probability is 1 / (1 + w)."""
    focus_weight: float = Field(4.0, ge=0.0)
    """Extra weight of GT-occupied, changed and action voxels."""
    anneal_epochs: float = Field(5.0, gt=0.0)
    """KL weight kl_max * min(1, epoch / anneal_epochs)."""
    kl_max: float = Field(0.1, ge=0.0)
    """Final KL weight. On a tiny overfit run (one push scene, 150 steps, docs/explanation/cnabu.md) 1.0 made the
    semantic NLL of the affected region worse than "no change" (2.51 vs 2.43: the KL pulls the
    15-class evidence towards uniform), 0.1 better (1.79); the occupancy NLL was about the same."""


def dirichlet_expected_ce(eta: Tensor, y: Tensor) -> Tensor:
    """E_{q ~ Dir(eta)}[-log q_y] = psi(S) - psi(eta_y); ``eta`` [B, C, ...], ``y`` [B, ...] class ids."""
    return torch.digamma(eta.sum(1)) - torch.digamma(eta.gather(1, y[:, None].long())[:, 0])


def dirichlet_kl_uniform(eta: Tensor) -> Tensor:
    """KL(Dir(eta) || Dir(1, ..., 1)) over the class axis 1, computed in float64 and returned in
    ``eta``'s dtype (the terms are large and cancel; float32 loses them at large evidence)."""
    e = eta.double()
    s = e.sum(1)
    c = eta.shape[1]
    kl = (torch.lgamma(s) - torch.lgamma(e).sum(1) - torch.lgamma(torch.tensor(float(c), dtype=e.dtype))
          + ((e - 1.0) * (torch.digamma(e) - torch.digamma(s)[:, None])).sum(1))
    return kl.to(eta.dtype)


def evidential_dirichlet_loss(eta: Tensor, y: Tensor, kl_weight: float) -> tuple[Tensor, Tensor]:
    """(expected CE, KL of the misleading evidence) per voxel."""
    ce = dirichlet_expected_ce(eta, y)
    onehot = F.one_hot(y.long(), eta.shape[1]).movedim(-1, 1).to(eta.dtype)
    eta_t = onehot + (1.0 - onehot) * eta
    return ce, kl_weight * dirichlet_kl_uniform(eta_t)


def blend(old: Tensor, pred: Tensor, p: Tensor) -> Tensor:
    """old * (1 - p) + pred * p (docs/explanation/cnabu.md, "The networks"): stays >= 1 when both are."""
    return old * (1.0 - p) + pred * p


def cnabu_loss(
    alpha: Tensor, beta: Tensor, eta: Tensor, change_logit: Tensor | None,
    prior_alpha: Tensor, prior_beta: Tensor, prior_eta: Tensor,
    gt_occ: Tensor, gt_cls: Tensor, change: Tensor | None, valid: Tensor, focus: Tensor,
    epoch: float, config: CNABULossConfig | None = None,
) -> dict[str, Tensor]:
    """All terms (scalars) and their weighted sum under ``total``. Shapes: [B, X, Y, Z] (``eta``
    [B, C, X, Y, Z]); ``gt_occ``, ``change``, ``valid``, ``focus`` bool, ``gt_cls`` integer."""
    cfg = config or CNABULossConfig()
    kl_w = cfg.kl_max * min(1.0, epoch / cfg.anneal_epochs)
    if change_logit is not None:
        p = torch.sigmoid(change_logit).detach()
        alpha = blend(prior_alpha, alpha, p)
        beta = blend(prior_beta, beta, p)
        eta = blend(prior_eta, eta, p[:, None])
    w = valid.to(alpha.dtype) * (1.0 + cfg.focus_weight * focus.to(alpha.dtype))
    wsum = w.sum().clamp_min(1.0)
    y = gt_occ.to(alpha.dtype)
    occ_ce, occ_kl = evidential_beta_loss(alpha, beta, y, kl_w)
    sem_ce, sem_kl = evidential_dirichlet_loss(eta, gt_cls, kl_w)
    terms = {
        "occ_ce": (occ_ce * w).sum() / wsum,
        "occ_kl": (occ_kl * w).sum() / wsum,
        "sem_ce": (sem_ce * w).sum() / wsum,
        "sem_kl": (sem_kl * w).sum() / wsum,
    }
    total = cfg.w_occupancy * (terms["occ_ce"] + terms["occ_kl"]) + cfg.w_semantic * (terms["sem_ce"] + terms["sem_kl"])
    if change_logit is not None and change is not None:
        pos = torch.tensor(cfg.change_pos_weight, dtype=change_logit.dtype)
        bce = F.binary_cross_entropy_with_logits(change_logit, change.to(change_logit.dtype), pos_weight=pos,
                                                 reduction="none")
        v = valid.to(bce.dtype)
        terms["change_bce"] = (bce * v).sum() / v.sum().clamp_min(1.0)
        total = total + cfg.w_change * terms["change_bce"]
    terms["total"] = total
    return terms
