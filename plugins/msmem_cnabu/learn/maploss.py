"""The losses of the whole-map observation network (``cnabu-map``, ``msmem_cnabu.mapnet``), taken by
``maptrain`` after every view of a rollout: the per-voxel occupancy and class NLLs (``map_loss``) and the
NLL of the top-view class map (``top_view_loss``), both of the bounded probabilities the belief reports.
"""

from __future__ import annotations

import torch
from torch import Tensor

from msmem_cnabu.mapnet import bounded_evidence


def map_loss(occ_logit: Tensor, cls_logit: Tensor, gt_occ: Tensor, gt_cls: Tensor, valid: Tensor,
             s_max: float, t_max: float, occupied_class_weight: float = 1.0, occupied_only: bool = False
             ) -> tuple[Tensor, Tensor]:
    """(occupancy NLL, class NLL), means over the valid voxels, of the bounded expected probabilities
    (exactly what the belief reports) against the ground truth (class 0 = free). The class NLL of
    voxels that are occupied in truth counts ``occupied_class_weight`` times (object voxels are a few
    percent of the shelf: without a weight the class head learns mostly "free"); with
    ``occupied_only`` (the ``object`` class head, whose free class is the occupancy's) it is taken on
    those voxels alone, as the NLL of the object class given occupied, ``-log(q_y / (1 - q_0))``:
    ``-log q_y`` would also push their occupancy up, on top of the occupancy NLL (measured: run 4
    trained that way lost 0.02 held-out occupancy mIoU and predicted objects in free columns).
    """
    _, _, _, p, q = bounded_evidence(occ_logit, cls_logit, s_max, t_max)
    m = valid.expand_as(gt_occ)
    y = gt_occ.to(p.dtype)
    occ_nll = -(y * torch.log(p) + (1 - y) * torch.log1p(-p))
    qy = torch.gather(q, 1, gt_cls.long()[:, None])[:, 0]
    cls_nll = -torch.log(qy)
    if occupied_only:  # the object class given occupied, -log(q_y / (1 - q_0)): (almost) no push on p
        cls_nll = cls_nll + torch.log1p(-q[:, 0])
    n = m.sum().clamp(min=1)
    w = y if occupied_only else 1.0 + (occupied_class_weight - 1.0) * y
    return occ_nll[m].sum() / n, (w * cls_nll)[m].sum() / w[m].sum().clamp(min=1)


def top_view_loss(occ_logit: Tensor, cls_logit: Tensor, gt_cls: Tensor, valid: Tensor, s_max: float,
                  t_max: float) -> Tensor:
    """NLL of the ground truth's top-view class map (the paper's 2-D semantic map, ``metrics.
    top_view_classes`` of the interior) under the belief's expected top-view class distribution, mean
    over the interior's columns.

    A column's top class is the class of its highest occupied interior voxel, else background. Under
    the belief (voxels independent), voxel z is the highest occupied one with probability
    ``P_z = p_z prod_{z' > z} (1 - p_z')``, so the column's top class is object class c with
    probability ``sum_z P_z r_c(z)`` (r: the voxel's object-class distribution, ``q[1:]`` renormalised)
    and background with ``prod_z (1 - p_z)``. Unlike the per-voxel NLL it charges a false occupied
    voxel above an object (it takes the top) and a wrong class on the surface the map is scored by."""
    _, _, _, p, q = bounded_evidence(occ_logit, cls_logit, s_max, t_max)
    v = valid.to(p.dtype)
    p = p * v  # boards and outside: not occupied (the metric sets them to background)
    log_free = torch.log1p(-p.clamp(max=1 - 1e-6))
    above = torch.flip(torch.cumsum(torch.flip(log_free, [-1]), -1), [-1]) - log_free  # sum over z' > z
    top = p * torch.exp(above)  # [B, X, Y, Z]
    r = q[:, 1:] / q[:, 1:].sum(1, keepdim=True)
    obj = (top[:, None] * r).sum(-1)  # [B, C - 1, X, Y]
    bg = torch.exp(log_free.sum(-1))[:, None]  # [B, 1, X, Y]
    probs = torch.cat([bg, obj], 1).clamp(min=1e-6)
    z = gt_cls.shape[-1]
    labels = torch.where(valid, gt_cls.long(), 0)
    nonzero = labels > 0
    highest = torch.where(nonzero, torch.arange(z, device=labels.device), -1).amax(-1, keepdim=True)
    gt_top = torch.gather(labels, -1, highest.clamp(min=0))[..., 0] * (highest[..., 0] >= 0)  # [B, X, Y]
    nll = -torch.log(torch.gather(probs, 1, gt_top[:, None])[:, 0])
    cols = valid.any(-1).expand_as(nll)
    return nll[cols].mean()
