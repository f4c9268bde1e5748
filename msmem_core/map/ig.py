"""Volumetric information gain of candidate views (paper eq. oig, after MEM's NBV planner).

``IG(v | Phi) = sum_{rays of v} sum_k H(p_k) prod_{j<k} (1 - p_j)`` along each ray's exact voxel
traversal from the camera, with ``p`` the expected occupancy clamped as MEM (> 0.95 -> 1,
< 0.05 -> 0, shelf boards occupied) and ``H`` the binary Shannon entropy of the clamped ``p`` in
**nats** (an unknown voxel contributes ln 2 = 0.693). Rays run from the near to the far plane of the
camera; t along a ray is the z-depth. Views visited since the last manipulation get no IG: callers
pass them as ``excluded`` to :meth:`IGService.best_two_step`.
"""

from __future__ import annotations

import hashlib
import itertools
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, Field

from msmem_core.map import raycast
from msmem_core.map.belief import BeliefDelta, EvidentialMap, _xlogx, bernoulli_entropy, categorical_entropy
from msmem_core.map.gain import sums_pairwise, voxel_information, voxel_information_of
from msmem_core.util.interrupt import deferred_interrupt
from msmem_core.util.trace import span
from msmem_core.util.validation import MODEL_CONFIG, Int
from msmem_core.world.camera import CameraConfig
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ShelfSpec


class IGConfig(BaseModel):
    """How IG is computed."""

    model_config = MODEL_CONFIG

    ray_stride_px: Int = Field(8, ge=1)
    """Cast a ray through every n-th pixel in u and v (640x480 / 8 = 80x60 = 4800 rays per view)."""
    early_exit: float = Field(1e-3, ge=0.0, lt=1.0)
    """Stop a ray once its transmission is <= this; error per ray <= early_exit * entropy left on it."""
    p_occ_clamp: float = Field(0.95, gt=0.5, le=1.0)
    """Expected occupancy above this counts as certainly occupied (p = 1, H = 0), as MEM."""
    p_free_clamp: float = Field(0.05, ge=0.0, lt=0.5)
    """Expected occupancy below this counts as certainly free (p = 0, H = 0), as MEM."""
    never_observed: Literal["belief", "prior"] = "belief"
    """The entropy IG counts on a voxel no camera ray has reached, for a belief that keeps a ray record
    (``EvidentialMap.observed``: ``cnabu-map``). ``belief``: the entropy of the predicted occupancy (a
    confident completion counts as known). ``prior``: the prior's ln 2, whatever the belief predicts
    there (the predicted occupancy still decides how far rays get); with the learned push model, whose
    predictions rewrite thousands of never-reached voxels, pushes then win on space the prediction made
    transparent and cost the map (docs/explanation/map-prediction.md). A belief without a ray record (the analytic
    update) holds the prior in never-reached voxels anyway."""
    information: Literal["occupancy", "occupancy-and-class"] = "occupancy-and-class"
    """What a voxel's state is. ``occupancy``: free or occupied (MEM, the paper). ``occupancy-and-class``:
    free or occupied by one of the object classes, whose entropy is ``H_b(p) + p * H(pi)`` with ``pi`` the
    expected categorical over the object classes (chain rule): a ray that would reach an object whose
    class no ray has seen is credited for the class it would resolve, not only for its occupancy."""
    gain: Literal["entropy", "expected-reduction"] = "expected-reduction"
    """What a voxel a ray reaches contributes. ``entropy``: the Shannon entropy of its expected state
    (MEM, the paper: one observation resolves it). ``expected-reduction``: the expected drop of that entropy
    when one more observation adds ``observation_evidence`` to the outcome it sees (a hit or a miss,
    drawn from the expected occupancy; the class, from the expected categorical): ``H(E[p]) -
    E_y[H(E[p | y])] >= 0``. A voxel that many rays have already reached, or whose evidence is split
    (a surface voxel that rays both hit and pass), gains little from one more; never-reached space and
    a vague prediction gain much."""
    observation_evidence: float = Field(10.0, gt=0.0)
    """Evidence one observation adds to a voxel (``expected-reduction``): the analytic update's ``w_occ``,
    ``w_free`` and ``w_cls``, which the ray record of ``cnabu-map`` uses too."""
    predicted_entropy: Literal["no-gain", "as-predicted"] = "no-gain"
    """What a manipulation's predicted change may do to the entropy IG counts. ``no-gain``: a voxel an
    effect model changed keeps at most the entropy it had before (``min(H_before, H_predicted)``): the
    prediction moves occupancy, so the view after it sees past what moved, but the uncertainty the
    prediction itself adds (a grasped object's voxels returned to the prior) is no information a
    camera can gain. A manipulation earns IG only where it opens space whose entropy was there
    before: never-observed voxels and the residual uncertainty of observed ones. ``as-predicted``: the
    predicted belief's own entropy (MEM's rule)."""


LN2 = np.float32(np.log(2.0))
"""The prior's occupancy entropy (nats)."""


def occupancy_reduction(alpha: NDArray[np.floating], beta: NDArray[np.floating], w: float) -> NDArray[np.float64]:
    """Expected drop of the Shannon entropy (nats) of the expected occupancy of ``Beta(alpha, beta)`` when one
    observation adds ``w`` to alpha (a hit, with probability ``E[p]``) or to beta (a miss). ``>= 0`` (entropy
    is concave and the expected posterior mean is the prior mean)."""
    a, b = np.asarray(alpha, np.float64), np.asarray(beta, np.float64)
    n = a + b
    p = a / n
    after = p * bernoulli_entropy((a + w) / (n + w)) + (1.0 - p) * bernoulli_entropy(a / (n + w))
    return np.maximum(bernoulli_entropy(p) - after, 0.0)


def class_reduction(eta: NDArray[np.floating], w: float) -> NDArray[np.float64]:
    """Expected drop of the Shannon entropy (nats) of the expected categorical of Dirichlet evidence
    ``eta [C, ...]`` when one observation adds ``w`` to class c, drawn from the expected categorical. ``>= 0``.

    With ``S = sum_k e_k`` and ``T = sum_k e_k log e_k``: the entropy is ``log S - T / S``, after class c
    it is ``log(S + w) - (T - e_c log e_c + (e_c + w) log(e_c + w)) / (S + w)``, and the expectation over
    c (weights ``e_c / S``) folds into sums over the classes (tests/test_ig_gain.py checks it against the
    entropy after each class, enumerated)."""
    e = np.asarray(eta, np.float64)
    s = e.sum(axis=0)
    positive = bool((e > 0.0).all())
    elog = e * np.log(e) if positive else _xlogx(e)
    ew = e + w
    total = elog.sum(axis=0)
    moved = (e * (ew * np.log(ew) - elog)).sum(axis=0)  # sum_c e_c ((e_c + w) log(e_c + w) - e_c log e_c)
    expected = np.log(s + w) - (s * total + moved) / (s * (s + w))
    return np.maximum(np.log(s) - total / s - expected, 0.0)


def _unique_deltas(deltas: Sequence[IGDelta]) -> tuple[list[IGDelta], NDArray[np.int64]]:
    """The distinct deltas and, per input delta, its index among them (candidates that change the
    field identically, e.g. pushes moving an object by the same whole number of voxels, are scored once)."""
    first: dict[bytes, int] = {}
    same = np.empty(len(deltas), dtype=np.int64)
    out: list[IGDelta] = []
    for i, d in enumerate(deltas):
        idx = np.asarray(d.idx, dtype=np.int64)
        key = hashlib.blake2b(idx.tobytes() + np.asarray(d.p, np.float32).tobytes()
                              + np.asarray(d.H, np.float32).tobytes(), digest_size=16).digest()
        if key not in first:
            first[key] = len(out)
            out.append(d)
        same[i] = first[key]
    return out, same


def shelf_wall_mask(grid: GridSpec, shelf: ShelfSpec) -> NDArray[np.bool_]:
    """Voxels whose centre lies outside the shelf interior, except in front of it (y < 0, open).

    These are the side, back, top and bottom boards seen through the grid's margin; IG treats them
    as occupied.
    """
    c = grid.centers()
    lo, hi = shelf.interior_lower, shelf.interior_upper
    outside = np.any((c < lo) | (c > hi), axis=-1)
    return outside & (c[..., 1] >= lo[1])


def shelf_interior_mask(grid: GridSpec, shelf: ShelfSpec) -> NDArray[np.bool_]:
    """Voxels whose centre lies in the closed shelf interior box ``[interior_lower, interior_upper]``.

    The complement of :func:`shelf_wall_mask` without the open front (voxels in front of the
    shelf, y < interior_lower.y, are neither walls nor interior). The paper's metrics are scored here.
    """
    c = grid.centers()
    return np.all((c >= shelf.interior_lower) & (c <= shelf.interior_upper), axis=-1)


@dataclass
class IGField:
    """What IG reads from a belief: flat float32 clamped occupancy ``p`` and its entropy ``H`` (nats)."""

    p: NDArray[np.float32]
    H: NDArray[np.float32]
    observed_record: bool = False
    """Whether ``H`` came from a belief with a ray record and ``never_observed: prior`` (a voxel a
    prediction rewrites is then never observed in the predicted belief)."""

    def copy(self) -> IGField:
        return IGField(self.p.copy(), self.H.copy(), self.observed_record)


@dataclass
class IGDelta:
    """A sparse change of an :class:`IGField`: new clamped ``p`` and ``H`` at flat voxel indices."""

    idx: NDArray[np.int64]
    """Sorted, unique flat voxel indices."""
    p: NDArray[np.float32]
    H: NDArray[np.float32]

    def apply(self, base: IGField) -> IGField:
        out = base.copy()
        out.p[self.idx] = self.p
        out.H[self.idx] = self.H
        return out


class IGService:
    """IG of a fixed set of viewpoints over beliefs on one grid.

    Per-view world ray directions (every ``ray_stride_px``-th pixel) are computed once here.
    """

    def __init__(
        self,
        grid: GridSpec,
        camera: CameraConfig,
        viewpoints: NDArray[np.floating],
        shelf: ShelfSpec,
        config: IGConfig | None = None,
    ) -> None:
        self.grid = grid
        self.camera = camera
        self.config = config or IGConfig()
        self.viewpoints = np.asarray(viewpoints, dtype=np.float64)
        if self.viewpoints.ndim != 3 or self.viewpoints.shape[1:] != (4, 4):
            raise ValueError(f"viewpoints must be [V, 4, 4] camera-to-world poses, got {self.viewpoints.shape}")
        self.walls = shelf_wall_mask(grid, shelf).ravel()
        self._g0, self._s, self._n = raycast.grid_params(grid)
        cam_dirs = camera.pixel_rays(self.config.ray_stride_px).reshape(-1, 3)
        self.origins = np.ascontiguousarray(self.viewpoints[:, :3, 3])
        """Camera centre per view, [V, 3]."""
        self.dirs = np.ascontiguousarray(np.einsum("vij,rj->vri", self.viewpoints[:, :3, :3], cam_dirs))
        """World ray direction per view and ray (image order), [V, R, 3], scaled so that t is the z-depth."""
        self.t_min, self.t_max = float(camera.near_m), float(camera.far_m)
        self.rays = raycast.RayTable.build(self.origins, self.dirs, grid, self.t_min, self.t_max)
        """The same rays with their grid entry/exit, grid-crossing rays first (what the kernels read)."""
        self._coarse: dict[int, raycast.RayTable] = {}
        self._prior_gain: dict[int, np.float32] = {}
        self._sweeps: list[tuple[IGField, int, float, NDArray[np.float64], NDArray[np.float64]]] = []
        """Recent base sweeps with their ray stops: (field, ray_step, eps, IG [V], stop t [V, R])."""

    @property
    def num_views(self) -> int:
        return int(self.viewpoints.shape[0])

    @property
    def rays_per_view(self) -> int:
        return int(self.dirs.shape[1])

    def prepare(self, belief: EvidentialMap, before: IGField | None = None) -> IGField:
        """Clamped occupancy (MEM: > p_occ_clamp -> 1, < p_free_clamp -> 0, walls 1) and its entropy.

        ``before``: the field of the belief a manipulation's prediction ``belief`` was made from; with
        ``predicted_entropy: no-gain`` no voxel's entropy rises above its entropy there."""
        if belief.grid != self.grid:
            raise ValueError("belief grid differs from the IG service's grid")
        with span("ig.prepare"):
            p = belief.expected_occupancy().ravel().astype(np.float32)
            p, h = self._clamp(p, self.walls)
            record = belief.observed is not None and self.config.never_observed == "prior"
            if self._mem():
                if record:
                    h[~belief.observed.ravel() & ~self.walls] = LN2  # type: ignore[union-attr]
            else:
                a, b = belief.alpha.ravel(), belief.beta.ravel()
                eta = belief.eta.reshape(belief.eta.shape[0], -1)
                if record:  # the prior's evidence where no ray reached
                    never = ~belief.observed.ravel()  # type: ignore[union-attr]
                    a, b = np.where(never, np.float32(1), a), np.where(never, np.float32(1), b)
                    eta = np.where(never[None], np.float32(1), eta)
                    # the prior's gain there; the predicted occupancy still decides how far rays get
                    h = self._information(a, b, eta, np.where(never & ~self.walls, np.float32(0.5), p), self.walls)
                else:
                    h = self._information(a, b, eta, p, self.walls)
            if before is not None and self.config.predicted_entropy == "no-gain":
                h = np.minimum(h, before.H)
            return IGField(p, h, record)

    def _mem(self) -> bool:
        """Whether a voxel's value is MEM's: the entropy of its clamped occupancy alone."""
        return self.config.information == "occupancy" and self.config.gain == "entropy"

    def _information(self, alpha: NDArray[np.floating], beta: NDArray[np.floating], eta: NDArray[np.floating],
                     p: NDArray[np.float32], walls: NDArray[np.bool_]) -> NDArray[np.float32]:
        """Per voxel what a ray reaching it gains (``gain``, ``information``), from its evidence and its
        clamped occupancy ``p``; 0 on walls and where ``p`` is clamped to 0, and no occupancy part where
        ``p`` is clamped to 1."""
        cfg = self.config
        if cfg.gain == "expected-reduction":  # the default: one numba pass (gain.py), numpy's result
            return voxel_information(alpha, beta, eta, p, walls, cfg.observation_evidence,
                                     cfg.information == "occupancy-and-class")
        return self._information_numpy(alpha, beta, eta, p, walls)

    def _information_numpy(self, alpha: NDArray[np.floating], beta: NDArray[np.floating], eta: NDArray[np.floating],
                           p: NDArray[np.float32], walls: NDArray[np.bool_]) -> NDArray[np.float32]:
        """:meth:`_information` in numpy, from :func:`occupancy_reduction` and :func:`class_reduction`
        (the reference of :func:`~msmem_core.map.gain.voxel_information`, and the ``entropy`` gain)."""
        cfg = self.config
        sure = (p <= 0.0) | (p >= 1.0)
        if cfg.gain == "entropy":
            h = bernoulli_entropy(p)
        else:
            h = np.where(sure, 0.0, occupancy_reduction(alpha, beta, cfg.observation_evidence))
        if cfg.information == "occupancy-and-class":
            cls = (categorical_entropy(eta[1:]) if cfg.gain == "entropy"
                   else class_reduction(eta[1:], cfg.observation_evidence))
            h = h + p * cls
        return np.where(walls, 0.0, h).astype(np.float32)

    def _prior_information(self, num_classes: int) -> np.float32:
        """What a ray reaching a voxel at the prior gains (``_information`` of the prior's evidence at
        p = 0.5 off the walls), cached per class count."""
        if num_classes not in self._prior_gain:
            one = np.ones(1, dtype=np.float32)
            self._prior_gain[num_classes] = self._information(one, one, np.ones((num_classes, 1), np.float32),
                                                              np.full(1, 0.5, np.float32), np.zeros(1, dtype=bool))[0]
        return self._prior_gain[num_classes]

    def _clamp(
        self, p: NDArray[np.float32], walls: NDArray[np.bool_]
    ) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
        """MEM's clamp of expected occupancy (in place) and its entropy."""
        p[p > self.config.p_occ_clamp] = 1.0
        p[p < self.config.p_free_clamp] = 0.0
        p[walls] = 1.0
        return p, bernoulli_entropy(p).astype(np.float32)

    # ------------------------------------------------------------------------------ incremental IG
    def field_delta(self, base: IGField, field: IGField) -> IGDelta:
        """The voxels where ``field`` differs from ``base`` (any predicted belief, dense)."""
        idx = np.flatnonzero((field.p != base.p) | (field.H != base.H))
        return IGDelta(idx, field.p[idx], field.H[idx])

    def belief_delta(self, base: IGField, delta: BeliefDelta) -> IGDelta:
        """The field change of a sparse belief change (``delta`` applied to the belief ``base`` came from).

        Only the changed voxels are evaluated; voxels whose clamped ``p`` stays the same are dropped.
        Equal to ``field_delta(base, prepare(delta.apply(belief), before=base))``.
        """
        return self.belief_deltas(base, [delta])[0]

    def belief_deltas(self, base: IGField, deltas: Sequence[BeliefDelta]) -> list[IGDelta]:
        """:meth:`belief_delta` of each of ``deltas``, with every candidate's voxels evaluated together:
        the default voxel values (``gain: expected-reduction``) of all of them in one parallel pass, each
        voxel's class sums in the order numpy adds them in its own candidate's array."""
        if not deltas:
            return []
        sizes = np.array([len(d.idx) for d in deltas], dtype=np.int64)
        idx = np.concatenate([np.asarray(d.idx, dtype=np.int64) for d in deltas])
        a = np.concatenate([np.asarray(d.alpha, dtype=np.float32) for d in deltas])
        b = np.concatenate([np.asarray(d.beta, dtype=np.float32) for d in deltas])
        etas = [np.asarray(d.eta) for d in deltas]
        p = (a / (a + b)).astype(np.float32)
        walls = self.walls[idx]
        p, h = self._clamp(p, walls)
        if self._mem():
            if base.observed_record:  # a predicted change clears the ray record where it writes
                h = np.where(walls, h, LN2).astype(np.float32)
        elif base.observed_record:  # the prior's gain off the walls: one value, computed once
            h = np.where(walls, np.float32(0), self._prior_information(etas[0].shape[0]))
        elif self.config.gain == "expected-reduction":
            pairwise = np.repeat(np.array([sums_pairwise(e) for e in etas], dtype=bool), sizes)
            h = voxel_information_of(a, b, np.concatenate(etas, axis=1), p, walls, self.config.observation_evidence,
                                     self.config.information == "occupancy-and-class", pairwise)
        else:  # numpy's sums follow each candidate's own array
            bounds = np.concatenate([[0], np.cumsum(sizes)])
            h = np.concatenate([self._information(a[lo:hi], b[lo:hi], e, p[lo:hi], walls[lo:hi])
                                for lo, hi, e in zip(bounds[:-1], bounds[1:], etas, strict=True)])
        if self.config.predicted_entropy == "no-gain":
            h = np.minimum(h, base.H[idx])
        keep = (p != base.p[idx]) | (h != base.H[idx])
        out = []
        for lo, hi in itertools.pairwise(np.concatenate([[0], np.cumsum(sizes)]).tolist()):
            k = keep[lo:hi]
            out.append(IGDelta(idx[lo:hi][k], p[lo:hi][k], h[lo:hi][k]))
        return out

    def coarse_rays(self, step: int) -> raycast.RayTable:
        """The ray table of every ``step``-th ray in both image axes (for screening candidates)."""
        if step == 1:
            return self.rays
        if step not in self._coarse:
            h, w = self.camera.pixel_rays(self.config.ray_stride_px).shape[:2]
            dirs = self.dirs.reshape(self.num_views, h, w, 3)[:, ::step, ::step].reshape(self.num_views, -1, 3)
            self._coarse[step] = raycast.RayTable.build(self.origins, dirs, self.grid, self.t_min, self.t_max)
        return self._coarse[step]

    def sweep(self, field: IGField, exact: bool = False, ray_step: int = 1) -> NDArray[np.float64]:
        """IG of every view, float64 [V], equal to ``view_ig(field, exact)`` (``ray_step`` > 1: over
        the screening rays of :meth:`coarse_rays`), remembered for this field together with where
        each ray stopped, which :meth:`view_ig_delta` uses. Fields are treated as immutable: the
        result is looked up by identity (the few most recent fields are kept)."""
        with span("ig.sweep", ray_step=ray_step):
            return self._sweep(field, 0.0 if exact else self.config.early_exit, ray_step)[0].copy()

    def _sweep(self, field: IGField, eps: float, ray_step: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        for f, step, e, ig, t_stop in self._sweeps:
            if f is field and step == ray_step and e == eps:
                return ig, t_stop
        rays = self.coarse_rays(ray_step)
        with deferred_interrupt():
            ig, t_stop = raycast.ig_views_stop(field.p, field.H, *rays.args(), self._g0, self._s, self._n, eps)
        self._sweeps = [(field, ray_step, eps, ig, t_stop), *self._sweeps[:3]]
        return ig, t_stop

    def view_ig_delta(
        self, base: IGField, deltas: Sequence[IGDelta], exact: bool = False, ray_step: int = 1,
        views: NDArray[np.integer] | None = None,
    ) -> NDArray[np.float64]:
        """IG of every view for K changed fields, float64 [K, V], re-scoring only affected rays.

        ``views``: only these views, [K, len(views)], each column equal to the full call's (the base
        field's IG of those views is computed for them alone, not remembered).

        Equal to ``view_ig([d.apply(base) for d in deltas], exact)`` up to float64 summation order
        (tested); the early exit applies the same way to both. ``ray_step > 1`` uses every
        ``ray_step``-th ray in both image axes only (a screening estimate, not comparable with
        full-density values). The base field's sweep (:meth:`sweep`) is computed once and reused;
        identical deltas are scored once.
        """
        with span("ig.incremental", ray_step=ray_step, candidates=len(deltas),
                  views=self.num_views if views is None else len(views)):
            return self._view_ig_delta(base, deltas, exact, ray_step, views)

    def _view_ig_delta(self, base: IGField, deltas: Sequence[IGDelta], exact: bool, ray_step: int,
                       views: NDArray[np.integer] | None = None) -> NDArray[np.float64]:
        eps = 0.0 if exact else self.config.early_exit
        k = len(deltas)
        rays = self.coarse_rays(ray_step)
        if views is not None:
            rays = rays.subset(np.asarray(views, dtype=np.int64))
        if k == 0:
            return np.zeros((0, len(rays.count)))
        if views is None:
            base_ig, t_stop = self._sweep(base, eps, ray_step)
        else:
            with deferred_interrupt():
                base_ig, t_stop = raycast.ig_views_stop(base.p, base.H, *rays.args(), self._g0, self._s, self._n, eps)
        deltas, same = _unique_deltas(deltas)
        k = len(deltas)
        sizes = np.array([len(d.idx) for d in deltas], dtype=np.int64)
        if not sizes.any():
            return np.repeat(base_ig[None], len(same), axis=0)
        all_idx = np.concatenate([np.asarray(d.idx, dtype=np.int64) for d in deltas])
        union, inverse = np.unique(all_idx, return_inverse=True)
        owner = np.repeat(np.arange(k, dtype=np.int64), sizes)
        # per union voxel, the candidates changing it (CSR, sorted by union position)
        order = np.argsort(inverse, kind="stable")
        cand_k = np.ascontiguousarray(owner[order])
        cand_ptr = np.zeros(len(union) + 1, dtype=np.int64)
        np.cumsum(np.bincount(inverse, minlength=len(union)), out=cand_ptr[1:])
        pu = np.repeat(base.p[union][:, None], k, axis=1)  # voxel-major [U, K]
        hu = np.repeat(base.H[union][:, None], k, axis=1)
        pu[inverse, owner] = np.concatenate([d.p for d in deltas])
        hu[inverse, owner] = np.concatenate([d.H for d in deltas])
        slot = np.full(self.grid.size, -1, dtype=np.int32)
        slot[union] = np.arange(len(union), dtype=np.int32)
        stop = ((base.p >= 1.0) & (slot < 0)).astype(np.uint8)
        # a box around the union voxels, widened a little beyond rounding (the kernel's ray filter)
        ijk = np.stack(np.unravel_index(union, self.grid.shape), axis=-1)
        pad = 1e-6 * self._s
        box_lo = self._g0 + ijk.min(axis=0) * self._s - pad
        box_hi = self._g0 + (ijk.max(axis=0) + 1) * self._s + pad
        # views differ in work (rays skipped): schedule them dynamically
        with deferred_interrupt(), numba.parallel_chunksize(4):
            change = raycast.ig_views_delta(
                base.p, base.H, stop, slot, pu, hu, cand_ptr, cand_k, *rays.args(), t_stop, box_lo, box_hi,
                self._g0, self._s, self._n, eps,
            )
        return (base_ig[None] + change)[same]

    def view_ig(self, fields: IGField | Sequence[IGField], exact: bool = False) -> NDArray[np.float64]:
        """IG of every view: float64 [V] for one field, [K, V] for a sequence of K fields.

        ``exact`` turns the early exit off (the result then matches the float64 reference).
        """
        eps = 0.0 if exact else self.config.early_exit
        args = (*self.rays.args(), self._g0, self._s, self._n, eps)
        with span("ig.sweep"), deferred_interrupt():
            if isinstance(fields, IGField):
                return raycast.ig_views(fields.p, fields.H, *args)
            if len(fields) == 0:
                return np.zeros((0, self.num_views))
            p = np.stack([f.p for f in fields], axis=1)  # voxel-major [N, K], as the batch kernel wants
            h = np.stack([f.H for f in fields], axis=1)
            stop = np.all(p >= 1.0, axis=1).astype(np.uint8)
            return raycast.ig_views_batch(p, h, stop, *args)

    def ray_ig(self, field: IGField, exact: bool = False) -> NDArray[np.float64]:
        """Per-ray IG, float64 [V, R] in image order of ``dirs`` (for debugging and tests)."""
        eps = 0.0 if exact else self.config.early_exit
        return self.rays.unsort(raycast.ig_rays(field.p, field.H, *self.rays.args(), self._g0, self._s, self._n, eps))

    def after_view(self, field: IGField, view: int) -> IGField:
        """Expected field after observing ``view``: H = 0 on its rays up to each first p == 1 voxel."""
        with span("ig.after_view"), deferred_interrupt():
            h = raycast.zero_entropy_along_view(
                field.p, field.H, self.origins[view], self.dirs[view], self._g0, self._s, self._n, self.t_min,
                self.t_max)
            return IGField(field.p, h, field.observed_record)

    def views_ig(self, field: IGField, views: NDArray[np.integer] | Sequence[int], exact: bool = False
                 ) -> NDArray[np.float64]:
        """IG of the listed views only, float64 [len(views)], equal to ``view_ig(field, exact)[views]`` bit
        for bit (each view's rays are summed in the same order)."""
        eps = 0.0 if exact else self.config.early_exit
        sel = np.asarray(views, dtype=np.int64)
        if len(sel) == 0:
            return np.zeros(0)
        with span("ig.views", views=len(sel)), deferred_interrupt():
            return raycast.ig_views(field.p, field.H, *self.rays.subset(sel).args(), self._g0, self._s, self._n, eps)

    def screened_view_ig(self, field: IGField, views: NDArray[np.integer], ray_step: int, finalists: int,
                         coarse: NDArray[np.float64] | None = None,
                         ) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
        """IG of ``views`` [K] screened: every view at every ``ray_step``-th ray in both image axes, the
        ``finalists`` best of them again at full density. Returns (values [K], exact [K]): the finalists
        get their full-density IG (equal to :meth:`view_ig`'s); every other view its screened IG times
        the finalists' median full/screened ratio, capped at the lowest finalist's value, so no
        screened view out-scores a finalist. ``ray_step`` 1 or at most ``finalists`` views: all exact.
        ``coarse``: the caller's screened sweep of ``field`` (else :meth:`sweep` at ``ray_step``)."""
        views = np.asarray(views, dtype=np.int64)
        if ray_step <= 1 or len(views) <= finalists:
            return self.views_ig(field, views), np.ones(len(views), dtype=bool)
        c = (self.sweep(field, ray_step=ray_step) if coarse is None else coarse)[views]
        top = np.argsort(-c, kind="stable")[:finalists]
        full = self.views_ig(field, views[top])
        ratio = float(np.median(full / np.maximum(c[top], 1e-12)))
        out = np.minimum(c * ratio, full.min())
        out[top] = full
        exact = np.zeros(len(views), dtype=bool)
        exact[top] = True
        return out, exact

    def best_two_step(
        self, field: IGField, excluded: set[int] | frozenset[int] = frozenset(),
        first: NDArray[np.float64] | None = None, ray_step: int = 1, finalists: int = 8,
    ) -> tuple[int, float, int, float]:
        """Greedy two-view lookahead (paper eq. oig, view branch, as MEM).

        ``v1 = argmax IG(v)`` over views not excluded, then ``v2 = argmax IG(v | after_view(v1))``
        over views not in ``excluded | {v1}``. Returns ``(v1, ig1, v2, ig2)``; ``v2 = -1, ig2 = 0``
        when no second view is left. Raises ``ValueError`` if every view is excluded. ``first``: the
        caller's ``view_ig(field)``, to skip recomputing it (views it sets to -inf are not taken as v1).
        ``ray_step`` > 1 screens the second view (:meth:`screened_view_ig`): ``ig2`` is the largest
        full-density IG among the ``finalists`` best screened views, so at most the exact one.
        """
        allowed = np.ones(self.num_views, dtype=bool)
        allowed[[v for v in excluded if 0 <= v < self.num_views]] = False
        if not allowed.any():
            raise ValueError("every viewpoint is excluded")
        ig = np.where(allowed, self.view_ig(field) if first is None else first, -np.inf)
        v1 = int(np.argmax(ig))
        allowed[v1] = False
        if not allowed.any():
            return v1, float(ig[v1]), -1, 0.0
        after = self.after_view(field, v1)
        rest = np.flatnonzero(allowed)
        if ray_step > 1 and len(rest) > finalists:
            values, exact = self.screened_view_ig(after, rest, ray_step, finalists,
                                                  coarse=self._coarse_sweep(after, ray_step))
            best = int(np.argmax(np.where(exact, values, -np.inf)))
            return v1, float(ig[v1]), int(rest[best]), float(values[best])
        # the remaining views, each exactly as in view_ig(after) (a few alone, rather than copy their rays)
        ig2 = self.view_ig(after)[rest] if 4 * len(rest) > self.num_views else self.views_ig(after, rest)
        best = int(np.argmax(ig2))
        return v1, float(ig[v1]), int(rest[best]), float(ig2[best])

    def _coarse_sweep(self, field: IGField, ray_step: int) -> NDArray[np.float64]:
        """Screened IG of every view of a one-off field (not remembered, unlike :meth:`sweep`)."""
        rays = self.coarse_rays(ray_step)
        with span("ig.sweep", ray_step=ray_step), deferred_interrupt():
            return raycast.ig_views(field.p, field.H, *rays.args(), self._g0, self._s, self._n,
                                    self.config.early_exit)
