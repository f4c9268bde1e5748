"""FE-vMF: the full-evidential contact-grasp network (paper sec. "Full-Evidential Grasp Learning").

Per point c_i of the frontier cloud (eq. FE-vMF_inference) the heads predict
mu_a_hat, kappa_a_hat (intermediate approach, vMF), mu_b, kappa_b (baseline, vMF), Beta affordance
evidence alpha = softplus(e_alpha) + 1, beta = softplus(e_beta) + 1 (eq. grasp_aff) and a width.
The executable approach is the projection of a_hat orthogonal to b (eq. proj).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import overload

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from torch import Tensor, nn

from msmem_grasp.backbone import PointTransformer


class FEVMFConfig(BaseModel):
    """Architecture of FE-vMF (defaults: a small PTv3 backbone, ~0.25 M parameters; docs/explanation/grasp.md)."""

    model_config = ConfigDict(extra="forbid")

    dim: int = Field(64, ge=8)
    """Feature width of the backbone."""
    layers: int = Field(4, ge=1)
    heads: int = Field(4, ge=1)
    patch_size: int = Field(128, ge=2)
    """Points per attention patch (PTv3: 128-1024)."""
    mlp_ratio: float = Field(4.0, gt=0.0)
    grid_m: float = Field(0.01, gt=0.0)
    """Quantisation cell of the serialisation."""
    pos_scale_m: float = Field(0.1, gt=0.0)
    shift_patches: bool = True
    in_features: int = Field(0, ge=0)
    """Extra per-point input features (e.g. normals, vacuity); 0 = coordinates only."""
    head_hidden: int = Field(64, ge=1)
    kappa_floor: float = Field(0.01, gt=0.0)
    """kappa = softplus(.) + kappa_floor keeps the vMF proper and the NLL bounded below."""
    max_width_m: float = Field(0.08, gt=0.0)
    """Width head range (0, max_width_m): the gripper's maximal opening."""


@dataclass
class GraspPrediction:
    """Per-point outputs of FE-vMF (all [N] or [N, 3])."""

    mu_a_hat: Tensor
    kappa_a_hat: Tensor
    mu_b: Tensor
    kappa_b: Tensor
    alpha: Tensor
    beta: Tensor
    width: Tensor

    @property
    def affordance(self) -> Tensor:
        """E[q] = alpha / S (eq. occ_beta2)."""
        return self.alpha / (self.alpha + self.beta)

    @property
    def uncertainty(self) -> Tensor:
        """chi = 2 / S (eq. occ_beta2)."""
        return 2.0 / (self.alpha + self.beta)

    def approach(self) -> tuple[Tensor, Tensor]:
        """(mu_a, kappa_a) of the projected approach (eq. proj)."""
        return project_approach(self.mu_a_hat, self.mu_b, self.kappa_a_hat)

    def detach(self) -> GraspPrediction:
        return GraspPrediction(**{f.name: getattr(self, f.name).detach() for f in fields(self)})


def _head(dim: int, hidden: int, out: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, out))


class FEVMF(nn.Module):
    """PTv3-style backbone + per-point MLP heads (eq. FE-vMF_inference)."""

    def __init__(self, config: FEVMFConfig | None = None) -> None:
        super().__init__()
        self.config = c = config or FEVMFConfig()
        self.backbone = PointTransformer(
            dim=c.dim, layers=c.layers, heads=c.heads, patch_size=c.patch_size, in_features=c.in_features,
            grid_m=c.grid_m, mlp_ratio=c.mlp_ratio, pos_scale_m=c.pos_scale_m, shift_patches=c.shift_patches,
        )
        self.approach_head = _head(c.dim, c.head_hidden, 4)  # direction (3) + kappa (1)
        self.baseline_head = _head(c.dim, c.head_hidden, 4)
        self.affordance_head = _head(c.dim, c.head_hidden, 2)  # evidence logits (alpha, beta)
        self.width_head = _head(c.dim, c.head_hidden, 1)

    def forward(self, points: Tensor, feats: Tensor | None = None, batch: Tensor | None = None) -> GraspPrediction:
        f = self.backbone(points, feats, batch)
        a = self.approach_head(f)
        b = self.baseline_head(f)
        e = F.softplus(self.affordance_head(f)) + 1.0
        floor = self.config.kappa_floor
        return GraspPrediction(
            mu_a_hat=F.normalize(a[:, :3], dim=-1, eps=1e-8),
            kappa_a_hat=F.softplus(a[:, 3]) + floor,
            mu_b=F.normalize(b[:, :3], dim=-1, eps=1e-8),
            kappa_b=F.softplus(b[:, 3]) + floor,
            alpha=e[:, 0],
            beta=e[:, 1],
            width=torch.sigmoid(self.width_head(f)[:, 0]) * self.config.max_width_m,
        )

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def size_bytes(self) -> int:
        """Size of the parameters (float32 by default) as stored in a state dict."""
        return sum(p.numel() * p.element_size() for p in self.parameters())


@overload
def project_approach(a_hat: Tensor, b: Tensor, kappa_a_hat: None = None) -> Tensor: ...
@overload
def project_approach(a_hat: Tensor, b: Tensor, kappa_a_hat: Tensor) -> tuple[Tensor, Tensor]: ...
def project_approach(a_hat: Tensor, b: Tensor, kappa_a_hat: Tensor | None = None) -> Tensor | tuple[Tensor, Tensor]:
    """Eq. proj: mu_a = P_b a_hat / ||P_b a_hat|| with P_b = I - b b^T; kappa_a = kappa_a_hat ||P_b a_hat||.

    If a_hat is (nearly) parallel to b, any direction orthogonal to b is returned (and kappa_a ~ 0,
    which says exactly that: the approach is undetermined).
    """
    r = a_hat - (a_hat * b).sum(-1, keepdim=True) * b
    norm = r.norm(dim=-1, keepdim=True)
    helper = torch.zeros_like(b)
    use_x = b[..., 0].abs() < 0.9
    helper[..., 0] = use_x.to(b.dtype)
    helper[..., 1] = (~use_x).to(b.dtype)
    fallback = F.normalize(torch.linalg.cross(b, helper, dim=-1), dim=-1)
    a = torch.where(norm > 1e-9, r / norm.clamp_min(1e-9), fallback)
    a = F.normalize(a - (a * b).sum(-1, keepdim=True) * b, dim=-1)  # second pass: exact when a_hat ~ b
    if kappa_a_hat is None:
        return a
    return a, kappa_a_hat * norm[..., 0]


ArrayT = Tensor | NDArray[np.floating]


def executable_grasp(contact: ArrayT, a: ArrayT, b: ArrayT, width: ArrayT) -> ArrayT:
    """Gripper poses [..., 4, 4] in the ``GripperSpec`` convention (torch in -> torch out, numpy -> numpy).

    Origin at the centre between the fingertips, c + (w/2) b; rotation columns (b, a x b, a), i.e.
    x = closing direction, z = approach, y = z cross x. ``a`` is re-orthogonalised against ``b``.
    """
    if isinstance(contact, Tensor):
        bt = F.normalize(torch.as_tensor(b), dim=-1)
        at = project_approach(torch.as_tensor(a), bt)
        pose = torch.zeros((*contact.shape[:-1], 4, 4), dtype=contact.dtype, device=contact.device)
        pose[..., :3, 0] = bt
        pose[..., :3, 1] = torch.linalg.cross(at, bt, dim=-1)
        pose[..., :3, 2] = at
        pose[..., :3, 3] = contact + 0.5 * torch.as_tensor(width)[..., None] * bt
        pose[..., 3, 3] = 1.0
        return pose
    c = np.asarray(contact, dtype=np.float64)
    bn = np.asarray(b, dtype=np.float64)
    bn = bn / np.linalg.norm(bn, axis=-1, keepdims=True)
    an = np.asarray(a, dtype=np.float64)
    an = an - (an * bn).sum(-1, keepdims=True) * bn
    an = an / np.linalg.norm(an, axis=-1, keepdims=True)
    pose_np = np.zeros((*c.shape[:-1], 4, 4))
    pose_np[..., :3, 0] = bn
    pose_np[..., :3, 1] = np.cross(an, bn)
    pose_np[..., :3, 2] = an
    pose_np[..., :3, 3] = c + 0.5 * np.asarray(width, dtype=np.float64)[..., None] * bn
    pose_np[..., 3, 3] = 1.0
    return pose_np
