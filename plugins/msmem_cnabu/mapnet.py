"""The whole-map observation network (``cnabu-map``): previous belief + one view -> the next belief over
every voxel (docs/explanation/map-prediction.md).

One step, for a belief ``B`` (alpha, beta, eta) and a view's ray masks (free, occ [X, Y, Z], seen
[C, X, Y, Z], ``AnalyticObservationModel.masks``):

1. *Evidence of the view* (no parameters): ``A`` = the analytic update of ``B`` with the masks
   (``analytic_update``: the same rule as ``analytic-observation``). So the network starts from
   what the rays say and only has to learn what they do not: interiors, backs, the space behind the
   front row, and which earlier evidence the new view overturns.
2. *Features per voxel*: logit of A's expected occupancy, log of its occupancy and class evidence
   totals, A's expected class probabilities, the view's free / occupied / seen masks, and where the
   voxel lies in its column: below the column's highest believed-occupied interior voxel (the
   column-fill twin's rule, as a feature) and how far below it.
3. *2.5-D U-Net* (height bins as channels, as the CNABU effect networks) gives every voxel a column
   context; a per-voxel MLP on [context, features] outputs a residual on A's logits: occupancy
   ``logit p = logit p_A + d_o`` and classes ``log q = log q_A + d_c``. The residual's last layer
   starts at zero, so an untrained network is the analytic update.
4. *Bounded evidence by construction* (``bounded_evidence``): the probabilities are mixed with a
   floor, ``p in [1/s_max, 1 - 1/s_max]`` and ``q_c >= 1/t_max``, and the evidence is the least
   committal Beta / Dirichlet with those means and every evidence >= 1: ``S = 1 / min(p, 1 - p)``,
   ``alpha = p S``, ``beta = (1 - p) S``; ``T = 1 / min_c q_c``, ``eta = q T``. So
   ``2 <= alpha + beta <= s_max`` and ``C <= sum(eta) <= t_max`` whatever the episode length, a
   voxel at p = 0.5 is the prior, and a voxel's vacuity ``C / T`` says how peaked its class is.

The shelf's boards (``valid`` False) get no residual: they keep A's probabilities, bounded.
Training unrolls sequences of views, each step fed the network's own previous output
(``msmem_cnabu.learn.maptrain``; its losses: ``msmem_cnabu.learn.maploss``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import Tensor, nn

from msmem_cnabu.network import unet, unet_layers
from msmem_core.world.scene import NUM_CLASSES

LOGIT_CLIP = 12.0


class MapNetConfig(BaseModel):
    """Architecture of the whole-map observation network (recorded in the weights' sidecar)."""

    model_config = ConfigDict(extra="forbid")

    kind: str = "map"
    grid_shape: tuple[int, int, int] = (78, 40, 30)
    """Voxels along x, y, z of the grid the network was trained on (z bins are channels)."""
    num_classes: int = Field(NUM_CLASSES, ge=2)
    embed: int = Field(6, ge=1, le=64)
    """Per-voxel embedding width before the height bins are flattened into channels."""
    width: int = Field(48, ge=4, le=512)
    """Channels of the first U-Net level (doubled per level)."""
    levels: int = Field(3, ge=1, le=5)
    context: int = Field(8, ge=1, le=64)
    """Column-context features per voxel handed to the per-voxel head."""
    hidden: int = Field(32, ge=4, le=512)
    w_obs: float = Field(10.0, gt=0.0)
    """Evidence per view of the analytic step inside the network (``analytic-observation``'s w_occ,
    w_free, w_cls)."""
    s_max: float = Field(100.0, gt=2.0)
    """Largest occupancy evidence total alpha + beta (p is kept in [1/s_max, 1 - 1/s_max])."""
    t_max: float = Field(300.0, gt=0.0)
    """Largest class evidence total sum(eta) (every q_c >= 1/t_max)."""
    class_head: Literal["joint", "object"] = "joint"
    """``joint``: a residual on all C class logits. ``object``: the class distribution is tied to the
    occupancy, ``q = [1 - p, p r]``, and the head predicts only ``r``, the object class of an occupied
    voxel (a residual on A's object-class distribution); its loss is taken on occupied voxels."""
    nearest_class: bool = False
    """Add, per voxel, the object-class distribution of the nearest voxel whose class A already knows
    (occupied, top object class above 1/2) and the distance to it (``nearest_known_class``)."""

    @model_validator(mode="after")
    def _check(self) -> MapNetConfig:
        if self.t_max <= self.num_classes:
            raise ValueError(f"t_max {self.t_max} must exceed num_classes {self.num_classes}")
        px, py = self.padded_xy
        if (px >> self.levels) * (py >> self.levels) < 2:
            raise ValueError(f"grid_shape {self.grid_shape[:2]} is too small for levels={self.levels}")
        return self

    @property
    def features(self) -> int:
        return 3 + self.num_classes + 5 + (self.num_classes if self.nearest_class else 0)

    @property
    def padded_xy(self) -> tuple[int, int]:
        m = 2**self.levels
        x, y = self.grid_shape[:2]
        return -(-x // m) * m, -(-y // m) * m


def analytic_update(alpha: Tensor, beta: Tensor, eta: Tensor, free: Tensor, occ: Tensor, seen: Tensor,
                    w: float) -> tuple[Tensor, Tensor, Tensor]:
    """``analytic-observation``'s rule (contradiction decay off) on [B, ...] tensors: occupied and
    class evidence at hits, free and background evidence before them."""
    f, o, s = free.to(alpha.dtype), occ.to(alpha.dtype), seen.to(alpha.dtype)
    eta = eta + w * s
    eta = torch.cat([eta[:, :1] + w * f[:, None], eta[:, 1:]], 1)
    return alpha + w * o, beta + w * f, eta


def nearest_known_class(occ_logit: Tensor, obj: Tensor, valid: Tensor, scale: float) -> Tensor:
    """[B, C, X, Y, Z]: per voxel the object-class distribution ``obj`` [B, C - 1, ...] of the nearest
    voxel whose class is known (``valid``, believed occupied and its top object class above 1/2;
    Euclidean distance in voxels), and that distance divided by ``scale``. A batch element with no
    known voxel gets a uniform distribution at distance 1."""
    from scipy import ndimage

    known = ((occ_logit > 0) & (obj.amax(1) > 0.5) & valid).numpy()
    out = torch.empty(obj.shape[0], obj.shape[1] + 1, *obj.shape[2:], dtype=obj.dtype)
    for i, k in enumerate(known):
        if not k.any():
            out[i, :-1] = 1.0 / obj.shape[1]
            out[i, -1] = 1.0
            continue
        dist, idx = ndimage.distance_transform_edt(~k, return_indices=True)
        flat = torch.from_numpy(np.ravel_multi_index(tuple(idx), k.shape).ravel())
        out[i, :-1] = obj[i].reshape(obj.shape[1], -1)[:, flat].reshape(obj.shape[1:])
        out[i, -1] = torch.from_numpy(np.minimum(dist / scale, 1.0).astype(np.float32))
    return out


def bounded_evidence(occ_logit: Tensor, cls_logit: Tensor, s_max: float, t_max: float
                     ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """(alpha, beta, eta, p, q) from logits: floored probabilities and the least committal evidence
    with those means (module docstring, step 4). ``occ_logit`` [B, ...], ``cls_logit`` [B, C, ...]."""
    c = cls_logit.shape[1]
    eps_o = 2.0 / s_max
    p = eps_o / 2 + (1 - eps_o) * torch.sigmoid(occ_logit)
    eps_c = c / t_max
    q = eps_c / c + (1 - eps_c) * torch.softmax(cls_logit, 1)
    s = 1.0 / torch.minimum(p, 1 - p)
    t = 1.0 / q.min(1, keepdim=True).values
    return p * s, (1 - p) * s, q * t, p, q


def known_object_classes(prev_logit: Tensor, prev_cls: Tensor, out_cls: Tensor, seen: Tensor, valid: Tensor
                         ) -> Tensor:
    """[B, C] bool: the object classes the map knows are in the scene (index 0, background, False).

    A class is known if the previous belief already names it somewhere (it is the top object class of
    a valid voxel believed occupied), or if this view's rays hit it (``seen``) at a voxel whose new top
    object class, before any restriction, is it. ``prev_logit`` [B, X, Y, Z]: the previous occupancy
    logit; ``prev_cls`` and ``out_cls`` [B, C, X, Y, Z]: log class probabilities (or log evidence) of
    the previous and the new belief. A class the segmentation reports only by a one-view confusion on
    an object already named is not made known: the voxel keeps its class."""
    def named(log_q: Tensor, where: Tensor) -> Tensor:
        top = F.one_hot(log_q[:, 1:].argmax(1), log_q.shape[1] - 1).permute(0, 4, 1, 2, 3).bool() & where
        return torch.cat([torch.zeros_like(top[:, :1, 0, 0, 0]), top.flatten(2).any(2)], 1)

    return named(prev_cls, ((prev_logit > 0) & valid)[:, None]) | named(out_cls, seen[:, 1:].bool() & valid)


def restrict_classes(cls_logit: Tensor, known: Tensor, weight: float) -> Tensor:
    """Class log probabilities with the object classes not ``known`` [B, C] down-weighted by ``weight``:
    ``r'_c ∝ r_c w_c`` (``w_c`` = 1 if known, else ``weight``) at the same background probability
    ``q_0``, so the occupancy is unchanged. Where no class is known the classes are left alone."""
    log_q = torch.log_softmax(cls_logit, 1)
    w = torch.where(known[:, 1:], 0.0, float(np.log(weight))).to(log_q.dtype)[:, :, None, None, None]
    obj = torch.log_softmax(log_q[:, 1:] + w, 1)  # nothing known: every class scaled alike, no change
    return torch.cat([log_q[:, :1], torch.log1p(-log_q[:, :1].exp().clamp(max=1 - 1e-7)) + obj], 1)


class MapNet(nn.Module):
    """One observation step over the whole map (module docstring)."""

    def __init__(self, config: MapNetConfig) -> None:
        super().__init__()
        self.config = cfg = config
        z = cfg.grid_shape[2]
        self.embed = nn.Linear(cfg.features, cfg.embed)
        w = cfg.width
        self.stem = nn.Conv2d(z * cfg.embed, w, 2, stride=2)
        self.down, self.enc, self.up, self.dec = unet_layers(w, cfg.levels)
        self.full = nn.ConvTranspose2d(w, w, 2, stride=2)
        self.column = nn.Conv2d(w, z * cfg.context, 1)
        last = nn.Linear(cfg.hidden, 1 + cfg.num_classes)
        nn.init.zeros_(last.weight)  # an untrained network is the analytic update
        nn.init.zeros_(last.bias)
        self.head = nn.Sequential(nn.Linear(cfg.context + cfg.features, cfg.hidden), nn.SiLU(), last)

    def features(self, alpha: Tensor, beta: Tensor, eta: Tensor, free: Tensor, occ: Tensor, seen: Tensor,
                 valid: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """(features [B, F, X, Y, Z], A's occupancy logit [B, X, Y, Z], A's log class probs [B, C, ...])
        of a belief (evidence [B, ...]) and a view's masks; ``valid`` [X, Y, Z] marks the interior."""
        a, b, e = analytic_update(alpha, beta, eta, free, occ, seen, self.config.w_obs)
        s = a + b
        t = e.sum(1)
        logit = (torch.log(a) - torch.log(b)).clamp(-LOGIT_CLIP, LOGIT_CLIP)
        logq = torch.log(e) - torch.log(t)[:, None]
        dt = alpha.dtype
        z = logit.shape[-1]
        height = torch.arange(z, device=logit.device)
        top = torch.where((logit > 0) & valid, height, -1).amax(-1, keepdim=True)  # [B, X, Y, 1]: -1 if none
        below = (height < top).to(dt)  # under the column's highest believed-occupied interior voxel
        depth = (top - height).clamp(min=0).to(dt) / z
        parts = [
            (logit / 4)[:, None], (torch.log(s) / 4)[:, None], (torch.log(t) / 4)[:, None], logq.exp(),
            free.to(dt)[:, None], occ.to(dt)[:, None], seen.any(1).to(dt)[:, None], below[:, None], depth[:, None],
        ]
        if self.config.nearest_class:
            parts.append(nearest_known_class(logit, torch.softmax(logq[:, 1:], 1), valid, float(z)))
        return torch.cat(parts, 1), logit, logq

    def _trunk(self, feats: Tensor) -> Tensor:
        """Per-voxel column context [B, X, Y, Z, context] from the features."""
        cfg = self.config
        bsz, f, x, y, z = feats.shape
        emb = torch.matmul(self.embed.weight, feats.reshape(bsz, f, -1)) + self.embed.bias[:, None]
        m = emb.reshape(bsz, -1, x, y, z).permute(0, 4, 1, 2, 3).reshape(bsz, z * cfg.embed, x, y)
        px, py = cfg.padded_xy
        h = unet(F.silu(self.stem(F.pad(m, (0, py - y, 0, px - x)))), self.down, self.enc, self.up, self.dec)
        h = self.column(F.silu(self.full(h)))[:, :, :x, :y]
        return h.reshape(bsz, z, cfg.context, x, y).permute(0, 3, 4, 1, 2)

    def forward(self, alpha: Tensor, beta: Tensor, eta: Tensor, free: Tensor, occ: Tensor, seen: Tensor,
                valid: Tensor) -> tuple[Tensor, Tensor]:
        """Logits of the next belief: occupancy [B, X, Y, Z] and classes [B, C, X, Y, Z]. Inputs: the
        previous evidence (alpha, beta [B, X, Y, Z], eta [B, C, ...]), the view's masks (free, occ
        [B, X, Y, Z], seen [B, C, ...]) and ``valid`` [X, Y, Z] (False on the shelf's boards)."""
        feats, logit, logq = self.features(alpha, beta, eta, free, occ, seen, valid)
        ctx = self._trunk(feats)
        h = torch.cat([ctx, feats.permute(0, 2, 3, 4, 1)], -1)
        d = self.head(h).permute(0, 4, 1, 2, 3) * valid.to(h.dtype)  # [B, 1 + C, X, Y, Z]
        o = logit + d[:, 0]
        if self.config.class_head == "joint":
            return o, logq + d[:, 1:]
        # object head: log q = [log(1 - p), log p + log r], r from A's object classes plus the residual
        r = torch.log_softmax(logq[:, 1:] + d[:, 2:], 1)
        return o, torch.cat([F.logsigmoid(-o)[:, None], F.logsigmoid(o)[:, None] + r], 1)

    def step(self, alpha: Tensor, beta: Tensor, eta: Tensor, free: Tensor, occ: Tensor, seen: Tensor,
             valid: Tensor, unseen_class_weight: float = 1.0, known: Tensor | None = None
             ) -> tuple[Tensor, Tensor, Tensor]:
        """The next belief's bounded evidence (alpha, beta, eta). With ``unseen_class_weight`` < 1 the
        object classes the map does not know are in the scene (``known_object_classes``) are
        down-weighted by it everywhere (``restrict_classes``)."""
        o, c = self(alpha, beta, eta, free, occ, seen, valid)
        c = self._restricted(c, alpha, beta, eta, seen, valid, unseen_class_weight, known)
        return bounded_evidence(o, c, self.config.s_max, self.config.t_max)[:3]

    def step_both(self, alpha: Tensor, beta: Tensor, eta: Tensor, free: Tensor, occ: Tensor, seen: Tensor,
                  valid: Tensor, unseen_class_weight: float = 1.0, known: Tensor | None = None
                  ) -> tuple[tuple[Tensor, Tensor, Tensor], tuple[Tensor, Tensor, Tensor]]:
        """``step``'s evidence before and after the class restriction, from one forward pass (the same
        twice when ``unseen_class_weight`` is 1)."""
        o, c = self(alpha, beta, eta, free, occ, seen, valid)
        raw = bounded_evidence(o, c, self.config.s_max, self.config.t_max)[:3]
        if unseen_class_weight >= 1.0:
            return raw, raw
        c = self._restricted(c, alpha, beta, eta, seen, valid, unseen_class_weight, known)
        return raw, bounded_evidence(o, c, self.config.s_max, self.config.t_max)[:3]

    @staticmethod
    def _restricted(c: Tensor, alpha: Tensor, beta: Tensor, eta: Tensor, seen: Tensor, valid: Tensor,
                    unseen_class_weight: float, known: Tensor | None) -> Tensor:
        """The class log probabilities ``c`` with the classes not known down-weighted (unchanged at 1)."""
        if unseen_class_weight >= 1.0:
            return c
        if known is None:
            prev_logit = (torch.log(alpha) - torch.log(beta)).clamp(-LOGIT_CLIP, LOGIT_CLIP)
            known = known_object_classes(prev_logit, torch.log(eta), c, seen, valid)
        return restrict_classes(c, known, unseen_class_weight)


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())

