"""Incremental IG (re-scoring only the rays that cross a candidate's changed voxels) equals a full re-score."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmem_core.map.belief import BeliefDelta, DeltaBeliefs, EvidentialMap
from msmem_core.map.ig import IGConfig, IGService
from msmem_core.world.camera import CameraConfig
from msmem_core.world.geometry import look_at
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ShelfSpec

MEM = {"gain": "entropy", "information": "occupancy"}
"""MEM's IG (the paper): a voxel counts the entropy of its clamped occupancy."""

SHELF = ShelfSpec(width_m=0.16, depth_m=0.12, height_m=0.08)
GRID = GridSpec.around_box(SHELF.interior_lower, SHELF.interior_upper, 0.01)  # 18 x 14 x 10
CAM = CameraConfig(width_px=64, height_px=48)
NUM_VIEWS = 6


def service(early_exit: float, never_observed: str = "prior") -> IGService:
    rng = np.random.default_rng(0)
    target = np.array([0.0, 0.06, 0.04])
    poses = []
    for _ in range(NUM_VIEWS):
        eye = target + np.array([rng.uniform(-0.15, 0.15), -rng.uniform(0.2, 0.35), rng.uniform(-0.05, 0.15)])
        poses.append(look_at(eye, target + rng.normal(scale=0.02, size=3)))
    return IGService(GRID, CAM, np.stack(poses), SHELF,
                     IGConfig(early_exit=early_exit, never_observed=never_observed, **MEM))  # type: ignore[arg-type]


def random_belief(rng: np.random.Generator) -> EvidentialMap:
    """Free (clamped), unknown, uncertain and occupied (clamped) voxels."""
    b = EvidentialMap.empty(GRID)
    kind = rng.integers(0, 4, GRID.shape)
    b.alpha[:] = np.where(kind == 3, 41.0, 1.0) + np.where(kind == 2, rng.uniform(0, 8, GRID.shape), 0.0)
    b.beta[:] = np.where(kind == 0, 41.0, 1.0) + np.where(kind == 2, rng.uniform(0, 8, GRID.shape), 0.0)
    return b


def random_deltas(base: EvidentialMap, rng: np.random.Generator, k: int) -> list[BeliefDelta]:
    """Box-shaped changes (as a push's) plus scattered voxels: occupied <-> free <-> prior."""
    out = []
    shape = np.asarray(GRID.shape)
    for _ in range(k):
        lo = rng.integers(0, shape - 1)
        hi = np.minimum(lo + rng.integers(1, 6, 3), shape)
        box = np.zeros(GRID.shape, bool)
        box[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] = True
        box |= rng.random(GRID.shape) < 0.01
        idx = np.flatnonzero(box)
        kind = rng.integers(0, 3, len(idx))
        alpha = np.where(kind == 0, 41.0, 1.0).astype(np.float32)
        beta = np.where(kind == 1, 41.0, 1.0).astype(np.float32)
        eta = np.ones((base.num_classes, len(idx)), np.float32)
        out.append(BeliefDelta(idx, alpha, beta, eta))
    return out


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([0.0, 1e-3, 0.05]), st.integers(1, 70), st.booleans())
def test_incremental_ig_equals_a_full_rescore(seed: int, eps: float, k: int, record: bool) -> None:
    rng = np.random.default_rng(seed)
    svc = service(eps)
    belief = random_belief(rng)
    if record:  # a ray record (cnabu-map): never-reached voxels count at the prior's entropy
        belief.observed = rng.random(GRID.shape) < 0.6
    deltas = random_deltas(belief, rng, k)
    base = svc.prepare(belief)
    predicted = DeltaBeliefs(belief, deltas)
    for exact in (False, True):
        full = svc.view_ig([svc.prepare(b, before=base) for b in predicted], exact=exact)
        fast = svc.view_ig_delta(base, [svc.belief_delta(base, d) for d in deltas], exact=exact)
        np.testing.assert_allclose(fast, full, rtol=1e-9, atol=1e-9)
        fields = [svc.field_delta(base, svc.prepare(b, before=base)) for b in predicted]
        dense = svc.view_ig_delta(base, fields, exact=exact)
        np.testing.assert_allclose(dense, full, rtol=1e-9, atol=1e-9)


def test_unchanged_candidates_score_the_base_ig_and_empty_batches_work() -> None:
    svc = service(1e-3)
    belief = random_belief(np.random.default_rng(3))
    base = svc.prepare(belief)
    same = svc.belief_delta(base, BeliefDelta(np.array([5, 9]), belief.alpha.ravel()[[5, 9]],
                                              belief.beta.ravel()[[5, 9]], belief.eta.reshape(15, -1)[:, [5, 9]]))
    assert len(same.idx) == 0  # nothing changes: dropped
    out = svc.view_ig_delta(base, [same, same])
    np.testing.assert_allclose(out, np.stack([svc.view_ig(base)] * 2), rtol=1e-12)
    assert svc.view_ig_delta(base, []).shape == (0, NUM_VIEWS)


@pytest.mark.parametrize("seed", [0, 1])
def test_delta_beliefs_materialise_the_change(seed: int) -> None:
    rng = np.random.default_rng(seed)
    belief = random_belief(rng)
    deltas = random_deltas(belief, rng, 3)
    seq = DeltaBeliefs(belief, deltas)
    assert len(seq) == 3
    b1 = seq[1]
    np.testing.assert_array_equal(b1.alpha.ravel()[deltas[1].idx], deltas[1].alpha)
    other = np.setdiff1d(np.arange(GRID.size), deltas[1].idx)
    np.testing.assert_array_equal(b1.alpha.ravel()[other], belief.alpha.ravel()[other])
    assert len(list(seq)) == 3
    assert len(seq[0:2]) == 2


def test_a_small_change_scores_alike_alone_duplicated_and_beside_others() -> None:
    """The rays skipped by the box filter and the deduplicated candidates change nothing: a one-voxel
    change scores the same alone (a tiny box), twice, and in a batch with changes elsewhere; the
    remembered sweep is view_ig."""
    rng = np.random.default_rng(7)
    svc = service(1e-3)
    belief = random_belief(rng)
    base = svc.prepare(belief)
    np.testing.assert_array_equal(svc.sweep(base), svc.view_ig(base))
    deltas = [svc.belief_delta(base, d) for d in random_deltas(belief, rng, 6)]
    free = np.flatnonzero(base.p == 0.0)
    small = svc.belief_delta(base, BeliefDelta(free[len(free) // 2 : len(free) // 2 + 1], np.array([41.0], np.float32),
                                               np.array([1.0], np.float32), np.ones((15, 1), np.float32)))
    assert len(small.idx) == 1  # a free voxel becomes occupied
    alone = svc.view_ig_delta(base, [small])
    full = svc.view_ig([small.apply(base)])
    np.testing.assert_allclose(alone, full, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(svc.view_ig_delta(base, [small, small]), np.concatenate([alone, alone]))
    mixed = svc.view_ig_delta(base, [deltas[0], small, *deltas[1:], small])
    np.testing.assert_allclose(mixed[[1, -1]], np.concatenate([alone, alone]), rtol=1e-12, atol=1e-12)


def test_never_reached_voxels_count_at_the_prior_and_a_prediction_injects_nothing() -> None:
    svc = service(0.0)
    belief = random_belief(np.random.default_rng(5))
    belief.alpha[:], belief.beta[:] = 1.0, 41.0  # everything confidently free ...
    belief.observed = np.ones(GRID.shape, bool)
    belief.observed[5:9, 8:12, 2:6] = False  # ... except a never-reached block the belief calls free too
    field = svc.prepare(belief)
    block = ~belief.observed.ravel() & ~svc.walls
    np.testing.assert_allclose(field.H[block], np.log(2.0), rtol=1e-6)
    assert (field.H[belief.observed.ravel() & ~svc.walls] == 0).all()
    assert svc.view_ig(field).max() > 1.0
    # a predicted change of observed free voxels to the prior adds no entropy
    idx = np.flatnonzero(belief.observed.ravel() & ~svc.walls)[:200]
    d = svc.belief_delta(field, BeliefDelta(idx, np.ones(len(idx), np.float32), np.ones(len(idx), np.float32),
                                            np.ones((belief.num_classes, len(idx)), np.float32)))
    assert (d.H == 0).all()
    blind = svc.prepare(EvidentialMap(belief.grid, belief.alpha, belief.beta, belief.eta))  # no ray record
    assert svc.view_ig(blind).max() == 0.0
