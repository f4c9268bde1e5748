"""IG's helpers checked against brute force on their edges: the shelf masks at voxel centres that lie
exactly on the interior's faces, the deduplication of candidate changes, a change applied to a field,
and the service's coarse rays (tests that catch the planted bugs mutmut makes in
``msmem_core/map/ig.py``; docs/explanation/reliability.md)."""

from __future__ import annotations

import numpy as np
import pytest
from test_ig import CAM, GRID, SHELF, random_belief, service, small_views

from msmem_core.map.ig import (
    IGConfig,
    IGDelta,
    IGField,
    IGService,
    _unique_deltas,
    shelf_interior_mask,
    shelf_wall_mask,
)
from msmem_core.util.trace import Span, Tracer, tracing
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import ShelfSpec

MEM = {"gain": "entropy", "information": "occupancy"}
"""MEM's IG (the paper): a voxel counts the entropy of its clamped occupancy."""

# every number a binary fraction: voxel centres land exactly on the interior's faces (x = +-0.375,
# y = 0 and 0.375, z = 0 and 0.25), so < against <= and > against >= decide those voxels
EXACT_SHELF = ShelfSpec(width_m=0.75, depth_m=0.375, height_m=0.25)
EXACT_GRID = GridSpec(origin_m=(-0.53125, -0.15625, -0.15625), voxel_m=0.0625, shape=(17, 11, 9))


def _brute_force(grid: GridSpec, shelf: ShelfSpec) -> tuple[np.ndarray, np.ndarray]:
    lo, hi = shelf.interior_lower.tolist(), shelf.interior_upper.tolist()
    walls, interior = np.zeros(grid.shape, bool), np.zeros(grid.shape, bool)
    for i, j, k in np.ndindex(*grid.shape):
        c = [grid.origin_m[a] + (n + 0.5) * grid.voxel_m for a, n in enumerate((i, j, k))]
        inside = all(lo[a] <= c[a] <= hi[a] for a in range(3))
        interior[i, j, k] = inside
        walls[i, j, k] = not inside and c[1] >= lo[1]  # outside, but not in front of the open side
    return walls, interior


def test_shelf_masks_equal_brute_force_with_centres_on_the_faces():
    centres = EXACT_GRID.centers()
    for axis, values in ((0, (-0.375, 0.375)), (1, (0.0, 0.375)), (2, (0.0, 0.25))):
        for v in values:
            assert (centres[..., axis] == v).any()  # the edge cases are in the grid
    walls, interior = _brute_force(EXACT_GRID, EXACT_SHELF)
    got_walls, got_interior = shelf_wall_mask(EXACT_GRID, EXACT_SHELF), shelf_interior_mask(EXACT_GRID, EXACT_SHELF)
    assert got_walls.shape == got_interior.shape == EXACT_GRID.shape
    assert got_walls.dtype == got_interior.dtype == np.bool_
    np.testing.assert_array_equal(got_walls, walls)
    np.testing.assert_array_equal(got_interior, interior)
    # the closed interior and the walls never overlap; what is neither lies in front of the shelf
    assert not (got_walls & got_interior).any()
    assert (centres[~got_walls & ~got_interior][:, 1] < 0).all()
    # and on the usual 1 cm grid of the IG tests
    walls, interior = _brute_force(GRID, SHELF)
    np.testing.assert_array_equal(shelf_wall_mask(GRID, SHELF), walls)
    np.testing.assert_array_equal(shelf_interior_mask(GRID, SHELF), interior)


def _delta(idx, p, h) -> IGDelta:
    return IGDelta(np.asarray(idx, np.int64), np.asarray(p, np.float32), np.asarray(h, np.float32))


def test_unique_deltas_merge_only_identical_changes():
    a = _delta([1, 5], [0.2, 1.0], [0.5, 0.0])
    same = _delta([1, 5], [0.2, 1.0], [0.5, 0.0])
    other_p = _delta([1, 5], [0.3, 1.0], [0.5, 0.0])
    other_h = _delta([1, 5], [0.2, 1.0], [0.6, 0.0])
    other_idx = _delta([1, 6], [0.2, 1.0], [0.5, 0.0])
    out, same_as = _unique_deltas([a, other_p, same, other_h, other_idx, a])
    assert same_as.dtype == np.int64
    assert same_as.tolist() == [0, 1, 0, 2, 3, 0]
    assert [d is x for d, x in zip(out, [a, other_p, other_h, other_idx], strict=True)] == [True] * 4
    empty, none = _unique_deltas([])
    assert empty == []
    assert none.shape == (0,)


def test_a_delta_applied_to_a_field_changes_only_its_voxels_and_leaves_the_base():
    base = IGField(np.full(6, 0.5, np.float32), np.full(6, 0.69, np.float32))
    out = _delta([1, 4], [0.0, 1.0], [0.0, 0.0]).apply(base)
    np.testing.assert_array_equal(out.p, np.array([0.5, 0.0, 0.5, 0.5, 1.0, 0.5], np.float32))
    np.testing.assert_array_equal(out.H, np.array([0.69, 0.0, 0.69, 0.69, 0.0, 0.69], np.float32))
    np.testing.assert_array_equal(base.p, np.full(6, 0.5, np.float32))  # a copy, not the base
    np.testing.assert_array_equal(base.H, np.full(6, 0.69, np.float32))


def test_service_keeps_its_inputs_and_coarse_rays_subsample_both_image_axes():
    views = small_views().astype(np.float32)  # float32 poses are widened, not kept
    svc = IGService(GRID, CAM, views, SHELF, IGConfig(**MEM))
    assert svc.camera is CAM
    assert svc.viewpoints.dtype == np.float64
    assert svc.walls.shape == (GRID.size,)
    np.testing.assert_array_equal(svc.walls, shelf_wall_mask(GRID, SHELF).ravel())
    h, w = CAM.pixel_rays(svc.config.ray_stride_px).shape[:2]
    coarse = svc.coarse_rays(2)
    assert svc.coarse_rays(2) is coarse  # built once
    assert svc.coarse_rays(1) is svc.rays
    assert coarse.dirs.shape[:2] == (svc.num_views, len(range(0, h, 2)) * len(range(0, w, 2)))
    full = svc.dirs.reshape(svc.num_views, h, w, 3)[:, ::2, ::2].reshape(svc.num_views, -1, 3)
    np.testing.assert_allclose(np.sort(coarse.dirs.reshape(-1, 3), axis=0), np.sort(full.reshape(-1, 3), axis=0))
    with pytest.raises(ValueError, match=r"viewpoints must be \[V, 4, 4\] camera-to-world poses, got \(4, 4\)"):
        IGService(GRID, CAM, np.eye(4), SHELF)
    with pytest.raises(ValueError, match=r"viewpoints must be \[V, 4, 4\] camera-to-world poses, got \(2, 3, 4\)"):
        IGService(GRID, CAM, np.zeros((2, 3, 4)), SHELF)  # three axes, but not 4 x 4 matrices


def test_prepare_refuses_a_belief_on_another_grid():
    svc = service()
    other = GridSpec(origin_m=GRID.origin_m, voxel_m=GRID.voxel_m, shape=(GRID.shape[0] + 1, *GRID.shape[1:]))
    from msmem_core.map.belief import EvidentialMap

    with pytest.raises(ValueError, match=r"^belief grid differs from the IG service's grid$"):
        svc.prepare(EvidentialMap.empty(other))
    assert svc.prepare(random_belief(0)).p.dtype == np.float32


@pytest.mark.parametrize("exact", [False, True])
def test_coarse_incremental_ig_equals_the_coarse_sweep_of_each_changed_field(exact):
    """``view_ig_delta`` with ``ray_step`` 2 re-scores the screening rays exactly as a fresh coarse sweep of
    the changed field would, with the early exit as asked (a large one, so that it matters)."""
    from test_ig_incremental import random_deltas

    svc = service(early_exit=0.3)
    rng = np.random.default_rng(11)
    belief = random_belief(5)
    base = svc.prepare(belief)
    deltas = [svc.belief_delta(base, d) for d in random_deltas(belief, rng, 4)]
    assert all(len(d.idx) for d in deltas)
    got = svc.view_ig_delta(base, deltas, exact=exact, ray_step=2)
    want = np.stack([svc.sweep(d.apply(base), exact=exact, ray_step=2) for d in deltas])
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-12)
    # the screening estimate is not the full-density IG, and the early exit changes it
    assert not np.allclose(got, svc.view_ig_delta(base, deltas, exact=exact, ray_step=1))
    assert not np.allclose(svc.sweep(base, exact=exact), svc.sweep(base, exact=not exact))
    np.testing.assert_allclose(svc.sweep(base, exact=exact), svc.view_ig(base, exact=exact), rtol=1e-9)


def test_defaults_are_the_early_exit_at_full_ray_density():
    """``sweep``, ``view_ig`` and ``view_ig_delta`` default to the configured early exit over every ray."""
    from test_ig_incremental import random_deltas

    svc = service(early_exit=0.3)
    belief = random_belief(7)
    base = svc.prepare(belief)
    deltas = [svc.belief_delta(base, d) for d in random_deltas(belief, np.random.default_rng(2), 3)]
    early = svc.view_ig(base, exact=False)
    assert not np.allclose(early, svc.view_ig(base, exact=True))  # the early exit matters here
    np.testing.assert_allclose(svc.view_ig(base), early, rtol=1e-12)
    np.testing.assert_allclose(svc.sweep(base), early, rtol=1e-9)
    want = svc.view_ig_delta(base, deltas, exact=False, ray_step=1)
    np.testing.assert_allclose(svc.view_ig_delta(base, deltas), want, rtol=1e-12)
    np.testing.assert_allclose(want, np.stack([svc.view_ig(d.apply(base)) for d in deltas]), rtol=1e-9)


def test_empty_batches_give_no_rows():
    svc = service()
    base = svc.prepare(random_belief(1))
    for got in (svc.view_ig([]), svc.view_ig_delta(base, []), svc.view_ig_delta(base, [], exact=True, ray_step=2)):
        assert got.shape == (0, svc.num_views)


@pytest.mark.parametrize("exact", [False, True])
def test_a_ray_lying_on_the_low_faces_of_the_changed_voxel_is_rescored(exact):
    """The incremental ray filter widens its box around the changed voxels: a ray running exactly along
    the voxel's low x and z faces (the traversal puts it in that voxel) still sees the change."""
    from msmem_core.map.belief import EvidentialMap
    from msmem_core.world.camera import CameraConfig

    cam = CameraConfig(width_px=72, height_px=56)  # every 8th pixel: u = 36, v = 28 is the principal point
    assert np.flatnonzero((cam.pixel_rays(8)[..., :2] == 0).all(axis=-1)).size == 1
    g, s = np.asarray(EXACT_GRID.origin_m), EXACT_GRID.voxel_m
    i, j, k = 8, 4, 3
    pose = np.eye(4)
    pose[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # camera x -> world x, y (down) -> -z, z -> +y
    pose[:3, 3] = [g[0] + i * s, -0.5, g[2] + k * s]  # on the low x and z faces of voxel (i, ., k)
    svc = IGService(EXACT_GRID, cam, pose[None], EXACT_SHELF, IGConfig(**MEM))
    base = svc.prepare(EvidentialMap.empty(EXACT_GRID))
    flat = np.ravel_multi_index((i, j, k), EXACT_GRID.shape)
    assert base.p[flat] == 0.5
    assert not svc.walls[flat]
    delta = _delta([flat], [1.0], [0.0])
    want = svc.view_ig(delta.apply(base), exact=exact)
    assert not np.allclose(want, svc.view_ig(base, exact=exact))  # the change is seen
    np.testing.assert_allclose(svc.view_ig_delta(base, [delta], exact=exact)[0], want, rtol=1e-9)


def test_unique_deltas_compare_values_not_the_dtypes_they_came_in():
    """A change handed over as Python ints / float64 is the same change as the int64 / float32 one."""
    a = _delta([1, 5], [0.25, 1.0], [0.5, 0.0])
    for b in (IGDelta(np.array([1, 5], np.int32), a.p, a.H), IGDelta(a.idx, a.p.astype(np.float64), a.H),
              IGDelta(a.idx, a.p, a.H.astype(np.float64))):
        out, same = _unique_deltas([a, b])
        assert len(out) == 1
        assert same.tolist() == [0, 0]


def test_the_clamp_is_strict_at_its_thresholds():
    """MEM's clamp: *above* p_occ_clamp is occupied, *below* p_free_clamp is free; the thresholds
    themselves stay uncertain (binary-exact thresholds, so that p lands exactly on them)."""
    from msmem_core.map.belief import EvidentialMap

    svc = IGService(GRID, CAM, small_views(), SHELF, IGConfig(p_occ_clamp=0.75, p_free_clamp=0.25, **MEM))
    b = EvidentialMap.empty(GRID)
    inside = np.flatnonzero(~svc.walls)[:4]
    for flat, (a, bb) in zip(inside, [(3.0, 1.0), (1.0, 3.0), (7.0, 1.0), (1.0, 7.0)], strict=True):
        b.alpha.reshape(-1)[flat], b.beta.reshape(-1)[flat] = a, bb
    f = svc.prepare(b)
    np.testing.assert_array_equal(f.p[inside], np.array([0.75, 0.25, 1.0, 0.0], np.float32))
    assert (f.H[inside[:2]] > 0).all()
    assert (f.H[inside[2:]] == 0).all()


def test_field_delta_lists_exactly_the_voxels_whose_p_or_h_differ():
    base = IGField(np.array([0.5, 0.5, 1.0, 0.0, 0.2], np.float32), np.array([0.69, 0.69, 0.0, 0.0, 0.5], np.float32))
    field = IGField(base.p.copy(), base.H.copy())
    field.p[1], field.H[3] = 0.0, 0.1  # p alone changes at 1, H alone at 3
    d = service().field_delta(base, field)
    assert d.idx.tolist() == [1, 3]
    np.testing.assert_array_equal(d.p, field.p[[1, 3]])
    np.testing.assert_array_equal(d.H, field.H[[1, 3]])
    np.testing.assert_array_equal(d.apply(base).p, field.p)


def test_remembered_sweeps_are_keyed_by_field_ray_step_and_early_exit():
    svc = service(early_exit=0.3)
    a, b = svc.prepare(random_belief(3)), svc.prepare(random_belief(4))
    fresh = service(early_exit=0.3)
    for field, step, exact in ((a, 1, False), (b, 1, False), (a, 2, False), (a, 1, True), (b, 2, True)):
        np.testing.assert_allclose(svc.sweep(field, exact=exact, ray_step=step),
                                   fresh.sweep(field.copy(), exact=exact, ray_step=step), rtol=1e-12)


class _Stages(Tracer):
    def __init__(self) -> None:
        self.seen: list[tuple[str, dict]] = []

    def begin(self, span: Span) -> None:
        self.seen.append((span.stage, dict(span.info)))


def test_ig_stages_are_reported_by_name_with_what_they_work_on():
    """``msmem perf step`` times IG by these span names and attributes."""
    from test_ig_incremental import random_deltas

    svc = service()
    belief = random_belief(2)
    rec = _Stages()
    with tracing(rec):
        base = svc.prepare(belief)
        svc.sweep(base, ray_step=2)
        deltas = [svc.belief_delta(base, d) for d in random_deltas(belief, np.random.default_rng(0), 3)]
        svc.view_ig_delta(base, deltas, ray_step=2)
        svc.view_ig_delta(base, deltas[:2], views=np.array([1, 4]))
        svc.view_ig(base)
        svc.views_ig(base, [0, 5, 2])
        svc.after_view(base, 0)
    assert rec.seen == [("ig.prepare", {}), ("ig.sweep", {"ray_step": 2}),
                        ("ig.incremental", {"ray_step": 2, "candidates": 3, "views": 6}),
                        ("ig.incremental", {"ray_step": 1, "candidates": 2, "views": 2}), ("ig.sweep", {}),
                        ("ig.views", {"views": 3}), ("ig.after_view", {})]


def test_view_ig_delta_over_some_views_equals_those_columns_of_the_full_call():
    from test_ig_incremental import random_deltas

    svc = service()
    belief = random_belief(3)
    base = svc.prepare(belief)
    deltas = [svc.belief_delta(base, d) for d in random_deltas(belief, np.random.default_rng(1), 4)]
    for exact in (False, True):
        full = svc.view_ig_delta(base, deltas, exact=exact)
        for views in ([2], [5, 0, 3], list(range(svc.num_views))):
            np.testing.assert_allclose(svc.view_ig_delta(base, deltas, exact=exact, views=np.array(views)),
                                       full[:, views], rtol=1e-12)
        assert svc.view_ig_delta(base, [], views=np.array([1, 2])).shape == (0, 2)


def test_a_removed_surface_opens_the_rays_behind_it():
    """A voxel that was certainly occupied (p = 1: base rays stop there) and that a candidate frees must
    not stop that candidate's rays: what lies behind it is scored as a fresh sweep would."""
    from msmem_core.map.belief import EvidentialMap

    svc = service()
    belief = EvidentialMap.empty(GRID)
    base = svc.prepare(belief)
    inside = np.flatnonzero(~svc.walls & (base.p == 0.5))
    for flat in inside[len(inside) // 2: len(inside) // 2 + 40: 8]:  # single voxels (slot 0) mid-shelf
        wall = IGField(base.p.copy(), base.H.copy())
        wall.p[flat], wall.H[flat] = 1.0, 0.0
        freed = _delta([flat], [0.0], [0.0])
        for exact in (False, True):
            want = svc.view_ig(freed.apply(wall), exact=exact)
            np.testing.assert_allclose(svc.view_ig_delta(wall, [freed], exact=exact)[0], want, rtol=1e-9)


def test_best_two_step_ignores_unknown_views_and_uses_the_callers_first_ig():
    svc = service()
    f = svc.prepare(random_belief(4))
    plain = svc.best_two_step(f)
    # indices that name no view (a stale exclusion list) are ignored, at both ends of the range
    assert svc.best_two_step(f, {-1, svc.num_views, svc.num_views + 3}) == plain
    with pytest.raises(ValueError, match=r"^every viewpoint is excluded$"):
        svc.best_two_step(f, set(range(svc.num_views)))
    # ``first`` stands in for view_ig(field): the first view is its argmax, with its value
    other = (plain[0] + 1) % svc.num_views
    first = np.zeros(svc.num_views)
    first[other] = 5.0
    v1, ig1, v2, _ = svc.best_two_step(f, first=first)
    assert (v1, ig1) == (other, 5.0)
    assert v2 != v1


def test_views_ig_equals_the_full_sweep_view_for_view():
    svc = service()
    f = svc.prepare(random_belief(6))
    full = svc.view_ig(f)
    for views in ([3], [5, 0, 2], list(range(svc.num_views))):
        np.testing.assert_array_equal(svc.views_ig(f, views), full[views])
    assert svc.views_ig(f, []).shape == (0,)


@pytest.mark.parametrize("finalists", [1, 2, 3])
def test_screened_view_ig_scores_its_finalists_exactly_and_ranks_no_other_view_above_them(finalists):
    svc = service()
    f = svc.prepare(random_belief(7))
    full = svc.view_ig(f)
    coarse = svc.sweep(f, ray_step=2)
    views = np.array([4, 1, 5, 0, 2])
    values, exact = svc.screened_view_ig(f, views, 2, finalists)
    assert exact.sum() == finalists
    # the finalists are the best screened views, scored at full density
    top = views[np.argsort(-coarse[views], kind="stable")[:finalists]]
    assert set(views[exact].tolist()) == set(top.tolist())
    np.testing.assert_array_equal(values[exact], full[views[exact]])
    assert np.all(values[~exact] <= values[exact].min())
    # the others: screened value times the finalists' median full/screened ratio, capped
    ratio = np.median(full[views[exact]] / coarse[views[exact]])
    np.testing.assert_allclose(values[~exact], np.minimum(coarse[views[~exact]] * ratio, values[exact].min()),
                               rtol=1e-12)
    # no screening (ray step 1, or no more views than finalists): every view exact
    for step, k in ((1, finalists), (2, len(views))):
        values, exact = svc.screened_view_ig(f, views, step, k)
        assert exact.all()
        np.testing.assert_array_equal(values, full[views])


def test_a_screened_second_view_is_the_best_full_density_one_among_the_finalists():
    svc = service()
    f = svc.prepare(random_belief(8))
    v1, ig1, v2, ig2 = svc.best_two_step(f, {2})
    after = svc.view_ig(svc.after_view(f, v1))
    # with every remaining view a finalist, screening changes nothing
    assert svc.best_two_step(f, {2}, ray_step=2, finalists=svc.num_views) == (v1, ig1, v2, ig2)
    s1, sig1, s2, sig2 = svc.best_two_step(f, {2}, ray_step=2, finalists=1)
    assert (s1, sig1) == (v1, ig1)
    assert s2 not in (v1, 2)
    assert sig2 == after[s2]
    assert sig2 <= ig2
    rest = [v for v in range(svc.num_views) if v not in (v1, 2)]
    screened = svc._coarse_sweep(svc.after_view(f, v1), 2)
    assert s2 == rest[int(np.argmax(screened[rest]))]
