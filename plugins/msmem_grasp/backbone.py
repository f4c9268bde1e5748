"""A PTv3-style point transformer in plain PyTorch (paper eq. FE-vMF_inference: f = PTv3(pcd)).

Point Transformer V3 (Wu et al. 2024) replaces neighbourhood search by *serialisation*: points are
quantised to a grid, sorted along a space-filling curve, and the sorted sequence is cut into patches
of ``patch_size`` points; self-attention runs only inside a patch. Here, as in PTv3:

- z-order (Morton) and Hilbert curves, each also with x and y swapped ("-trans"), alternate across
  layers, so a point meets different neighbours at every depth;
- patches are shifted by half a patch on every other layer, so information crosses patch borders;
- pre-norm residual blocks (attention, MLP), with a conditional positional encoding before each.

Deviations (no CUDA extensions: spconv's backward needs CUDA, see ENV-NOTES): the positional
encoding is an MLP on each point's offset from its patch centroid instead of PTv3's sparse-conv
xCPE; there is no grid pooling (U-Net) stage, so all layers run at full resolution; several points
may share a grid cell (ties are broken by the exact coordinates and features, and exact duplicates
are run once, so the output is exactly permutation-equivariant).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

Order = Literal["z", "z-trans", "hilbert", "hilbert-trans"]
MAX_BITS = 10
"""Bits per axis of the curve encoders: 1024 cells per axis (10.24 m at 1 cm)."""


# --------------------------------------------------------------------------------------------- curves
def _spread_bits(v: Tensor) -> Tensor:
    """Insert two zero bits between the lowest 10 bits of v (int64): b9..b0 -> b9 0 0 b8 0 0 ... b0."""
    v = v & 0x3FF
    v = (v | (v << 16)) & 0x30000FF
    v = (v | (v << 8)) & 0x300F00F
    v = (v | (v << 4)) & 0x30C30C3
    v = (v | (v << 2)) & 0x9249249
    return v


def morton_encode(grid: Tensor) -> Tensor:
    """z-order code [N] (int64) of integer cells grid [N, 3] in [0, 1024): bits interleaved x, y, z (x highest)."""
    g = grid.long()
    return (_spread_bits(g[:, 0]) << 2) | (_spread_bits(g[:, 1]) << 1) | _spread_bits(g[:, 2])


def hilbert_encode(grid: Tensor, bits: int = MAX_BITS) -> Tensor:
    """Hilbert code [N] (int64) of integer cells grid [N, 3] in [0, 2^bits).

    Skilling's method ("Programming the Hilbert curve", 2004): turn the coordinates into the
    "transposed" Hilbert index by undoing the per-level reflections/exchanges and Gray-coding, then
    interleave the bits (axis 0 most significant). Consecutive codes are 6-connected cells.
    """
    x = [grid[:, i].long().clone() for i in range(3)]
    m = 1 << (bits - 1)
    q = m
    while q > 1:  # inverse undo
        p = q - 1
        for i in range(3):
            has = (x[i] & q) != 0
            t = (x[0] ^ x[i]) & p
            x0_new = torch.where(has, x[0] ^ p, x[0] ^ t)
            if i > 0:
                x[i] = torch.where(has, x[i], x[i] ^ t)
            x[0] = x0_new
        q >>= 1
    for i in range(1, 3):  # Gray encode
        x[i] = x[i] ^ x[i - 1]
    t = torch.zeros_like(x[0])
    q = m
    while q > 1:
        t = torch.where((x[2] & q) != 0, t ^ (q - 1), t)
        q >>= 1
    x = [xi ^ t for xi in x]
    code = torch.zeros_like(x[0])
    for b in range(bits - 1, -1, -1):
        for i in range(3):
            code = (code << 1) | ((x[i] >> b) & 1)
    return code


def encode(grid: Tensor, order: Order) -> Tensor:
    """Space-filling-curve code of integer cells for one of the four PTv3 orders."""
    if order.endswith("-trans"):
        grid = grid[:, [1, 0, 2]]
    return morton_encode(grid) if order.startswith("z") else hilbert_encode(grid)


# ------------------------------------------------------------------------------------ serialisation
@dataclass(frozen=True)
class PatchLayout:
    """Where every point sits in the padded patch tensor of one (order, shift).

    ``index`` [num_patches, patch_size]: point index per slot, N (a zero row) for padding;
    ``valid`` [num_patches, patch_size]: slot holds a point; ``slot`` [N]: flat slot of each point.
    """

    index: Tensor
    valid: Tensor
    slot: Tensor


def serialise(grid: Tensor, batch: Tensor, order: Order) -> Tensor:
    """Permutation [N] sorting points by (cloud, curve code); ties keep the current order (stable)."""
    perm = torch.sort(encode(grid, order), stable=True).indices
    return perm[torch.sort(batch[perm], stable=True).indices]


def canonical(points: Tensor, feats: Tensor | None, batch: Tensor) -> tuple[Tensor, Tensor]:
    """(rep [M], inverse [N]): one representative per distinct (cloud, point, features) row, listed in
    lexicographic row order, and each point's representative. Running the network on ``rep`` in this
    order makes ties in the curve code (points sharing a cell) independent of the input order, and
    identical points get identical outputs, so the network is exactly permutation-equivariant."""
    rows = [batch[:, None].to(points.dtype), points.detach()]
    if feats is not None:
        rows.append(feats.detach().to(points.dtype))
    table = torch.cat(rows, 1)
    perm = torch.arange(len(points), device=points.device)
    for col in reversed(range(table.shape[1])):  # lexicographic: stable sorts, least significant first
        perm = perm[torch.sort(table[perm, col], stable=True).indices]
    ordered = table[perm]
    first = torch.ones(len(points), dtype=torch.bool, device=points.device)
    first[1:] = (ordered[1:] != ordered[:-1]).any(1)
    rep = perm[first]
    inverse = torch.empty_like(perm)
    inverse[perm] = torch.cumsum(first, 0) - 1
    return rep, inverse


def patch_layout(perm: Tensor, batch: Tensor, patch_size: int, shift: int) -> PatchLayout:
    """Cut each cloud's serialised sequence into patches after ``shift`` leading pad slots."""
    n = len(perm)
    counts = torch.bincount(batch, minlength=int(batch.max()) + 1 if n else 1)
    padded = ((counts + shift + patch_size - 1) // patch_size) * patch_size
    padded = torch.where(counts > 0, padded, torch.zeros_like(padded))
    start = torch.cumsum(padded, 0) - padded  # first slot of each cloud
    first = torch.cumsum(counts, 0) - counts  # first sorted position of each cloud
    b_sorted = batch[perm]
    rank = torch.arange(n, device=perm.device) - first[b_sorted]
    slot_sorted = start[b_sorted] + shift + rank
    total = int(padded.sum())
    index = torch.full((total,), n, dtype=torch.long, device=perm.device)
    index[slot_sorted] = perm
    slot = torch.empty(n, dtype=torch.long, device=perm.device)
    slot[perm] = slot_sorted
    index = index.view(-1, patch_size)
    return PatchLayout(index=index, valid=index < n, slot=slot)


# ---------------------------------------------------------------------------------------- modules
class PatchAttention(nn.Module):
    """Multi-head self-attention inside each patch; padded slots are masked as keys."""

    def __init__(self, dim: int, heads: int) -> None:
        super().__init__()
        if dim % heads:
            raise ValueError(f"dim {dim} is not divisible by heads {heads}")
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: Tensor, valid: Tensor) -> Tensor:
        p, s, d = x.shape
        qkv = self.qkv(x).view(p, s, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        mask = valid[:, None, None, :]  # [P, 1, 1, S]: True = attend to this key
        out = F.scaled_dot_product_attention(qkv[0], qkv[1], qkv[2], attn_mask=mask)
        return self.proj(out.transpose(1, 2).reshape(p, s, d))


class Block(nn.Module):
    """Pre-norm transformer block: x += CPE(offset to patch centroid); x += Attn(LN x); x += MLP(LN x)."""

    def __init__(self, dim: int, heads: int, mlp_ratio: float) -> None:
        super().__init__()
        hidden = int(dim * mlp_ratio)
        self.cpe = nn.Sequential(nn.Linear(3, dim), nn.GELU(), nn.Linear(dim, dim))
        self.norm1 = nn.LayerNorm(dim)
        self.attn = PatchAttention(dim, heads)
        self.norm2 = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, dim))

    def forward(self, x: Tensor, rel: Tensor, valid: Tensor) -> Tensor:
        x = x + self.cpe(rel)
        x = x + self.attn(self.norm1(x), valid)
        return x + self.mlp(self.norm2(x))


class PointTransformer(nn.Module):
    """Serialised patch-attention encoder: points [N, 3] (+ feats [N, F]) -> features [N, dim].

    ``orders`` cycle over the layers; with ``shift_patches`` odd layers shift the patch borders by
    half a patch. ``grid_m`` is the quantisation cell of the serialisation and ``pos_scale_m`` the
    length that positions are divided by before they enter an MLP.
    """

    def __init__(
        self,
        dim: int = 64,
        layers: int = 4,
        heads: int = 4,
        patch_size: int = 128,
        in_features: int = 0,
        grid_m: float = 0.01,
        mlp_ratio: float = 4.0,
        pos_scale_m: float = 0.1,
        orders: Sequence[Order] = ("z", "hilbert", "z-trans", "hilbert-trans"),
        shift_patches: bool = True,
    ) -> None:
        super().__init__()
        if patch_size < 2 or layers < 1 or not orders:
            raise ValueError("need patch_size >= 2, layers >= 1 and at least one order")
        self.dim, self.patch_size, self.in_features = dim, patch_size, in_features
        self.grid_m, self.pos_scale_m = grid_m, pos_scale_m
        self.orders: tuple[Order, ...] = tuple(orders)
        self.shift_patches = shift_patches
        self.embed = nn.Sequential(nn.Linear(3 + in_features, dim), nn.GELU(), nn.Linear(dim, dim))
        self.blocks = nn.ModuleList(Block(dim, heads, mlp_ratio) for _ in range(layers))
        self.norm = nn.LayerNorm(dim)

    def layer_schedule(self) -> list[tuple[Order, int]]:
        """(order, shift) of every layer."""
        half = self.patch_size // 2 if self.shift_patches else 0
        return [(self.orders[i % len(self.orders)], half * (i % 2)) for i in range(len(self.blocks))]

    def quantise(self, points: Tensor, batch: Tensor) -> Tensor:
        """Integer grid cells [N, 3] relative to each cloud's minimum corner."""
        nb = int(batch.max()) + 1
        lo = torch.full((nb, 3), float("inf"), dtype=points.dtype, device=points.device)
        lo = lo.scatter_reduce(0, batch[:, None].expand(-1, 3), points, reduce="amin")
        grid = torch.floor((points - lo[batch]) / self.grid_m).long()
        if int(grid.max()) >= 1 << MAX_BITS:
            raise ValueError(f"cloud spans more than {1 << MAX_BITS} cells of {self.grid_m} m; raise grid_m")
        return grid

    def _layouts(self, points: Tensor, batch: Tensor) -> list[PatchLayout]:
        """Patch layout of every layer for distinct points in canonical order."""
        grid = self.quantise(points.detach(), batch)
        perms: dict[Order, Tensor] = {}
        out = []
        for order, shift in self.layer_schedule():
            if order not in perms:
                perms[order] = serialise(grid, batch, order)
            out.append(patch_layout(perms[order], batch, self.patch_size, shift))
        return out

    def layouts(self, points: Tensor, feats: Tensor | None = None, batch: Tensor | None = None) -> list[PatchLayout]:
        """The patch layout of every layer in terms of the input points (for tests and inspection);
        duplicates of a point share its slot and only the representative is listed in ``index``."""
        batch = torch.zeros(len(points), dtype=torch.long, device=points.device) if batch is None else batch.long()
        rep, inverse = canonical(points, feats, batch)
        rep_pad = torch.cat([rep, rep.new_full((1,), len(points))])  # padding slots -> N
        out = []
        for lay in self._layouts(points[rep], batch[rep]):
            out.append(PatchLayout(index=rep_pad[lay.index], valid=lay.valid, slot=lay.slot[inverse]))
        return out

    def forward(self, points: Tensor, feats: Tensor | None = None, batch: Tensor | None = None) -> Tensor:
        """Per-point features [N, dim]. ``batch`` [N] (int64) separates clouds that share no patch."""
        if (feats is None) != (self.in_features == 0):
            got = None if feats is None else tuple(feats.shape)
            raise ValueError(f"model expects {self.in_features} input features, got {got}")
        if len(points) == 0:
            return points.new_zeros((0, self.dim))
        batch = torch.zeros(len(points), dtype=torch.long, device=points.device) if batch is None else batch.long()
        rep, inverse = canonical(points, feats, batch)
        points, batch = points[rep], batch[rep]
        feats = None if feats is None else feats[rep]
        nb = int(batch.max()) + 1
        count = torch.bincount(batch, minlength=nb).to(points.dtype)[:, None]
        centre = torch.zeros((nb, 3), dtype=points.dtype, device=points.device).index_add_(0, batch, points) / count
        local = (points - centre[batch]) / self.pos_scale_m
        x = self.embed(local if feats is None else torch.cat([local, feats], dim=1))
        local_pad = torch.cat([local, local.new_zeros(1, 3)])
        for block, layout in zip(self.blocks, self._layouts(points, batch), strict=True):
            valid = layout.valid
            pos = local_pad[layout.index]  # [P, S, 3], zeros at padding
            w = valid.to(pos.dtype)[..., None]
            centroid = (pos * w).sum(1, keepdim=True) / w.sum(1, keepdim=True).clamp_min(1.0)
            rel = (pos - centroid) * w
            xp = torch.cat([x, x.new_zeros(1, self.dim)])[layout.index]
            xp = block(xp, rel, valid)
            x = xp.reshape(-1, self.dim)[layout.slot]
        return self.norm(x)[inverse]

    def forward_list(self, clouds: Sequence[Tensor], feats: Sequence[Tensor] | None = None) -> list[Tensor]:
        """Per-cloud features for a list of clouds, run as one batch."""
        sizes = [len(c) for c in clouds]
        batch = torch.repeat_interleave(torch.arange(len(clouds)), torch.tensor(sizes)).to(clouds[0].device)
        out = self(torch.cat(list(clouds)), None if feats is None else torch.cat(list(feats)), batch)
        return list(out.split(sizes))
