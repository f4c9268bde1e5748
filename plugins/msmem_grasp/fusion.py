"""FE-UMGF: full-evidential uncertainty-guided multi-view grasp fusion (paper sec. FE-UMGF).

A global grasp buffer G_t is updated every step with the current per-point predictions G'_t
(FE-vMF, or the geometric fallback, on the FPP cloud of the current belief):

- *Decay*: every buffered grasp's evidence is multiplied by gamma (``decay``, ~0.99 per step):
  the Beta evidence alpha, beta and the vMF natural parameters kappa*mu of a_hat and b.
- *Matching*: a new grasp (contact c', baseline b', width w') joins the buffered grasp (c, b) with
  the nearest contact within ``match_radius_m`` whose baseline agrees, ``cos(b, b') > min_abs_cos``
  (0.86, ~30 deg). A grasp is one physical grasp whichever of its two contacts names it: a new grasp
  whose *opposite* contact c' + w' b' lies within the radius of c with ``cos(b, b') < -min_abs_cos``
  is the same grasp seen from its other side; b' is flipped and its contact swapped (c' <- c' + w' b')
  before it is summed. The nearest qualifying match wins (one KD-tree query per representation).
- *Fusion* per cluster (paper eq. for alpha_t, beta_t): ``alpha = gamma * alpha_old + sum(alpha_new)``
  and likewise beta; orientation as ViSO-Grasp: natural parameters ``kappa * mu`` of b and of a_hat
  are summed (a_hat is never flipped: the approach of a grasp does not depend on which contact names
  it), and mean and concentration are recovered as ``mu = eta / |eta|``, ``kappa = |eta|``; the
  approach is then the projection of mu_a_hat orthogonal to mu_b (eq. proj). The width is the
  evidence-weighted (S = alpha + beta) mean. The cluster keeps its contact (the cluster centre).
- *New clusters*: unmatched new grasps are appended.
- *After a manipulation* (``confirm``): the first update keeps only the buffered grasps that a new
  grasp of the post-manipulation view matches; the others were about geometry that may have moved.
- *Stale grasps*: a grasp whose contact left the believed surface (no voxel of the 3x3x3 around the
  contact believed occupied: expected occupancy <= ``surface_threshold`` = 0.5, i.e. believed free
  or back to the prior after a manipulation; or outside the grid) is dropped; so are the weakest
  (smallest S) beyond ``max_grasps``.

Everything is array code over all grasps at once (``scipy.spatial.cKDTree`` for the matching,
``np.add.at`` for the sums); no Python loop touches a grasp or a point.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from msmem_core.world.geometry import F64

if TYPE_CHECKING:
    from msmem_core.map.belief import EvidentialMap
    from msmem_grasp.fevmf import GraspPrediction


def _unit(v: F64) -> tuple[F64, F64]:
    """(v / |v|, |v|) row-wise; zero rows give (0, 0)."""
    n = np.linalg.norm(v, axis=-1)
    return v / np.maximum(n, 1e-300)[..., None], n


def project_approach_np(a_hat: F64, b: F64, kappa_a_hat: F64 | None = None) -> tuple[F64, F64]:
    """Eq. proj in numpy: mu_a = P_b a_hat / |P_b a_hat|, kappa_a = kappa_a_hat |P_b a_hat|.
    Where a_hat is parallel to b any direction orthogonal to b is returned (kappa_a ~ 0)."""
    b, _ = _unit(b)
    r = a_hat - np.einsum("nk,nk->n", a_hat, b)[:, None] * b
    a, norm = _unit(r)
    helper = np.where(np.abs(b[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    fallback, _ = _unit(np.cross(b, helper))
    a = np.where(norm[:, None] > 1e-9, a, fallback)
    kappa = (np.ones(len(a)) if kappa_a_hat is None else kappa_a_hat) * norm
    return a, kappa


@dataclass(frozen=True)
class GraspHypotheses:
    """Evidential grasps at contacts (numpy float64): contact [N, 3]; mu_a_hat [N, 3] (unit) and
    kappa_a_hat [N]; mu_b [N, 3] (unit, directed from the contact into the object) and kappa_b [N];
    Beta affordance evidence alpha, beta [N] (>= 1 per prediction); width [N] (m)."""

    contact: F64
    mu_a_hat: F64
    kappa_a_hat: F64
    mu_b: F64
    kappa_b: F64
    alpha: F64
    beta: F64
    width: F64

    def __len__(self) -> int:
        return len(self.alpha)

    @classmethod
    def empty(cls) -> GraspHypotheses:
        z3, z = np.zeros((0, 3)), np.zeros(0)
        return cls(z3, z3.copy(), z.copy(), z3.copy(), z.copy(), z.copy(), z.copy(), z.copy())

    @classmethod
    def from_prediction(cls, points: NDArray[np.floating], pred: GraspPrediction) -> GraspHypotheses:
        """Per-point FE-vMF outputs (torch) at the cloud's points."""
        def f(t: Any) -> F64:
            return np.asarray(t.detach().double().cpu().numpy(), dtype=np.float64)

        return cls(np.asarray(points, dtype=np.float64).reshape(-1, 3), f(pred.mu_a_hat), f(pred.kappa_a_hat),
                   f(pred.mu_b), f(pred.kappa_b), f(pred.alpha), f(pred.beta), f(pred.width))

    def subset(self, keep: NDArray[np.bool_] | NDArray[np.intp]) -> GraspHypotheses:
        return GraspHypotheses(**{f.name: getattr(self, f.name)[keep] for f in fields(self)})

    @classmethod
    def concat(cls, items: list[GraspHypotheses]) -> GraspHypotheses:
        if not items:
            return cls.empty()
        return cls(**{f.name: np.concatenate([getattr(g, f.name) for g in items]) for f in fields(cls)})

    @property
    def opposite(self) -> F64:
        """The other contact, c + w b."""
        return self.contact + self.width[:, None] * self.mu_b

    @property
    def evidence(self) -> F64:
        """S = alpha + beta."""
        return self.alpha + self.beta

    @property
    def affordance(self) -> F64:
        """E[q] = alpha / S (eq. occ_beta2)."""
        return self.alpha / self.evidence

    @property
    def uncertainty(self) -> F64:
        """chi = 2 / S (eq. occ_beta2)."""
        return 2.0 / self.evidence

    def approach(self) -> tuple[F64, F64]:
        """(mu_a, kappa_a): a_hat projected orthogonal to b (eq. proj)."""
        return project_approach_np(self.mu_a_hat, self.mu_b, self.kappa_a_hat)

    def poses(self) -> F64:
        """Executable gripper poses [N, 4, 4]: centre c + (w/2) b, frame (b, a x b, a)."""
        from msmem_grasp.fevmf import executable_grasp  # torch: imported on use

        a, _ = self.approach()
        out: F64 = executable_grasp(self.contact, a, self.mu_b, self.width)  # type: ignore[assignment]
        return out


class FusionConfig(BaseModel):
    """FE-UMGF parameters (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    match_radius_m: float = Field(0.01, gt=0.0, le=0.1)
    """A new grasp joins a buffered one whose contact is at most this far (paper: 1 cm)."""
    min_abs_cos: float = Field(0.86, ge=0.0, lt=1.0)
    """... and whose baseline agrees: |cos(b, b')| above this (0.86 ~ 30 deg)."""
    decay: float = Field(0.99, gt=0.0, le=1.0)
    """gamma: evidence kept per step (Beta evidence and vMF natural parameters)."""
    surface_threshold: float = Field(0.5, ge=0.0, lt=1.0)
    """A contact is on the believed surface while some voxel within ``surface_radius_voxels`` has
    expected occupancy above this (a region reset to the prior, p = 0.5, is not a surface)."""
    surface_radius_voxels: int = Field(1, ge=0, le=5)
    neighbours: int = Field(8, ge=1, le=64)
    """Buffered grasps examined per query (the nearest ones within the radius)."""
    max_grasps: int = Field(20000, ge=1)
    """Buffer capacity; beyond it the grasps with the least evidence S are dropped."""


@dataclass(frozen=True)
class FusionStats:
    """What one ``GraspBuffer.update`` did."""

    new: int
    matched: int
    flipped: int
    added: int
    dropped_stale: int
    dropped_capacity: int
    size: int
    dropped_unconfirmed: int = 0
    """Buffered grasps no new grasp matched, dropped because the update was to ``confirm`` them."""


class GraspBuffer:
    """The global grasp buffer G_t of FE-UMGF (see the module docstring)."""

    def __init__(self, config: FusionConfig | None = None) -> None:
        self.config = config or FusionConfig()
        self.clear()

    def clear(self) -> None:
        z3, z = np.zeros((0, 3)), np.zeros(0)
        self.contact: F64 = z3
        self.eta_a: F64 = z3.copy()
        """sum of kappa_a_hat * mu_a_hat per cluster (decayed)."""
        self.eta_b: F64 = z3.copy()
        """sum of kappa_b * mu_b per cluster (decayed)."""
        self.alpha: F64 = z
        self.beta: F64 = z.copy()
        self.width: F64 = z.copy()
        self.hits: NDArray[np.int64] = np.zeros(0, np.int64)
        """Predictions fused into each cluster so far (itself included)."""
        self.steps = 0

    def __len__(self) -> int:
        return len(self.alpha)

    # ----------------------------------------------------------------------------------- reading
    def hypotheses(self) -> GraspHypotheses:
        """The fused grasps: mean and concentration recovered from the natural parameters."""
        mu_a, ka = _unit(self.eta_a)
        mu_b, kb = _unit(self.eta_b)
        return GraspHypotheses(self.contact.copy(), mu_a, ka, mu_b, kb, self.alpha.copy(), self.beta.copy(),
                               self.width.copy())

    # ---------------------------------------------------------------------------------- updating
    def _match(self, new: GraspHypotheses) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Per new grasp: index of the buffered grasp it joins (-1: none) and whether it is flipped."""
        from scipy.spatial import cKDTree
        cfg = self.config
        n = len(new)
        target = np.full(n, -1, np.int64)
        flipped = np.zeros(n, dtype=bool)
        if not len(self) or not n:
            return target, flipped
        tree = cKDTree(self.contact)
        k = min(cfg.neighbours, len(self))
        best = np.full(n, np.inf)
        for points, sign in ((new.contact, 1.0), (new.opposite, -1.0)):
            dist, idx = tree.query(points, k=k, distance_upper_bound=cfg.match_radius_m)
            dist, idx = dist.reshape(n, k), idx.reshape(n, k)
            found = idx < len(self)
            safe = np.where(found, idx, 0)
            mu_b = self.eta_b[safe] / np.maximum(np.linalg.norm(self.eta_b[safe], axis=-1, keepdims=True), 1e-300)
            cos = np.einsum("nkd,nd->nk", mu_b, new.mu_b)
            ok = found & (sign * cos > cfg.min_abs_cos)
            d = np.where(ok, dist, np.inf)
            j = np.argmin(d, axis=1)  # neighbours come sorted by distance: the nearest qualifying one
            dj = d[np.arange(n), j]
            better = dj < best
            best[better] = dj[better]
            target[better] = safe[np.arange(n), j][better]
            flipped[better] = sign < 0
        return target, flipped

    def update(self, new: GraspHypotheses, belief: EvidentialMap | None = None, confirm: bool = False) -> FusionStats:
        """G_t <- FE-UMGF(G_{t-1}, G'_t); with ``belief``, grasps off its surface are dropped. With
        ``confirm`` (the first update after a manipulation), buffered grasps that no new grasp matches
        are dropped: only the hypotheses the post-manipulation view confirms are kept."""
        cfg = self.config
        unconfirmed = 0
        if confirm and len(self):
            joined = np.zeros(len(self), dtype=bool)
            target, _ = self._match(new)
            joined[target[target >= 0]] = True
            unconfirmed = int((~joined).sum())
            self._keep(joined)
        gamma = cfg.decay
        self.alpha = gamma * self.alpha
        self.beta = gamma * self.beta
        self.eta_a = gamma * self.eta_a
        self.eta_b = gamma * self.eta_b
        target, flipped = self._match(new)
        m = target >= 0
        if m.any():
            t = target[m]
            sign = np.where(flipped[m], -1.0, 1.0)
            s_old = self.alpha + self.beta  # decayed
            s_new = new.alpha[m] + new.beta[m]
            w_sum = s_old * self.width
            np.add.at(w_sum, t, s_new * new.width[m])
            np.add.at(self.alpha, t, new.alpha[m])
            np.add.at(self.beta, t, new.beta[m])
            np.add.at(self.eta_b, t, (sign * new.kappa_b[m])[:, None] * new.mu_b[m])
            np.add.at(self.eta_a, t, new.kappa_a_hat[m][:, None] * new.mu_a_hat[m])
            np.add.at(self.hits, t, 1)
            self.width = w_sum / np.maximum(self.alpha + self.beta, 1e-300)
        add = new.subset(~m)
        self.contact = np.concatenate([self.contact, add.contact])
        self.eta_a = np.concatenate([self.eta_a, add.kappa_a_hat[:, None] * add.mu_a_hat])
        self.eta_b = np.concatenate([self.eta_b, add.kappa_b[:, None] * add.mu_b])
        self.alpha = np.concatenate([self.alpha, add.alpha])
        self.beta = np.concatenate([self.beta, add.beta])
        self.width = np.concatenate([self.width, add.width])
        self.hits = np.concatenate([self.hits, np.ones(len(add), np.int64)])
        stale = 0
        if belief is not None:
            keep = self.on_surface(belief)
            stale = int((~keep).sum())
            self._keep(keep)
        over = max(0, len(self) - cfg.max_grasps)
        if over:
            order = np.argsort(-(self.alpha + self.beta), kind="stable")
            keep = np.zeros(len(self), dtype=bool)
            keep[order[: cfg.max_grasps]] = True
            self._keep(keep)
        self.steps += 1
        return FusionStats(len(new), int(m.sum()), int((flipped & m).sum()), len(add), stale, over, len(self),
                           unconfirmed)

    def on_surface(self, belief: EvidentialMap) -> NDArray[np.bool_]:
        """[N]: the contact's voxel neighbourhood (radius ``surface_radius_voxels``) holds a voxel with
        expected occupancy above ``surface_threshold`` (believed occupied); contacts outside the grid
        are not on it."""
        from scipy import ndimage
        if not len(self):
            return np.zeros(0, dtype=bool)
        cfg = self.config
        grid = belief.grid
        p = belief.expected_occupancy()
        r = cfg.surface_radius_voxels
        near = ndimage.maximum_filter(p, size=2 * r + 1, mode="constant", cval=0.0) if r > 0 else p
        ijk = grid.index_of(self.contact)
        inside = grid.contains_index(ijk)
        out = np.zeros(len(self), dtype=bool)
        ii = ijk[inside]
        out[inside] = near[ii[:, 0], ii[:, 1], ii[:, 2]] > cfg.surface_threshold
        return out

    def _keep(self, keep: NDArray[np.bool_]) -> None:
        for name in ("contact", "eta_a", "eta_b", "alpha", "beta", "width", "hits"):
            setattr(self, name, getattr(self, name)[keep])

    def state(self) -> dict[str, Any]:
        """A copy of the buffer's arrays (for tests and logging)."""
        return {name: np.array(getattr(self, name)) for name in
                ("contact", "eta_a", "eta_b", "alpha", "beta", "width", "hits")}
