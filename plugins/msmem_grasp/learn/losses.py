"""The composite FE-vMF loss (paper eq. fevmf_loss).

L_i = q_i^dag (L_vMF(a_hat) + L_vMF(b)) + L_EDL(alpha_i, beta_i) + q_i^dag L1(width):
- orientation terms on positives only (points within max(2 mm, half a voxel) of a GT contact); where
  several GT grasps share a contact, the NLL is averaged over them, so a low kappa between the
  feasible directions beats a confident pick of one of them;
- the baseline target is the *directed* GT b (from the contact to the opposite contact);
- the evidential Beta loss (digamma expected cross-entropy + annealed KL to Beta(1, 1) of the
  misleading evidence) on all points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field
from scipy.spatial import cKDTree
from torch import Tensor

from msmem_grasp.fevmf import GraspPrediction
from msmem_grasp.vmf import log_normaliser


class LossConfig(BaseModel):
    """Weights of the FE-vMF loss terms and the KL annealing schedule."""

    model_config = ConfigDict(extra="forbid")

    w_approach: float = Field(1.0, ge=0.0)
    w_baseline: float = Field(1.0, ge=0.0)
    w_affordance: float = Field(1.0, ge=0.0)
    w_width: float = Field(1.0, ge=0.0)
    """Weight of the L1 width error measured in units of ``max_width_m``."""
    anneal_epochs: float = Field(10.0, gt=0.0)
    """KL weight min(1, epoch / anneal_epochs)."""
    max_width_m: float = Field(0.08, gt=0.0)


@dataclass
class GraspTargets:
    """Ground truth for one cloud of N points, P of them positive, each with up to G GT grasps.

    ``positive_index`` [P] indexes the cloud; ``approach``/``baseline`` [P, G, 3] are unit vectors
    (baseline directed from the contact to the opposite one), ``width`` [P, G], ``mask`` [P, G] marks
    real (non-padding) entries; every positive has at least one.
    """

    num_points: int
    positive_index: Tensor
    approach: Tensor
    baseline: Tensor
    width: Tensor
    mask: Tensor

    @property
    def label(self) -> Tensor:
        """Affordance label q^dag [N] (1 at positives)."""
        y = torch.zeros(self.num_points, dtype=self.approach.dtype, device=self.approach.device)
        y[self.positive_index] = 1.0
        return y


def vmf_nll(mu: Tensor, kappa: Tensor, targets: Tensor, mask: Tensor) -> Tensor:
    """Per-point NLL [P] averaged over the valid targets [P, G, 3]:
    mean_j -log p(t_j | mu, kappa) = -log C(kappa) - kappa mu . mean_j t_j.
    """
    m = mask.to(targets.dtype)
    mean_target = (targets * m[..., None]).sum(1) / m.sum(1, keepdim=True).clamp_min(1.0)
    return -log_normaliser(kappa) - kappa * (mu * mean_target).sum(-1)


def beta_expected_ce(alpha: Tensor, beta: Tensor, y: Tensor) -> Tensor:
    """E_{q ~ Beta(alpha, beta)}[-y log q - (1 - y) log(1 - q)]
    = y (psi(S) - psi(alpha)) + (1 - y)(psi(S) - psi(beta)), S = alpha + beta."""
    ds = torch.digamma(alpha + beta)
    return y * (ds - torch.digamma(alpha)) + (1.0 - y) * (ds - torch.digamma(beta))


def beta_kl_uniform(alpha: Tensor, beta: Tensor) -> Tensor:
    """KL(Beta(alpha, beta) || Beta(1, 1)) = lnG(S) - lnG(alpha) - lnG(beta)
    + (alpha - 1)(psi(alpha) - psi(S)) + (beta - 1)(psi(beta) - psi(S)).

    Computed in float64 and returned in the inputs' dtype: the terms are large and cancel (in
    float32, Beta(1e8, 1e8) gave -160 instead of 8.83 and the gradient vanished near 1e6)."""
    a, b = alpha.double(), beta.double()
    s = a + b
    ds = torch.digamma(s)
    kl = (
        torch.lgamma(s) - torch.lgamma(a) - torch.lgamma(b)
        + (a - 1.0) * (torch.digamma(a) - ds) + (b - 1.0) * (torch.digamma(b) - ds)
    )
    return kl.to(alpha.dtype)


def evidential_beta_loss(alpha: Tensor, beta: Tensor, y: Tensor, kl_weight: float) -> tuple[Tensor, Tensor]:
    """(expected CE [N], KL [N]) of the evidential affordance loss. The KL regularises only the
    misleading evidence: the correct outcome's parameter is reset to 1 (alpha~ = y + (1-y) alpha,
    beta~ = (1-y) + y beta), the wrong outcome's evidence is kept and pushed to 0."""
    ce = beta_expected_ce(alpha, beta, y)
    alpha_t = y + (1.0 - y) * alpha
    beta_t = (1.0 - y) + y * beta
    return ce, kl_weight * beta_kl_uniform(alpha_t, beta_t)


def total_loss(
    outputs: GraspPrediction, batch: GraspTargets, epoch: float, config: LossConfig | None = None
) -> dict[str, Tensor]:
    """All loss terms (scalars) and their weighted sum under "total"."""
    cfg = config or LossConfig()
    idx = batch.positive_index
    y = batch.label
    kl_weight = min(1.0, epoch / cfg.anneal_epochs)
    ce, kl = evidential_beta_loss(outputs.alpha, outputs.beta, y, kl_weight)
    if len(idx):
        nll_a = vmf_nll(outputs.mu_a_hat[idx], outputs.kappa_a_hat[idx], batch.approach, batch.mask).mean()
        nll_b = vmf_nll(outputs.mu_b[idx], outputs.kappa_b[idx], batch.baseline, batch.mask).mean()
        m = batch.mask.to(batch.width.dtype)
        err = (outputs.width[idx, None] - batch.width).abs() * m
        width = ((err.sum(1) / m.sum(1).clamp_min(1.0)) / cfg.max_width_m).mean()
    else:  # no positives: zero terms that keep the graph (and DDP) happy
        zero = (outputs.kappa_a_hat.sum() + outputs.kappa_b.sum() + outputs.width.sum()) * 0.0
        nll_a = nll_b = width = zero
    terms = {
        "approach": nll_a,
        "baseline": nll_b,
        "affordance_ce": ce.mean(),
        "affordance_kl": kl.mean(),
        "width": width,
    }
    terms["total"] = (
        cfg.w_approach * nll_a + cfg.w_baseline * nll_b
        + cfg.w_affordance * (terms["affordance_ce"] + terms["affordance_kl"]) + cfg.w_width * width
    )
    return terms


def assign_targets(
    points: Tensor,
    contacts: Tensor,
    approach: Tensor,
    baseline: Tensor,
    width: Tensor,
    radius_m: float = 0.002,
    max_grasps: int = 32,
) -> GraspTargets:
    """Label the points within ``radius_m`` of a GT contact [G, 3] positive and gather, per positive,
    up to ``max_grasps`` GT grasps whose contact lies within the radius (nearest first).

    Use radius max(2 mm, half a voxel) for clouds taken from a voxel belief.
    """
    if len(contacts) == 0 or len(points) == 0:
        z = points.new_zeros((0, max_grasps, 3))
        return GraspTargets(len(points), torch.zeros(0, dtype=torch.long), z, z.clone(),
                            points.new_zeros((0, max_grasps)), torch.zeros((0, max_grasps), dtype=torch.bool))
    tree = cKDTree(contacts.detach().cpu().double().numpy())
    k = min(max_grasps, len(contacts))
    dist, nn_np = tree.query(points.detach().cpu().double().numpy(), k=k, distance_upper_bound=radius_m)
    near = torch.from_numpy(np.isfinite(dist).reshape(len(points), k)).to(points.device)
    nn_idx = torch.from_numpy(np.minimum(nn_np, len(contacts) - 1).reshape(len(points), k)).to(points.device)
    pos = near[:, 0].nonzero()[:, 0]
    sel, mask = nn_idx[pos], near[pos]
    pad = max_grasps - k

    def gather(x: Tensor) -> Tensor:
        g = x.to(points)[sel]
        return torch.nn.functional.pad(g, (0, 0) * (g.dim() - 2) + (0, pad))

    return GraspTargets(
        num_points=len(points),
        positive_index=pos,
        approach=gather(approach),
        baseline=gather(baseline),
        width=gather(width),
        mask=torch.nn.functional.pad(mask, (0, pad)),
    )
