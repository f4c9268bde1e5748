"""IG's default voxel value: the expected drop of the entropy of the voxel's expected state (free, or
occupied by one object class) when one more observation adds the analytic update's evidence
(``IGConfig.gain: expected-reduction``, ``information: occupancy-and-class``)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from test_ig import CAM, GRID, SHELF, random_belief, small_views

from msmem_core.map.belief import EvidentialMap, bernoulli_entropy, categorical_entropy
from msmem_core.map.ig import IGConfig, IGService, class_reduction, occupancy_reduction, shelf_wall_mask


def _occupancy_by_enumeration(a: float, b: float, w: float) -> float:
    """H(E[p]) minus the entropy after a hit (probability E[p]: alpha + w) or a miss (beta + w)."""
    p = a / (a + b)
    hit, miss = (a + w) / (a + b + w), a / (a + b + w)
    return float(bernoulli_entropy(np.array(p)) - p * bernoulli_entropy(np.array(hit))
                 - (1 - p) * bernoulli_entropy(np.array(miss)))


def _class_by_enumeration(eta: np.ndarray, w: float) -> float:
    q = eta / eta.sum()
    after = 0.0
    for c in range(len(eta)):
        e = eta.copy()
        e[c] += w
        after += q[c] * float(categorical_entropy(e[:, None])[0])
    return float(categorical_entropy(eta[:, None])[0]) - after


@settings(max_examples=60, deadline=None)
@given(st.floats(1.0, 500.0), st.floats(1.0, 500.0), st.floats(0.1, 50.0))
def test_occupancy_reduction_is_the_expected_entropy_drop_and_never_negative(a: float, b: float, w: float) -> None:
    got = float(occupancy_reduction(np.array([a]), np.array([b]), w)[0])
    np.testing.assert_allclose(got, max(0.0, _occupancy_by_enumeration(a, b, w)), atol=1e-12)
    assert 0.0 <= got <= np.log(2) + 1e-12


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(1.0, 200.0), min_size=2, max_size=15), st.floats(0.1, 50.0))
def test_class_reduction_is_the_expected_entropy_drop_and_never_negative(eta: list[float], w: float) -> None:
    e = np.array(eta)
    got = float(class_reduction(e[:, None], w)[0])
    np.testing.assert_allclose(got, max(0.0, _class_by_enumeration(e, w)), atol=1e-10)
    assert 0.0 <= got <= np.log(len(eta)) + 1e-12


def test_what_one_more_view_can_still_resolve() -> None:
    w = 10.0
    prior, seen_free_once, split, split_often = occupancy_reduction(
        np.array([1.0, 1.0, 11.0, 51.0]), np.array([1.0, 11.0, 11.0, 51.0]), w)
    assert prior > 0.4  # never observed: one view resolves most of it
    assert seen_free_once < 0.25 * prior  # seen free once: little left to learn
    assert split < 0.15 * prior
    assert split_often < 0.1 * split
    vague, sure = class_reduction(np.stack([np.ones(14), np.r_[101.0, np.ones(13)]], axis=1), w)
    assert vague > 0.5
    assert sure < 0.02


def test_the_default_field_counts_the_class_an_unlabelled_object_would_show() -> None:
    """Two beliefs alike in occupancy: an object seen with its class and one at the prior (an unlabelled
    object, ``unknown_evidence: prior``). The default field credits only the second, MEM's alike."""
    svc = IGService(GRID, CAM, small_views(), SHELF, IGConfig())
    mem = IGService(GRID, CAM, small_views(), SHELF, IGConfig(gain="entropy", information="occupancy"))
    known = EvidentialMap.empty(GRID, 15)
    c = GRID.centers()
    box = (np.abs(c[..., 0]) < 0.05) & (np.abs(c[..., 1] - 0.15) < 0.05) & (c[..., 2] < 0.1)
    known.alpha[box], known.beta[box] = 30.0, 1.0
    known.alpha[~box], known.beta[~box] = 1.0, 30.0
    known.eta[3, box] = 60.0
    unknown = known.copy()
    unknown.eta[:, box] = 1.0
    f_known, f_unknown = svc.prepare(known), svc.prepare(unknown)
    inner = box.ravel() & ~shelf_wall_mask(GRID, SHELF).ravel()
    assert inner.sum() > 100
    assert f_unknown.H[inner].min() > 0.5
    assert f_known.H[inner].max() < 0.05
    np.testing.assert_array_equal(mem.prepare(known).H, mem.prepare(unknown).H)
    assert svc.view_ig(f_unknown).max() > 5 * svc.view_ig(f_known).max()


@settings(max_examples=8, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_the_default_field_of_a_sparse_change_equals_a_full_rescore(seed: int) -> None:
    from msmem_core.map.belief import BeliefDelta

    svc = IGService(GRID, CAM, small_views(), SHELF, IGConfig())
    b = random_belief(seed)
    rng = np.random.default_rng(seed)
    idx = np.unique(rng.integers(0, GRID.size, 400))
    f32 = np.float32
    d = BeliefDelta(idx, rng.uniform(1, 30, len(idx)).astype(f32), rng.uniform(1, 30, len(idx)).astype(f32),
                    rng.uniform(1, 30, (b.num_classes, len(idx))).astype(f32))
    base = svc.prepare(b)
    sparse = svc.belief_delta(base, d).apply(base)
    full = svc.prepare(d.apply(b), before=base)
    np.testing.assert_allclose(sparse.H, full.H, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(sparse.p, full.p)
    assert (full.H >= 0).all()


def test_never_observed_prior_credits_the_prior_and_leaves_how_far_rays_get() -> None:
    from msmem_core.map.belief import BeliefDelta

    svc = IGService(GRID, CAM, small_views(), SHELF, IGConfig(never_observed="prior"))
    plain = IGService(GRID, CAM, small_views(), SHELF, IGConfig())
    b = random_belief(3)
    rng = np.random.default_rng(3)
    b.observed = rng.random(GRID.shape) < 0.5
    f, g = svc.prepare(b), plain.prepare(b)
    np.testing.assert_array_equal(f.p, g.p)  # transmission: the predicted occupancy, as without the rule
    never = ~b.observed.ravel() & ~shelf_wall_mask(GRID, SHELF).ravel() & (f.p > 0) & (f.p < 1)
    prior = occupancy_reduction(np.ones(1), np.ones(1), 10.0)[0] + 0.5 * class_reduction(np.ones((14, 1)), 10.0)[0]
    np.testing.assert_allclose(f.H[never], prior, rtol=1e-5)
    idx = np.unique(rng.integers(0, GRID.size, 300))
    f32 = np.float32
    d = BeliefDelta(idx, rng.uniform(1, 30, len(idx)).astype(f32), rng.uniform(1, 30, len(idx)).astype(f32),
                    rng.uniform(1, 30, (b.num_classes, len(idx))).astype(f32))
    sparse = svc.belief_delta(f, d).apply(f)
    after = d.apply(b)
    full = svc.prepare(after, before=f)
    np.testing.assert_array_equal(sparse.p, full.p)
    np.testing.assert_allclose(sparse.H, full.H, rtol=1e-6, atol=1e-7)


def _numpy_information(alpha, beta, eta, p, walls, w):  # type: ignore[no-untyped-def]
    """The default voxel value from the numpy functions, as ``IGService._information_numpy`` composes them."""
    sure = (p <= 0.0) | (p >= 1.0)
    h = np.where(sure, 0.0, occupancy_reduction(alpha, beta, w)) + p * class_reduction(eta[1:], w)
    return np.where(walls, 0.0, h).astype(np.float32)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["C", "F", "strided"]), st.integers(2, 20), st.integers(1, 300))
def test_the_information_kernel_is_numpys_result_in_every_memory_layout(seed: int, layout: str, classes: int,
                                                                       n: int) -> None:
    # numpy sums over the classes one after the other or pairwise, by the memory layout: the kernel must
    # give the same float32 values; prior evidence (1), p clamped to 0 or 1 and walls take short cuts
    from msmem_core.map.gain import voxel_information
    rng = np.random.default_rng(seed)
    alpha = rng.uniform(1.0, 60.0, n).astype(np.float32)
    beta = rng.uniform(1.0, 60.0, n).astype(np.float32)
    eta = rng.uniform(1.0, 40.0, (classes, n)).astype(np.float32)
    eta[rng.random((classes, n)) < 0.4] = 1.0
    p = (alpha / (alpha + beta)).astype(np.float32)
    p[rng.random(n) < 0.2] = 0.0
    p[rng.random(n) < 0.2] = 1.0
    walls = rng.random(n) < 0.1
    if layout == "F":
        eta = np.asfortranarray(eta)
    elif layout == "strided":
        eta = np.repeat(eta, 2, axis=1)[:, ::2]
    want = _numpy_information(alpha, beta, eta, p, walls, 10.0)
    got = voxel_information(alpha, beta, eta, p, walls, 10.0, True)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, want)


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["C", "F", "strided", "column"]), st.integers(1, 40))
def test_the_kernels_class_sums_add_in_numpys_order(seed: int, layout: str, rows: int) -> None:
    from msmem_core.map.gain import _sum, sums_pairwise
    a = np.random.default_rng(seed).uniform(-1.0, 1.0, (rows, 1 if layout == "column" else 50))
    a = {"F": np.asfortranarray(a), "strided": np.repeat(a, 2, axis=1)[:, ::2]}.get(layout, a)
    want = a.sum(axis=0)
    got = np.array([_sum(np.ascontiguousarray(a[:, j]), rows, sums_pairwise(a)) for j in range(a.shape[1])])
    np.testing.assert_array_equal(got, want)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["C", "F", "strided", "column"]), st.integers(1, 40),
       st.integers(0, 300))
def test_the_class_entropy_kernel_is_numpys_categorical_entropy_in_every_memory_layout(
        seed: int, layout: str, classes: int, n: int) -> None:
    # the float32 class sums and the float64 x log x sums add in numpy's order for the layout (one
    # after the other, or pairwise): the same float64 values, bit for bit
    from msmem_core.map.gain import class_entropy
    rng = np.random.default_rng(seed)
    n = 1 if layout == "column" else n
    eta = rng.uniform(1.0, 40.0, (classes, n)).astype(np.float32)
    eta[rng.random((classes, n)) < 0.4] = 1.0  # the prior's evidence
    eta[rng.random((classes, n)) < 0.05] = 1e6  # one class nearly certain
    if layout == "F":
        eta = np.asfortranarray(eta)
    elif layout == "strided":
        eta = np.repeat(eta, 2, axis=1)[:, ::2]
    got = class_entropy(eta)
    assert got.dtype == np.float64
    assert got.shape == (n,)
    np.testing.assert_array_equal(got, categorical_entropy(eta))


@settings(max_examples=12, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["expected-reduction", "entropy"]), st.booleans())
def test_the_batched_deltas_are_the_per_candidate_ones(seed: int, gain: str, no_gain: bool) -> None:
    # the candidates' voxel values in one pass: every candidate's change exactly as belief_delta gives it,
    # with its class evidence in either memory layout, one voxel or none changed, and walls among them
    from msmem_core.map.belief import BeliefDelta

    svc = IGService(GRID, CAM, small_views(), SHELF,
                    IGConfig(gain=gain, predicted_entropy="no-gain" if no_gain else "as-predicted"))  # type: ignore[arg-type]
    b = random_belief(seed)
    base = svc.prepare(b)
    rng = np.random.default_rng(seed)
    f32 = np.float32
    deltas = []
    for k in range(7):
        n = [0, 1, 2, 30, 400, 1200, 57][k]
        idx = np.unique(rng.integers(0, GRID.size, n))
        # large evidence: the class part is a small difference of logarithms, where the order of the
        # class sums shows in float32
        eta = rng.uniform(1, 3e4, (b.num_classes, len(idx))).astype(f32)
        eta[rng.random(eta.shape) < 0.3] = 1.0
        same = rng.random(len(idx)) < 0.2  # some voxels keep the base's evidence: no change
        occ_only = rng.random(len(idx)) < 0.2  # others keep its occupancy evidence: only the class changes
        alpha = rng.uniform(1, 30, len(idx)).astype(f32)
        alpha[rng.random(len(idx)) < 0.2] = 1.0  # the prior: more to gain than the base (no-gain caps it)
        beta = np.where(alpha == 1.0, f32(1.0), rng.uniform(1, 30, len(idx))).astype(f32)
        alpha = np.where(same | occ_only, b.alpha.ravel()[idx], alpha).astype(f32)
        beta = np.where(same | occ_only, b.beta.ravel()[idx], beta).astype(f32)
        eta = np.where(same[None], b.eta.reshape(b.num_classes, -1)[:, idx], eta)
        if k % 2:
            eta = np.ascontiguousarray(eta.T).T
        deltas.append(BeliefDelta(idx, alpha, beta, eta))
    want = [svc.belief_delta(base, d) for d in deltas]
    got = svc.belief_deltas(base, deltas)
    assert len(got) == len(want)
    for w, g in zip(want, got, strict=True):
        for name in ("idx", "p", "H"):
            assert getattr(g, name).dtype == getattr(w, name).dtype
            np.testing.assert_array_equal(getattr(g, name), getattr(w, name))
    if gain == "expected-reduction" and not no_gain:  # each voxel's value as its own array gives it
        from msmem_core.map.gain import voxel_information
        for d, g in zip(deltas, got, strict=True):
            walls = svc.walls[d.idx]
            p, _ = svc._clamp((d.alpha / (d.alpha + d.beta)).astype(f32), walls)
            h = voxel_information(d.alpha, d.beta, d.eta, p, walls, svc.config.observation_evidence, True)
            np.testing.assert_array_equal(g.H, h[np.searchsorted(d.idx, g.idx)])


def test_the_class_entropy_at_some_voxels_is_the_whole_arrays_there() -> None:
    # at idx only, but with the sums of the whole array's layout (eta[:, idx] is column-major: its
    # sums would be pairwise where the whole C-ordered array's are not)
    from msmem_core.map.gain import class_entropy_at
    rng = np.random.default_rng(5)
    eta = rng.uniform(1.0, 3e4, (15, 4000)).astype(np.float32)
    eta[rng.random(eta.shape) < 0.4] = 1.0
    idx = np.unique(rng.integers(0, 4000, 900))
    for a in (eta, np.asfortranarray(eta)):
        np.testing.assert_array_equal(class_entropy_at(a, idx), categorical_entropy(a)[idx])
    assert not np.array_equal(categorical_entropy(eta[:, idx]), categorical_entropy(eta)[idx])


def test_the_batched_class_entropies_are_each_arrays_own() -> None:
    from msmem_core.map.gain import class_entropies, class_entropy
    rng = np.random.default_rng(9)
    etas = []
    for k, n in enumerate([0, 1, 2, 700, 33, 1500]):
        e = rng.uniform(1.0, 3e4, (15, n)).astype(np.float32)
        e[rng.random(e.shape) < 0.4] = 1.0
        etas.append(np.ascontiguousarray(e.T).T if k % 2 else e)  # both layouts: pairwise and not
    got = class_entropies(etas)
    for e, g in zip(etas, got, strict=True):
        np.testing.assert_array_equal(g, class_entropy(e))
