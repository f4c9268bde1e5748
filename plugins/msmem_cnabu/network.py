"""The CNABU network: a 2.5-D U-Net with the height bins as channels (docs/explanation/cnabu.md, "The networks").

Input, per voxel: the belief features (``features.belief_features``: expected occupancy, occupancy
uncertainty 2/S, semantic vacuity, expected class probabilities) and the action's voxel channels
(``features``: ray masks, swept volume, ...); per sample: the action's scalar channels (a learned
per-channel offset of the action's stem).

Data flow (B samples, grid X x Y x Z, C classes):

1. *Height bins as channels*: a per-voxel linear embedding shared over the Z bins (belief -> ``embed``,
   action -> ``action_embed`` features) is flattened to Z * embed channels of a 2-D X x Y map. The
   belief part and the action part have separate stems whose outputs are summed (the same as one
   stem over the concatenation), so ``predict_many`` runs the belief's stem once for K candidates.
2. *U-Net* on the bird's-eye map: a stride-2 stem (2 x 2 patches), ``levels`` resolutions with two
   3 x 3 conv blocks each (GroupNorm, SiLU), skip connections, a transposed conv back to full
   resolution.
3. *Column context*: a 1 x 1 conv to Z * ``context`` channels, i.e. ``context`` features per voxel.
4. *Per-voxel heads* on [context, belief features, action voxel channels]: the change logit (push
   and grasp) and, through a small MLP, the evidence: occupancy (alpha, beta) and class (eta) as
   ``relu(prior - 1 + evidence_scale * out) + 1``, i.e. relu + 1 of a residual on the prior, so the
   identity is easy to learn and every evidence is >= 1.

At inference (``predict_many``) the evidence head runs only on the voxels whose change probability
passes the threshold (or, for observe, that the view reached); the belief models copy the prior
everywhere else.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import BaseModel, ConfigDict, Field, model_validator
from torch import Tensor, nn

from msmem_core.world.scene import NUM_CLASSES

Kind = Literal["observe", "push", "grasp"]
KINDS: tuple[str, ...] = ("observe", "push", "grasp")


def belief_feature_count(num_classes: int) -> int:
    """Expected occupancy, occupancy uncertainty, vacuity and one probability per class."""
    return 3 + num_classes


def action_channel_counts(kind: str, num_classes: int) -> tuple[int, int]:
    """(voxel channels, scalar channels) of an action of ``kind`` (see ``features``)."""
    if kind == "observe":
        return 2 + num_classes, 0  # free, occupied, class seen (one-hot per class)
    if kind in ("push", "grasp"):
        return 2, 4  # swept volume, start/contact; 4 scalars (direction, length/width ...)
    raise ValueError(f"unknown CNABU kind {kind!r}; kinds: {', '.join(KINDS)}")


class CNABUNetConfig(BaseModel):
    """Architecture of one CNABU network (recorded in the weights' sidecar)."""

    model_config = ConfigDict(extra="forbid")

    kind: Kind
    grid_shape: tuple[int, int, int] = (78, 40, 30)
    """Voxels along x, y, z of the grid the network was trained on (z bins are channels)."""
    num_classes: int = Field(NUM_CLASSES, ge=2)
    embed: int = Field(4, ge=1, le=64)
    """Per-voxel belief embedding width before the height bins are flattened into channels."""
    action_embed: int = Field(2, ge=1, le=64)
    width: int = Field(32, ge=4, le=512)
    """Channels of the first U-Net level (doubled per level)."""
    levels: int = Field(3, ge=1, le=5)
    context: int = Field(4, ge=1, le=64)
    """Column-context features per voxel handed to the per-voxel heads."""
    hidden: int = Field(32, ge=4, le=512)
    """Hidden width of the per-voxel evidence MLP."""
    evidence_scale: float = Field(10.0, gt=0.0)
    """Evidence change per unit of the head's output (the analytic update adds 10 per view)."""

    @model_validator(mode="after")
    def _coarsest_level_has_room(self) -> CNABUNetConfig:
        px, py = self.padded_xy
        if (px >> self.levels) * (py >> self.levels) < 2:
            raise ValueError(f"grid_shape {self.grid_shape[:2]} is too small for levels={self.levels}: the coarsest "
                             f"map would be {px >> self.levels} x {py >> self.levels}, GroupNorm needs at least 2 "
                             "values per channel; use fewer levels")
        return self

    @property
    def change_head(self) -> bool:
        return self.kind in ("push", "grasp")

    @property
    def in_voxel(self) -> int:
        return belief_feature_count(self.num_classes)

    @property
    def action_voxel(self) -> int:
        return action_channel_counts(self.kind, self.num_classes)[0]

    @property
    def action_scalars(self) -> int:
        return action_channel_counts(self.kind, self.num_classes)[1]

    @property
    def padded_xy(self) -> tuple[int, int]:
        """X and Y padded to a multiple of 2 ** levels (the stem halves them, each level again)."""
        m = 2**self.levels
        x, y = self.grid_shape[:2]
        return -(-x // m) * m, -(-y // m) * m


@dataclass
class CNABUOutput:
    """Evidence [B, X, Y, Z] (``eta``: [B, C, X, Y, Z]) and the change logit (None for observe)."""

    alpha: Tensor
    beta: Tensor
    eta: Tensor
    change_logit: Tensor | None

    @property
    def change(self) -> Tensor | None:
        return None if self.change_logit is None else torch.sigmoid(self.change_logit)


def _norm(c: int) -> nn.GroupNorm:
    return nn.GroupNorm(min(8, c), c)


class _Block(nn.Module):
    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(cin, cout, 3, padding=1, bias=False), _norm(cout), nn.SiLU(),
            nn.Conv2d(cout, cout, 3, padding=1, bias=False), _norm(cout), nn.SiLU(),
        )

    def forward(self, x: Tensor) -> Tensor:
        return self.net(x)


def unet_layers(width: int, levels: int) -> tuple[nn.ModuleList, nn.ModuleList, nn.ModuleList, nn.ModuleList]:
    """The U-Net's (down, enc, up, dec) layers on a ``width``-channel map: ``levels`` resolutions, the
    channels doubled per level, two 3 x 3 conv blocks each (shared by the CNABU and the map networks)."""
    widths = [width * 2**i for i in range(levels)]
    down, enc, up, dec = nn.ModuleList(), nn.ModuleList(), nn.ModuleList(), nn.ModuleList()
    cin = width
    for i, c in enumerate(widths):
        down.append(nn.Identity() if i == 0 else nn.Conv2d(cin, c, 2, stride=2))
        enc.append(_Block(c if i else cin, c))
        cin = c
    for c_hi, c_lo in zip(widths[::-1][:-1], widths[::-1][1:], strict=True):
        up.append(nn.ConvTranspose2d(c_hi, c_lo, 2, stride=2))
        dec.append(_Block(2 * c_lo, c_lo))
    return down, enc, up, dec


def unet(h: Tensor, down: nn.ModuleList, enc: nn.ModuleList, up: nn.ModuleList, dec: nn.ModuleList) -> Tensor:
    """The U-Net of ``unet_layers`` on ``h`` [B, width, X, Y]: encoder, then decoder with skip connections."""
    skips = []
    for d, e in zip(down, enc, strict=True):
        h = e(d(h))
        skips.append(h)
    for u, d, skip in zip(up, dec, skips[::-1][1:], strict=True):
        h = d(torch.cat([u(h), skip], 1))
    return h


class CNABUNet(nn.Module):
    def __init__(self, config: CNABUNetConfig) -> None:
        super().__init__()
        self.config = cfg = config
        z = cfg.grid_shape[2]
        self.embed_belief = nn.Linear(cfg.in_voxel, cfg.embed)
        self.embed_action = nn.Linear(cfg.action_voxel, cfg.action_embed)
        w = cfg.width
        self.stem_belief = nn.Conv2d(z * cfg.embed, w, 2, stride=2)
        self.stem_action = nn.Conv2d(z * cfg.action_embed, w, 2, stride=2, bias=False)
        self.stem_scalars = nn.Linear(cfg.action_scalars, w, bias=False) if cfg.action_scalars else None
        self.down, self.enc, self.up, self.dec = unet_layers(w, cfg.levels)
        self.full = nn.ConvTranspose2d(w, w, 2, stride=2)
        self.column = nn.Conv2d(w, z * cfg.context, 1)
        per_voxel = cfg.context + cfg.in_voxel + cfg.action_voxel
        self.change = nn.Linear(per_voxel, 1) if cfg.change_head else None
        if self.change is not None:  # an untrained model changes (almost) nothing: p_change ~ 0.05
            nn.init.constant_(self.change.bias, -3.0)
        last = nn.Linear(cfg.hidden, 2 + cfg.num_classes)
        nn.init.zeros_(last.weight)  # starts as the identity on the prior
        nn.init.zeros_(last.bias)
        self.evidence = nn.Sequential(nn.Linear(per_voxel, cfg.hidden), nn.SiLU(), last)

    # ------------------------------------------------------------------------------------ pieces
    @staticmethod
    def _flatten_z(vox: Tensor, embed: nn.Linear) -> Tensor:
        """[B, F, X, Y, Z] -> per-voxel embedding flattened over z: [B, Z * E, X, Y]."""
        b, f, x, y, z = vox.shape
        e = torch.matmul(embed.weight, vox.reshape(b, f, -1)) + embed.bias[:, None]  # [B, E, N], channel-first
        return e.reshape(b, -1, x, y, z).permute(0, 4, 1, 2, 3).reshape(b, z * embed.out_features, x, y)

    def _pad(self, m: Tensor) -> Tensor:
        px, py = self.config.padded_xy
        return F.pad(m, (0, py - m.shape[-1], 0, px - m.shape[-2]))

    def belief_stem(self, belief: Tensor) -> Tensor:
        """The belief's share of the stem, [B, width, X'/2, Y'/2] (computed once per belief)."""
        return self.stem_belief(self._pad(self._flatten_z(belief, self.embed_belief)))

    def action_stem(self, action_vox: Tensor, action_scalars: Tensor,
                    nonzero: tuple[Tensor, ...] | None = None) -> Tensor:
        """The action's share: its voxel channels through the stem, its scalars as a per-channel offset.

        The same linear map as ``stem_action(pad(flatten_z(action_vox, embed_action)))``, computed with
        the embedding folded into the stem's kernel and, as the stem's 2 x 2 patches do not overlap,
        as a scatter of the kernel's weights from the action's nonzero voxels only (action channels are
        sparse: a swept volume, a grasped region); the embedding's bias becomes a fixed map over the
        unpadded area. ``nonzero``: ``torch.nonzero(action_vox, as_tuple=True)`` if already computed.
        """
        b, _, x, y, z = action_vox.shape
        kernel, bias_map = self._folded_action_stem(x, y, z)
        k, c, i, j, kz = nonzero if nonzero is not None else torch.nonzero(action_vox, as_tuple=True)
        zf = kernel.shape[1]
        rows = ((kz * zf + c) * 2 + i % 2) * 2 + j % 2
        vals = kernel.reshape(-1, kernel.shape[-1]).index_select(0, rows)  # [N, width]
        if action_vox.dtype != torch.bool:
            vals = vals * action_vox[k, c, i, j, kz].to(vals.dtype)[:, None]
        px, py = self.config.padded_xy
        hx, hy = px // 2, py // 2
        flat = torch.zeros(b * hx * hy, kernel.shape[-1], dtype=kernel.dtype)
        flat.index_add_(0, (k * hx + i // 2) * hy + j // 2, vals)
        m = flat.reshape(b, hx, hy, kernel.shape[-1]).permute(0, 3, 1, 2) + bias_map
        if self.stem_scalars is not None:
            m = m + self.stem_scalars(action_scalars.to(m.dtype))[:, :, None, None]
        return m

    def _folded_action_stem(self, x: int, y: int, z: int) -> tuple[Tensor, Tensor]:
        """The action embedding folded into the stem's kernel, [Z, F, 2, 2, width], and the embedding's
        bias through the stem over the unpadded area, [1, width, X'/2, Y'/2]. Cached while the weights
        are unchanged (their in-place version counters), i.e. computed once at inference; recomputed,
        with gradients, whenever autograd is on."""
        emb, stem = self.embed_action, self.stem_action
        key = (x, y, z, stem.weight._version, emb.weight._version, emb.bias._version,
               id(stem.weight), id(emb.weight), id(emb.bias))
        cached = getattr(self, "_fold_cache", None)
        if torch.is_grad_enabled() or cached is None or cached[0] != key:
            w = stem.weight.reshape(stem.out_channels, z, emb.out_features, 2, 2)
            kernel = torch.einsum("ozekl,ef->zfklo", w, emb.weight)
            inside = self._pad(torch.ones(1, 1, x, y, dtype=kernel.dtype))
            bias_map = F.conv2d(inside, torch.einsum("ozekl,e->okl", w, emb.bias)[:, None], stride=2)
            if torch.is_grad_enabled():
                return kernel, bias_map
            cached = (key, kernel, bias_map)
            object.__setattr__(self, "_fold_cache", cached)
        return cached[1], cached[2]

    def trunk(self, stem: Tensor) -> Tensor:
        """U-Net from the summed stems to full-resolution features [B, width, X', Y'] (padded)."""
        return F.silu(self.full(self._decode(stem)))

    def _decode(self, stem: Tensor) -> Tensor:
        """The U-Net up to its last transposed conv: [B, width, X'/2, Y'/2]."""
        return unet(F.silu(stem), self.down, self.enc, self.up, self.dec)

    def _trunk_rows(self, stem: Tensor) -> Tensor:
        """``trunk`` as per-pixel rows [B * X' * Y', width] in (b, x, y) order: the last transposed conv
        (2 x 2, stride 2: each half-resolution pixel's features map linearly to its 2 x 2 block) as
        one GEMM, its output shuffled into place by one copy."""
        h = self._decode(stem)
        b, w, hx, hy = h.shape
        o = self.full.out_channels
        kernel = self.full.weight.permute(0, 2, 3, 1).reshape(w, 4 * o)  # [in, (a, b, out)]
        t = h.permute(0, 2, 3, 1).reshape(-1, w) @ kernel  # [B * hx * hy, (a, b, out)]
        rows = t.reshape(b, hx, hy, 2, 2, o).permute(0, 1, 3, 2, 4, 5).reshape(-1, o)  # x = 2i + a, y = 2j + b
        return F.silu(rows.add_(self.full.bias), inplace=True)

    def columns(self, stem: Tensor) -> Tensor:
        """U-Net from the summed stems to the column context [B, Z, context, X, Y]."""
        cfg = self.config
        h = self.column(self.trunk(stem))
        x, y, z = cfg.grid_shape
        return h[:, :, :x, :y].reshape(h.shape[0], z, cfg.context, x, y)

    def context(self, stem: Tensor) -> Tensor:
        """Per-voxel context [B, X, Y, Z, context] (channels last)."""
        return self.columns(stem).permute(0, 3, 4, 1, 2)

    def _heads_input(self, ctx: Tensor, belief: Tensor, action_vox: Tensor) -> Tensor:
        """Per-voxel head input [B, X, Y, Z, context + features] (channels last)."""
        return torch.cat([ctx, belief.permute(0, 2, 3, 4, 1), action_vox.permute(0, 2, 3, 4, 1)], -1)

    def _evidence(self, h: Tensor, prior: Tensor) -> Tensor:
        """relu(prior - 1 + scale * out) + 1 for per-voxel inputs h [..., D], prior [..., 2 + C]."""
        return F.relu(prior - 1.0 + self.config.evidence_scale * self.evidence(h)) + 1.0

    def _residual_at(self, prep: PreparedBelief, idx: Tensor, ctx_action: Tensor) -> Tensor:
        """The evidence head's residual ``evidence_scale * out`` at voxels ``idx`` of a prepared belief
        from their [context, action channels] [M, context + Fa], channel-first [2 + C, M]; the evidence
        is ``relu(prior - 1 + residual) + 1`` (``FlatPrediction.evidence``). The first layer's belief
        part comes precomputed per voxel (``prep.hidden``), the activations run in place."""
        cfg = self.config
        first, last = self.evidence[0], self.evidence[2]
        w = first.weight
        w_ca = torch.cat([w[:, :cfg.context], w[:, cfg.context + cfg.in_voxel:]], 1)
        h = prep.hidden.index_select(0, idx).addmm_(ctx_action, w_ca.T)  # [M, hidden], in place
        F.silu(h, inplace=True)
        s = cfg.evidence_scale
        return torch.addmm((s * last.bias)[:, None], s * last.weight, h.T)

    # ---------------------------------------------------------------------------------- forward
    def forward(self, belief: Tensor, prior: Tensor, action_vox: Tensor, action_scalars: Tensor) -> CNABUOutput:
        """All voxels. ``belief`` [B, Fb, X, Y, Z] features, ``prior`` [B, 2 + C, X, Y, Z] evidence
        (alpha, beta, eta), ``action_vox`` [B, Fa, X, Y, Z], ``action_scalars`` [B, S]."""
        ctx = self.context(self.belief_stem(belief) + self.action_stem(action_vox, action_scalars))
        h = self._heads_input(ctx, belief, action_vox)
        ev = self._evidence(h, prior.permute(0, 2, 3, 4, 1)).permute(0, 4, 1, 2, 3)
        logit = self.change(h)[..., 0] if self.change is not None else None
        return CNABUOutput(ev[:, 0], ev[:, 1], ev[:, 2:], logit)

    @torch.no_grad()
    def prepare(self, belief: Tensor, prior: Tensor | None = None, region: Tensor | None = None) -> PreparedBelief:
        """What ``predict_flat`` needs of one belief, computed once for all its candidates: the belief's
        share of the stem, the evidence MLP's and the change head's belief parts (with ``region``
        [1, X, Y, Z], if given, folded in as -inf outside it), and the prior if given (only
        ``FlatPrediction.evidence`` reads it; the belief models blend the residual themselves)."""
        cfg = self.config
        x, y, z = cfg.grid_shape
        nc, nb = cfg.context, cfg.in_voxel
        bf = belief[0].reshape(belief.shape[1], -1)  # [Fb, N]: channel-first, never copied transposed
        base = None
        if self.change is not None:
            wc = self.change.weight[0]
            bias = self.change.bias[0] + self.column.bias.reshape(z, nc) @ wc[:nc]  # [Z]: with the context part's
            base = (wc[nc:nc + nb] @ bf).reshape(x, y, z) + bias
            if region is not None:
                if region.shape[0] != 1:
                    raise ValueError("prepare() folds one region shared by all candidates")
                base = base.masked_fill(~region[0], -math.inf)
        first = self.evidence[0]
        hidden = torch.addmm(first.bias, bf.T, first.weight[:, nc:nc + nb].T)  # the evidence MLP's belief part, rows
        pr = None if prior is None else prior[0].reshape(prior.shape[1], -1)
        return PreparedBelief(self.belief_stem(belief), pr, hidden, base, region is not None and base is not None)

    @torch.no_grad()
    def predict_many(
        self, belief: Tensor | PreparedBelief, prior: Tensor | None, action_vox: Tensor, action_scalars: Tensor,
        threshold: float, region: Tensor | None = None, nonzero: tuple[Tensor, ...] | None = None,
    ) -> list[tuple[Tensor, Tensor, Tensor]]:
        """``predict_flat`` split per action: (indices [M], change probability [M], evidence [M, 2 + C])."""
        out = self.predict_flat(belief, prior, action_vox, action_scalars, threshold, region, nonzero)
        b = [0, *torch.cumsum(out.counts, 0).tolist()]
        ev = out.evidence
        return [(out.idx[s:e], out.p[s:e], ev[:, s:e].T) for s, e in itertools.pairwise(b)]

    @torch.no_grad()
    def predict_flat(
        self, belief: Tensor | PreparedBelief, prior: Tensor | None, action_vox: Tensor, action_scalars: Tensor,
        threshold: float, region: Tensor | None = None, nonzero: tuple[Tensor, ...] | None = None,
    ) -> FlatPrediction:
        """Inference for K actions on one belief (``belief`` [1, Fb, ...], ``prior`` [1, 2 + C, ...], or
        ``belief`` = ``prepare(belief, prior, region)`` and ``prior`` None; ``action_vox`` [K, Fa, ...]).
        Per action (concatenated, see ``FlatPrediction``): flat voxel indices, sorted; change
        probability; the evidence head's residual, at the voxels it changes: p_change > ``threshold``
        (push, grasp) or ``region`` [K or 1, X, Y, Z] (observe: the voxels the view's rays reached),
        always within ``region`` if given. ``nonzero``: ``torch.nonzero(action_vox, as_tuple=True)``
        if the caller has it.

        The same numbers as ``forward`` (up to float rounding; a test), computed sparsely: the
        belief's part once; the action's stem as a scatter from its nonzero voxels; the change head
        (linear) as the sum of its context part (folded into one GEMM width -> Z per pixel), its
        belief part and its action part (only where the action is nonzero); the column conv and the
        evidence head only at the selected voxels, the column conv once per selected column (selected
        voxels come in flat order, so a column's voxels are consecutive)."""
        cfg = self.config
        k_n = action_vox.shape[0]
        x, y, z = cfg.grid_shape
        nc = cfg.context
        if isinstance(belief, PreparedBelief):
            if region is not None and belief.region_folded and region.shape[0] == 1:
                region = None  # already in the prepared logits
            prep = belief
        else:
            shared = region is not None and region.shape[0] == 1 and self.change is not None
            prep = self.prepare(belief, prior, region if shared else None)
            if shared:
                region = None
        nz = nonzero if nonzero is not None else torch.nonzero(action_vox, as_tuple=True)
        stem = prep.stem + self.action_stem(action_vox, action_scalars, nz)
        rows = self._trunk_rows(stem)  # [K * X' * Y', w]
        px, py = self.config.padded_xy
        wcol = self.column.weight[:, :, 0, 0]  # [Z * context, width]
        bcol = self.column.bias
        if self.change is not None:
            wc = self.change.weight[0]
            w_logit = torch.einsum("zcw,c->zw", wcol.reshape(z, nc, -1), wc[:nc])  # context part folded in
            # one GEMM gives the logits in flat voxel order [K, X', Y', Z]: no permutes
            full = (rows @ w_logit.T).reshape(k_n, px, py, z)  # its bias is in prep.base
            ak, ac, ai, aj, az = nz  # the action channels' part, only where they are nonzero
            av_nz = wc[nc + cfg.in_voxel:][ac]
            if action_vox.dtype != torch.bool:
                av_nz = av_nz * action_vox[ak, ac, ai, aj, az].to(rows.dtype)
            full.index_put_((ak, ai, aj, az), av_nz, accumulate=True)
            logits = full[:, :x, :y]
            logits += prep.base  # [X, Y, Z], -inf outside a folded region
            sel_all = logits > math.log(threshold / (1.0 - threshold))
            if region is not None:
                sel_all &= region.reshape(region.shape[0], x, y, z)
        else:
            if region is None:
                raise ValueError("an observe network needs the region its view reached")
            sel_all = region.reshape(region.shape[0], x, y, z).expand(k_n, -1, -1, -1)
        # every selected (candidate, voxel) at once: one column conv per selected column, one evidence MLP call
        pos = flat_nonzero(sel_all)  # sorted: a candidate's voxels, and a column's, are consecutive
        n = x * y * z
        kk = pos // n
        idx = pos - kk * n
        cols, inverse = torch.unique_consecutive(pos // z, return_inverse=True)  # (candidate, x, y) columns
        kz = pos - cols.index_select(0, inverse) * z
        ck, cxy = cols // (x * y), cols % (x * y)  # row gathers by index_select: much faster than indexing
        col_row = (ck * px + cxy // y) * py + cxy % y  # each column's row in the padded maps
        per_col = torch.addmm(bcol, rows.index_select(0, col_row), wcol.T)
        c = per_col.reshape(-1, nc).index_select(0, inverse * z + kz)  # [M, context]
        fa = action_vox.shape[1]
        flat_action = action_vox.reshape(-1)
        at = kk * (fa * n) + idx
        av = torch.stack([flat_action.index_select(0, at + f * n) for f in range(fa)], 1)
        res = self._residual_at(prep, idx, torch.cat([c, av.to(c.dtype)], -1))
        if self.change is not None:
            p_sel = torch.sigmoid(full.reshape(-1).index_select(0, col_row.index_select(0, inverse) * z + kz))
        else:
            p_sel = torch.ones(len(idx))
        return FlatPrediction(torch.bincount(kk, minlength=k_n), idx, p_sel, res, prep.pr)


@dataclass
class FlatPrediction:
    """K actions' predictions concatenated in action order (``CNABUNet.predict_flat``)."""

    counts: Tensor
    """[K] selected voxels per action."""
    idx: Tensor
    """[M] flat voxel indices, sorted within each action."""
    p: Tensor
    """[M] change probability (1 for observe)."""
    residual: Tensor
    """[2 + C, M] the evidence head's residual on the prior (``evidence_scale * out``), channel-first."""
    prior: Tensor | None
    """[2 + C, X * Y * Z] the belief's evidence (alpha, beta, eta), if it was given."""

    @property
    def evidence(self) -> Tensor:
        """[2 + C, M] new evidence ``relu(prior - 1 + residual) + 1`` (the belief models fuse this into
        their blend instead of gathering the prior here)."""
        if self.prior is None:
            raise ValueError("FlatPrediction.evidence needs the prior: pass it to predict_flat / prepare")
        return F.relu(self.prior.index_select(1, self.idx) - 1.0 + self.residual) + 1.0

    @staticmethod
    def cat(parts: list[FlatPrediction]) -> FlatPrediction:
        if len(parts) == 1:
            return parts[0]
        return FlatPrediction(torch.cat([q.counts for q in parts]), torch.cat([q.idx for q in parts]),
                              torch.cat([q.p for q in parts]), torch.cat([q.residual for q in parts], 1),
                              parts[0].prior)


@dataclass
class PreparedBelief:
    """One belief as ``CNABUNet.predict_many`` reuses it over its candidates (``CNABUNet.prepare``)."""

    stem: Tensor
    """The belief's share of the stem, [1, width, X'/2, Y'/2]."""
    pr: Tensor | None
    """Prior evidence, [2 + C, X * Y * Z] (None if not given)."""
    hidden: Tensor
    """The evidence MLP's first layer on the belief features, with its bias, [X * Y * Z, hidden] (rows:
    gathered per selected voxel)."""
    base: Tensor | None
    """The change head's belief part and all its biases (its own, the column conv's through it), [X, Y, Z]
    (-inf outside a folded region); None for observe."""
    region_folded: bool


def flat_nonzero(mask: Tensor) -> Tensor:
    """Sorted flat positions of the True entries of a bool tensor, as ``torch.nonzero(mask.reshape(-1))``.
    For sparse, clustered masks (changed voxels come in z-runs) scanning 8 bytes at a time as int64
    words and expanding only the nonzero words is about twice as fast."""
    flat = mask.reshape(-1)
    if flat.numel() % 8 or flat.dtype != torch.bool:
        return torch.nonzero(flat).squeeze(1)
    words = torch.nonzero(flat.view(torch.int64)).squeeze(1)
    bytes_ = torch.nonzero(flat.view(-1, 8).index_select(0, words))
    return words.index_select(0, bytes_[:, 0]) * 8 + bytes_[:, 1]


def parameter_bytes(model: nn.Module) -> int:
    """Size of the float32 state dict's tensors."""
    return sum(t.numel() * t.element_size() for t in model.state_dict().values())
