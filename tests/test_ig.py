"""IG of candidate views matches a brute-force reference, and the view lookahead uses it correctly."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msmem_core.map import raycast
from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig import IGConfig, IGField, IGService, shelf_wall_mask
from msmem_core.map.ig_reference import after_view_reference, ig_rays_reference, traverse
from msmem_core.world.camera import CameraConfig
from msmem_core.world.geometry import look_at
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ShelfSpec

MEM = {"gain": "entropy", "information": "occupancy"}
"""MEM's IG (the paper): a voxel counts the entropy of its clamped occupancy."""

SHELF = ShelfSpec(width_m=0.16, depth_m=0.12, height_m=0.08)
GRID = GridSpec.around_box(SHELF.interior_lower, SHELF.interior_upper, 0.01)  # 18 x 14 x 10
CAM = CameraConfig(width_px=64, height_px=48)  # every 8th pixel: 8 x 6 = 48 rays per view
NUM_VIEWS = 6


def small_views(seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    target = np.array([0.0, 0.06, 0.04])
    poses = []
    for _ in range(NUM_VIEWS):
        eye = target + np.array([rng.uniform(-0.15, 0.15), -rng.uniform(0.2, 0.35), rng.uniform(-0.05, 0.15)])
        poses.append(look_at(eye, target + rng.normal(scale=0.02, size=3)))
    return np.stack(poses)


def service(early_exit: float = 1e-3) -> IGService:
    return IGService(GRID, CAM, small_views(), SHELF, IGConfig(early_exit=early_exit, **MEM))


def random_belief(seed: int) -> EvidentialMap:
    """Evidence spanning free (clamped), unknown, uncertain and occupied (clamped) voxels."""
    rng = np.random.default_rng(seed)
    b = EvidentialMap.empty(GRID)
    kind = rng.integers(0, 4, GRID.shape)
    b.alpha[:] = np.where(kind == 3, 41.0, 1.0) + np.where(kind == 2, rng.uniform(0, 8, GRID.shape), 0.0)
    b.beta[:] = np.where(kind == 0, 41.0, 1.0) + np.where(kind == 2, rng.uniform(0, 8, GRID.shape), 0.0)
    return b


def test_ig_entropy_is_in_nats_and_clamped_as_mem() -> None:
    svc = service()
    b = random_belief(1)
    f = svc.prepare(b)
    p = b.expected_occupancy().ravel()
    walls = shelf_wall_mask(GRID, SHELF).ravel()
    assert np.all(f.p[walls] == 1.0)
    assert np.all(f.H[walls] == 0.0)
    assert np.all(f.p[(p > 0.95)] == 1.0)
    assert np.all(f.p[(p < 0.05) & ~walls] == 0.0)
    unknown = (p == 0.5) & ~walls
    np.testing.assert_allclose(f.H[unknown], np.log(2), rtol=1e-6)


def test_shelf_walls_are_the_margin_voxels_except_the_open_front() -> None:
    m = shelf_wall_mask(GRID, SHELF)
    assert not m[1:-1, 1:-1, 1:-1].any()  # interior
    assert m[0, 1:, :].all()
    assert m[-1, 1:, :].all()
    assert m[:, -1, :].all()  # back
    assert m[:, 1:, 0].all()
    assert m[:, 1:, -1].all()
    assert not m[:, 0, :].any()  # open front (y < 0)


@settings(max_examples=8, deadline=None)
@given(st.integers(0, 2**31 - 1))
def test_exact_ig_matches_the_float64_reference(seed: int) -> None:
    svc = service()
    f = svc.prepare(random_belief(seed))
    ref, _ = ig_rays_reference(f.p, f.H, svc.origins, svc.dirs, GRID, svc.t_min, svc.t_max)
    np.testing.assert_allclose(svc.ray_ig(f, exact=True), ref, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(svc.view_ig(f, exact=True), ref.sum(axis=1), rtol=1e-6)


@settings(max_examples=8, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([1e-3, 0.05, 0.3]))
def test_early_exit_error_per_ray_is_bounded_by_eps_times_the_entropy_left(seed: int, eps: float) -> None:
    svc = service(early_exit=eps)
    f = svc.prepare(random_belief(seed))
    exact, _ = ig_rays_reference(f.p, f.H, svc.origins, svc.dirs, GRID, svc.t_min, svc.t_max)
    same_rule, left = ig_rays_reference(f.p, f.H, svc.origins, svc.dirs, GRID, svc.t_min, svc.t_max, eps)
    fast = svc.ray_ig(f)
    np.testing.assert_allclose(fast, same_rule, rtol=1e-6, atol=1e-12)
    err = exact - fast
    assert np.all(err >= -1e-9)
    assert np.all(err <= eps * left + 1e-9)


@settings(max_examples=10, deadline=None)
@given(st.integers(0, 2**31 - 1), st.floats(0.0, 1.0))
def test_ig_is_never_negative(seed: int, unknown_fraction: float) -> None:
    rng = np.random.default_rng(seed)
    b = EvidentialMap.empty(GRID)
    b.alpha[:] = rng.uniform(1, 60, GRID.shape)
    b.beta[:] = rng.uniform(1, 60, GRID.shape)
    keep = rng.random(GRID.shape) < unknown_fraction
    b.alpha[keep] = b.beta[keep] = 1.0
    svc = service()
    f = svc.prepare(b)
    assert np.all(svc.view_ig(f) >= 0)
    assert np.all(svc.view_ig(f, exact=True) >= 0)


def test_a_fully_known_map_has_no_ig() -> None:
    rng = np.random.default_rng(0)
    b = EvidentialMap.empty(GRID)
    occupied = rng.random(GRID.shape) < 0.2
    b.alpha[occupied] = 25.0
    b.beta[~occupied] = 25.0
    svc = service()
    assert np.all(svc.view_ig(svc.prepare(b)) == 0.0)
    assert np.all(svc.view_ig(svc.prepare(EvidentialMap.empty(GRID))) > 1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_after_view_zeroes_exactly_the_voxels_up_to_each_rays_first_confident_hit(seed: int) -> None:
    svc = service()
    f = svc.prepare(random_belief(seed))
    for view in range(NUM_VIEWS):
        after = svc.after_view(f, view)
        expected = after_view_reference(f.p, f.H, svc.origins[view], svc.dirs[view], GRID, svc.t_min, svc.t_max)
        np.testing.assert_array_equal(after.H, expected)
        assert after.p is f.p
        assert np.any(after.H != f.H)
        assert svc.view_ig(after)[view] == 0.0  # seeing the same view again gains nothing


def test_batched_beliefs_equal_separate_calls() -> None:
    svc = service()
    fields = [svc.prepare(random_belief(s)) for s in range(5)]
    batch = svc.view_ig(fields)
    assert batch.shape == (5, NUM_VIEWS)
    for k, f in enumerate(fields):
        np.testing.assert_array_equal(batch[k], svc.view_ig(f))
    np.testing.assert_array_equal(svc.view_ig(fields, exact=True)[2], svc.view_ig(fields[2], exact=True))


def test_best_two_step_skips_visited_views_and_looks_one_view_ahead() -> None:
    svc = service()
    f = svc.prepare(random_belief(4))
    ig = svc.view_ig(f)
    best = int(np.argmax(ig))
    v1, ig1, v2, ig2 = svc.best_two_step(f, set())
    assert (v1, ig1) == (best, ig[best])
    after = svc.view_ig(svc.after_view(f, v1))
    assert v2 != v1
    assert ig2 == after[v2] == max(after[v] for v in range(NUM_VIEWS) if v != v1)

    excluded = {best, 2}
    v1, ig1, v2, _ = svc.best_two_step(f, excluded)
    assert v1 not in excluded
    assert v2 not in excluded | {v1}
    assert ig1 == max(ig[v] for v in range(NUM_VIEWS) if v not in excluded)

    assert svc.best_two_step(f, set(range(1, NUM_VIEWS)))[2:] == (-1, 0.0)
    with pytest.raises(ValueError, match="excluded"):
        svc.best_two_step(f, set(range(NUM_VIEWS)))


@settings(max_examples=30, deadline=None)
@given(
    st.integers(0, 2**31 - 1),
    st.sampled_from(["random", "axis", "inside"]),
)
def test_dda_visits_the_same_voxels_as_an_independent_traversal(seed: int, kind: str) -> None:
    rng = np.random.default_rng(seed)
    lo, hi = GRID.origin, GRID.upper_m
    if kind == "inside":
        o = rng.uniform(lo, hi)
    else:
        o = rng.uniform(lo - 0.3, hi + 0.3)
    d = rng.normal(size=3)
    if kind == "axis":  # parallel to one or two grid axes
        d[rng.choice(3, size=int(rng.integers(1, 3)), replace=False)] = 0.0
        if not d.any():
            d[0] = 1.0
    g0, s, n = raycast.grid_params(GRID)
    nb = int(n.sum())
    vox, tin, tout = np.empty(nb, np.int64), np.empty(nb), np.empty(nb)
    m = raycast.traverse(*o, *d, g0, s, n, 0.0, 5.0, np.zeros(0, np.uint8), vox, tin, tout)
    ref_vox, ref_in, ref_out = traverse(o, d, GRID, 0.0, 5.0)
    np.testing.assert_array_equal(vox[:m], ref_vox)
    np.testing.assert_allclose(tin[:m], ref_in, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(tout[:m], ref_out, rtol=1e-9, atol=1e-12)


def test_field_copy_is_independent() -> None:
    f = IGField(np.zeros(3, np.float32), np.ones(3, np.float32))
    g = f.copy()
    g.H[0] = 5
    assert f.H[0] == 1
