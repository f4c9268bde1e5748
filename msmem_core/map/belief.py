"""The evidential metric-semantic belief (paper eq. occ_beta and the Dirichlet after it).

Entropies here are Shannon entropies in nats of the *expected* Bernoulli / categorical
distribution, the quantities IG and Delta-H use; they are not the differential entropies of the
Beta or Dirichlet themselves (what ``scipy.stats.beta(...).entropy()`` would return).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, overload

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import UserError
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import NUM_CLASSES


def _xlogx(p: NDArray[np.floating]) -> NDArray[np.float64]:
    """p * log(p) with 0 log 0 = 0, in float64."""
    p64 = np.asarray(p, dtype=np.float64)
    return np.where(p64 > 0.0, p64 * np.log(np.where(p64 > 0.0, p64, 1.0)), 0.0)  # log never sees p <= 0


def categorical_entropy(eta: NDArray[np.floating]) -> NDArray[np.float64]:
    """Shannon entropy (nats) of the expected categorical of Dirichlet evidence ``eta [C, ...]``."""
    e = np.asarray(eta)
    return -_xlogx(e / e.sum(axis=0, keepdims=True)).sum(axis=0)


def bernoulli_entropy(p: NDArray[np.floating]) -> NDArray[np.float64]:
    """Shannon entropy (nats) of Bernoulli(p), elementwise; 0 at p in {0, 1}."""
    p64 = np.asarray(p, dtype=np.float64)
    q64 = 1.0 - p64
    if p64.size and bool(((p64 > 0.0) & (q64 > 0.0)).all()):  # no 0 log 0 to guard
        return -(p64 * np.log(p64) + q64 * np.log(q64))
    return -(_xlogx(p64) + _xlogx(q64))


def bytes_per_voxel(num_classes: int = NUM_CLASSES) -> int:
    """Estimated peak memory of an episode per grid voxel: the float32 belief (alpha, beta and
    ``num_classes`` eta) twice (the belief and the updated copy) plus the float64 temporaries of the
    semantic entropy (four arrays of ``num_classes`` values). 616 bytes for 15 classes; measured with
    tracemalloc: 68 bytes of belief and a 503-byte peak while ``total_semantic_entropy`` runs."""
    return 2 * (2 + num_classes) * 4 + 4 * num_classes * 8


def memory_limit_bytes() -> int:
    """The most a grid may need: half of the machine's physical memory."""
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):  # no sysconf: assume 8 GiB of memory
        return 4 << 30


def _gib(n: float) -> str:
    return f"{n / 2**40:.1f} TiB" if n >= 2**40 else f"{n / 2**30:.1f} GiB"


def check_grid_memory(grid: GridSpec, num_classes: int = NUM_CLASSES) -> GridSpec:
    """The grid, or a one-line ``UserError`` giving its size and the limit, before anything is allocated."""
    need = grid.size * bytes_per_voxel(num_classes)
    limit = memory_limit_bytes()
    if need > limit:
        x, y, z = grid.shape
        raise UserError(
            f"grid of {x} x {y} x {z} = {grid.size:,} voxels of {grid.voxel_m * 1000:g} mm needs about {_gib(need)} "
            f"for the belief and its working arrays, more than the limit of {_gib(limit)} (half of physical "
            f"memory); use a larger grid.voxel_m or a smaller shelf")
    return grid


@dataclass
class EvidentialMap:
    """Beta occupancy evidence ``alpha, beta [X,Y,Z]`` and Dirichlet class evidence ``eta [C,X,Y,Z]``.

    Evidence is float32 and never below the prior 1. Class 0 is background (free space / shelf).
    """

    grid: GridSpec
    alpha: NDArray[np.float32]
    beta: NDArray[np.float32]
    eta: NDArray[np.float32]
    observed: NDArray[np.bool_] | None = None
    """``[X, Y, Z]``: which voxels a camera ray has reached (passed through or hit), kept by an
    observation model whose evidence is a prediction rather than a ray count (``cnabu-map`` completes
    voxels no ray reached, confidently); a predicted change (``BeliefDelta.apply``) clears it where it
    writes. None: the evidence itself is the ray record (the analytic update), and *never seen* is
    read from the vacuity (:meth:`never_seen`)."""

    def __post_init__(self) -> None:
        shape = tuple(self.grid.shape)
        if self.alpha.shape != shape or self.beta.shape != shape or self.eta.shape[1:] != shape:
            raise ValueError(
                f"evidence shapes {self.alpha.shape}, {self.beta.shape}, {self.eta.shape} do not match grid {shape}"
            )
        if self.observed is not None and (self.observed.shape != shape or self.observed.dtype != np.bool_):
            raise ValueError(f"observed must be a bool array of the grid's shape {shape}, got "
                             f"{self.observed.dtype} {self.observed.shape}")

    @classmethod
    def empty(cls, grid: GridSpec, num_classes: int = NUM_CLASSES) -> EvidentialMap:
        """The uninformed prior: all evidence 1 (p = 0.5, vacuity 1)."""
        check_grid_memory(grid, num_classes)
        shape = tuple(grid.shape)
        return cls(
            grid=grid,
            alpha=np.ones(shape, np.float32),
            beta=np.ones(shape, np.float32),
            eta=np.ones((num_classes, *shape), np.float32),
        )

    @property
    def num_classes(self) -> int:
        return int(self.eta.shape[0])

    def copy(self) -> EvidentialMap:
        return EvidentialMap(self.grid, self.alpha.copy(), self.beta.copy(), self.eta.copy(),
                             None if self.observed is None else self.observed.copy())

    def capped(self, region: NDArray[np.bool_], cap: float) -> EvidentialMap:
        """A copy with the evidence of ``region`` ([X, Y, Z]) shrunk towards the prior: where alpha +
        beta > ``cap``, alpha - 1, beta - 1 and eta - 1 are scaled by (cap - 2) / (alpha + beta - 2).
        Expected occupancy moves towards 0.5 but stays on its side of it and the class argmax is kept,
        except with ``cap`` 2, which resets those voxels to the prior."""
        idx = np.flatnonzero(region)
        a, b = self.alpha.reshape(-1)[idx], self.beta.reshape(-1)[idx]
        s = a + b
        big = s > cap
        idx, a, b, s = idx[big], a[big], b[big], s[big]
        f = ((cap - 2.0) / (s - 2.0)).astype(np.float32)
        out = self.copy()
        out.alpha.reshape(-1)[idx] = 1.0 + f * (a - 1.0)
        out.beta.reshape(-1)[idx] = 1.0 + f * (b - 1.0)
        eta = out.eta.reshape(self.num_classes, -1)
        eta[:, idx] = 1.0 + f[None] * (eta[:, idx] - 1.0)
        return out

    # ------------------------------------------------------------------ expected distributions
    def expected_occupancy(self) -> NDArray[np.float32]:
        """E[occupancy] = alpha / (alpha + beta), [X,Y,Z]."""
        return self.alpha / (self.alpha + self.beta)

    def class_probs(self) -> NDArray[np.float32]:
        """E[class] = eta / sum_c eta, [C,X,Y,Z]."""
        return self.eta / self.eta.sum(axis=0, keepdims=True)

    def vacuity(self) -> NDArray[np.float32]:
        """Semantic vacuity chi = C / sum_c eta in (0, 1]; 1 for the prior."""
        return np.float32(self.num_classes) / self.eta.sum(axis=0)

    def occupancy_entropy(self) -> NDArray[np.float64]:
        """Shannon entropy (nats) of the expected Bernoulli occupancy, [X,Y,Z]."""
        return bernoulli_entropy(self.expected_occupancy())

    def semantic_entropy(self) -> NDArray[np.float64]:
        """Shannon entropy (nats) of the expected categorical, [X,Y,Z]."""
        return categorical_entropy(self.eta)

    def total_semantic_entropy(self) -> float:
        """H(Phi) of the Delta-H term: semantic entropy summed over all voxels (nats)."""
        return float(self.semantic_entropy().sum())

    def never_seen(self, vacuity_threshold: float) -> NDArray[np.bool_]:
        """``[X, Y, Z]`` voxels no camera ray has reached: ``~observed`` where the map keeps that
        record, else where the semantic vacuity is at or above ``vacuity_threshold`` (prior: 1; the
        analytic update's first view: 0.6). Skills that look for hidden space read this, so a
        completed prediction does not count as seen."""
        if self.observed is not None:
            return ~self.observed
        return self.vacuity() >= vacuity_threshold

    def argmax_class(self, tau_chi: float) -> NDArray[np.int64]:
        """Most likely class per voxel, -1 (*unknown*) where vacuity >= tau_chi."""
        cls = np.argmax(self.eta, axis=0).astype(np.int64)
        cls[self.vacuity() >= tau_chi] = -1
        return cls

    # ------------------------------------------------------------------------------- storage
    def save(self, path: str | Path) -> None:
        arrays: dict[str, Any] = {"grid": np.array(self.grid.model_dump_json()), "alpha": self.alpha,
                                  "beta": self.beta, "eta": self.eta}
        if self.observed is not None:
            arrays["observed"] = self.observed
        np.savez_compressed(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> EvidentialMap:
        with np.load(path) as f:
            grid = GridSpec.model_validate(json.loads(str(f["grid"])))
            return cls(
                grid,
                f["alpha"].astype(np.float32),
                f["beta"].astype(np.float32),
                f["eta"].astype(np.float32),
                f["observed"].astype(bool) if "observed" in f.files else None,
            )


# ------------------------------------------------------------------------------ sparse predictions
@dataclass
class BeliefDelta:
    """A sparse change of a belief: the new evidence at some voxels (flat indices, sorted, unique).

    An effect model's ``Prediction`` holds one per candidate action, so K predictions cost K small
    arrays instead of K full maps, and IG / entropy / disturbance terms touch only the changed voxels.
    """

    idx: NDArray[np.int64]
    alpha: NDArray[np.float32]
    """[M] new Beta alpha at ``idx``."""
    beta: NDArray[np.float32]
    eta: NDArray[np.float32]
    """[C, M] new Dirichlet evidence at ``idx``."""

    def against(self, base: EvidentialMap) -> BeliefDelta:
        """This change without the voxels whose new evidence equals ``base``'s (what actually changes)."""
        c = base.num_classes
        keep = (self.alpha != base.alpha.reshape(-1)[self.idx]) | (self.beta != base.beta.reshape(-1)[self.idx])
        keep |= np.any(self.eta != base.eta.reshape(c, -1)[:, self.idx], axis=0)
        return BeliefDelta(self.idx[keep], self.alpha[keep], self.beta[keep], self.eta[:, keep])

    def apply(self, base: EvidentialMap) -> EvidentialMap:
        """``base`` with this change written in (a new map)."""
        out = base.copy()
        out.alpha.reshape(-1)[self.idx] = self.alpha
        out.beta.reshape(-1)[self.idx] = self.beta
        out.eta.reshape(out.num_classes, -1)[:, self.idx] = self.eta
        if out.observed is not None:  # a prediction is not an observation
            out.observed.reshape(-1)[self.idx] = False
        return out


class DeltaBeliefs(Sequence[EvidentialMap]):
    """K beliefs stored as one base map and K :class:`BeliefDelta`; an item is built on access
    (``Prediction.beliefs``)."""

    def __init__(self, base: EvidentialMap, deltas: Sequence[BeliefDelta]) -> None:
        self.base = base
        self.deltas = list(deltas)

    def __len__(self) -> int:
        return len(self.deltas)

    @overload
    def __getitem__(self, i: int) -> EvidentialMap: ...
    @overload
    def __getitem__(self, i: slice) -> list[EvidentialMap]: ...
    def __getitem__(self, i: int | slice) -> EvidentialMap | list[EvidentialMap]:
        if isinstance(i, slice):
            return [d.apply(self.base) for d in self.deltas[i]]
        return self.deltas[i].apply(self.base)

    def __iter__(self) -> Iterator[EvidentialMap]:
        for d in self.deltas:
            yield d.apply(self.base)
