"""The evidential map and the analytic observation update (sigma_o) integrate depth frames correctly."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats
from hypothesis import given, settings
from hypothesis import strategies as st
from msmem_analytic.observation import AnalyticObservationConfig, AnalyticObservationModel
from pydantic import ValidationError

from msmem_core.map.belief import EvidentialMap
from msmem_core.map.ig_reference import traverse
from msmem_core.world.camera import CameraConfig, Observation
from msmem_core.world.geometry import look_at
from msmem_core.world.grid import GridSpec
from msmem_core.world.scene import NUM_CLASSES

GRID = GridSpec(origin_m=(-0.1, -0.01, -0.01), voxel_m=0.01, shape=(20, 16, 12))
CAM = CameraConfig(width_px=160, height_px=120)
TAU_CHI = 0.5


def plane_observation(pose: np.ndarray, plane_y: float, label: int, camera: CameraConfig = CAM) -> Observation:
    """Depth + labels of the infinite plane y = plane_y seen from ``pose`` (z-depth, pixel centres)."""
    k = camera.intrinsics
    v, u = np.mgrid[0 : camera.height_px, 0 : camera.width_px]
    cam = np.stack([(u + 0.5 - k[0, 2]) / k[0, 0], (v + 0.5 - k[1, 2]) / k[1, 1], np.ones(u.shape)], -1)
    d_world = cam @ pose[:3, :3].T
    z = (plane_y - pose[1, 3]) / d_world[..., 1]
    depth = np.where((z > camera.near_m) & (z < camera.far_m), z, 0.0).astype(np.float32)
    labels = np.where(depth > 0, label, 0).astype(np.int16)
    return Observation(depth, labels, k, pose)


def pose_facing_plane(dx: float = 0.0, dz: float = 0.0) -> np.ndarray:
    eye = np.array([0.0031 + dx, -0.2513, 0.0517 + dz])
    return look_at(eye, eye + np.array([0.013, 1.0, 0.021]))


PLANE_Y = 0.0937  # inside voxel row j = 10 (y in [0.09, 0.10)), away from its faces


def test_empty_map_is_the_uninformed_prior() -> None:
    b = EvidentialMap.empty(GRID)
    assert b.eta.shape == (NUM_CLASSES, *GRID.shape)
    assert np.all(b.expected_occupancy() == 0.5)
    assert np.all(b.vacuity() == 1.0)
    np.testing.assert_allclose(b.occupancy_entropy(), np.log(2))
    np.testing.assert_allclose(b.semantic_entropy(), np.log(NUM_CLASSES), rtol=1e-6)
    assert np.all(b.argmax_class(TAU_CHI) == -1)
    assert b.argmax_class(TAU_CHI).dtype == np.int64
    assert (b.alpha.dtype, b.beta.dtype, b.eta.dtype) == (np.float32,) * 3


def test_entropies_are_shannon_entropies_of_the_expected_distributions() -> None:
    rng = np.random.default_rng(3)
    b = EvidentialMap.empty(GRID)
    b.alpha[:] = rng.uniform(1, 50, GRID.shape)
    b.beta[:] = rng.uniform(1, 50, GRID.shape)
    b.eta[:] = rng.uniform(1, 30, b.eta.shape)
    p = b.expected_occupancy().astype(np.float64)
    np.testing.assert_allclose(b.occupancy_entropy(), scipy.stats.entropy(np.stack([p, 1 - p]), axis=0), rtol=1e-6)
    expected = scipy.stats.entropy(b.class_probs().astype(np.float64), axis=0)
    np.testing.assert_allclose(b.semantic_entropy(), expected, rtol=1e-5)
    np.testing.assert_allclose(b.total_semantic_entropy(), b.semantic_entropy().sum(), rtol=1e-9)


def test_save_and_load_round_trip(tmp_path) -> None:  # type: ignore[no-untyped-def]
    rng = np.random.default_rng(0)
    b = EvidentialMap.empty(GRID)
    b.alpha[:] = rng.uniform(1, 5, GRID.shape)
    b.save(tmp_path / "belief.npz")
    c = EvidentialMap.load(tmp_path / "belief.npz")
    assert c.grid == b.grid
    for name in ("alpha", "beta", "eta"):
        np.testing.assert_array_equal(getattr(c, name), getattr(b, name))
        assert getattr(c, name).dtype == np.float32  # the belief is float32 however the file stores it


def test_weights_must_be_positive() -> None:
    for field in ("w_occ", "w_free", "w_cls", "pixel_stride"):
        with pytest.raises(ValidationError):
            AnalyticObservationConfig(**{field: 0})
    assert AnalyticObservationModel(w_occ=3.0).config.w_occ == 3.0


def test_a_plane_marks_the_voxels_holding_its_returns_occupied_and_the_space_before_it_free() -> None:
    model = AnalyticObservationModel()
    obs = plane_observation(pose_facing_plane(), PLANE_Y, label=4)
    free, occ, seen = model.masks(EvidentialMap.empty(GRID), obs)

    st_ = model.config.pixel_stride
    v, u = np.nonzero(obs.depth[::st_, ::st_] > 0)
    k = obs.intrinsics
    z = obs.depth[::st_, ::st_][v, u].astype(np.float64)
    pc = np.stack([(u * st_ + 0.5 - k[0, 2]) / k[0, 0] * z, (v * st_ + 0.5 - k[1, 2]) / k[1, 1] * z, z], -1)
    hits = pc @ obs.camera_to_world[:3, :3].T + obs.camera_to_world[:3, 3]
    idx = GRID.index_of(hits)
    inside = GRID.contains_index(idx)
    assert inside.sum() > 100
    expected_occ = np.zeros(GRID.shape, bool)
    expected_occ[tuple(idx[inside].T)] = True
    np.testing.assert_array_equal(occ, expected_occ)
    assert np.all(np.nonzero(occ)[1] == 10)
    assert np.array_equal(np.nonzero(seen.any(axis=0)), np.nonzero(occ))
    assert seen[4].sum() == occ.sum()

    # free voxels: everything an independent (Siddon) traversal crosses before the return
    expected_free = np.zeros(GRID.size, bool)
    o = obs.camera_to_world[:3, 3]
    for p in hits:
        d = (p - o) / np.linalg.norm(p - o)
        vox, _, t_out = traverse(o, d, GRID, 0.0, np.inf)
        t_hit = np.linalg.norm(p - o)
        expected_free[vox[t_out <= t_hit]] = True
    np.testing.assert_array_equal(free.ravel(), expected_free & ~occ.ravel())
    assert np.all(np.nonzero(free)[1] <= 10)  # nothing behind the plane's voxel row
    assert free[:, :10].sum() > 1000  # the space in front of the plane is seen


def test_two_agreeing_views_make_voxels_confident_and_one_view_does_not() -> None:
    model = AnalyticObservationModel()
    b0 = EvidentialMap.empty(GRID)
    b1 = model.update(b0, plane_observation(pose_facing_plane(), PLANE_Y, label=7))
    b2 = model.update(b1, plane_observation(pose_facing_plane(0.012, -0.007), PLANE_Y, label=7))
    assert np.all(b0.alpha == 1.0)
    assert np.all(b0.beta == 1.0)

    twice = (b1.alpha > 1) & (b2.alpha > b1.alpha)  # hit in both views
    assert twice.sum() > 100
    p1, p2 = b1.expected_occupancy(), b2.expected_occupancy()
    np.testing.assert_allclose(p1[b1.alpha > 1], 11 / 12, rtol=1e-6)
    np.testing.assert_allclose(p2[twice], 21 / 22, rtol=1e-6)
    assert np.all(p2[twice] > 0.95)
    assert np.all(p1[b1.alpha > 1] < 0.95)
    np.testing.assert_allclose(b2.vacuity()[twice], NUM_CLASSES / 35, rtol=1e-6)
    np.testing.assert_allclose(b1.vacuity()[b1.alpha > 1], 0.6, rtol=1e-6)
    assert np.all(b2.argmax_class(TAU_CHI)[twice] == 7)
    assert np.all(b1.argmax_class(TAU_CHI)[b1.alpha > 1] == -1)

    free_twice = b2.beta == 21.0
    assert free_twice.sum() > 200
    assert np.all(p2[free_twice] < 0.05)
    assert np.all(b2.argmax_class(TAU_CHI)[free_twice] == 0)  # free space is background


@st.composite
def observations(draw: st.DrawFn) -> Observation:
    seed = draw(st.integers(0, 2**31 - 1))
    rng = np.random.default_rng(seed)
    cam = CameraConfig(width_px=16, height_px=12)
    target = rng.uniform(GRID.origin, GRID.upper_m)
    eye = target + rng.normal(size=3) * 0.3 + np.array([0.0, -0.3, 0.0])
    pose = look_at(eye, target)
    depth = rng.uniform(0.05, 0.9, (12, 16)).astype(np.float32)
    depth[rng.random((12, 16)) < 0.2] = 0.0
    labels = rng.integers(0, NUM_CLASSES, (12, 16)).astype(np.int16)
    return Observation(depth, labels, cam.intrinsics, pose)


@settings(max_examples=15, deadline=None)
@given(st.lists(observations(), min_size=1, max_size=4), st.integers(1, 3))
def test_any_sequence_of_observations_keeps_the_belief_valid(obs_list: list[Observation], stride: int) -> None:
    model = AnalyticObservationModel(pixel_stride=stride)
    b = EvidentialMap.empty(GRID)
    for o in obs_list:
        prev = b
        b = model.update(b, o)
        assert b is not prev
        assert np.all(b.alpha >= prev.alpha)
        assert np.all(b.beta >= prev.beta)
        assert np.all(b.eta >= prev.eta)
    assert np.all(b.alpha >= 1)
    assert np.all(b.beta >= 1)
    assert np.all(b.eta >= 1)
    p = b.expected_occupancy()
    assert np.all((p >= 0) & (p <= 1))
    assert np.all(b.occupancy_entropy() >= 0)
    assert np.all(b.semantic_entropy() >= -1e-9)
    chi = b.vacuity()
    assert np.all((chi > 0) & (chi <= 1))
    assert np.all(b.class_probs().sum(axis=0) == pytest.approx(1.0, abs=1e-5))


def test_a_voxel_an_object_left_flips_to_free_within_two_views_with_contradiction_decay() -> None:
    """The object that made a plane at PLANE_Y moved away (the wall is now 5 cm further back)."""
    pose_a, pose_b = pose_facing_plane(), pose_facing_plane(0.012, -0.007)

    def run(decay: float) -> tuple[np.ndarray, np.ndarray]:
        model = AnalyticObservationModel(contradiction_decay=decay)
        b = EvidentialMap.empty(GRID)
        for pose in (pose_a, pose_b, pose_a, pose_b):  # four agreeing views: well established
            b = model.update(b, plane_observation(pose, PLANE_Y, label=7))
        was_occ = b.expected_occupancy() > 0.95
        for pose in (pose_a, pose_b):  # the object left: two views see through to the back
            b = model.update(b, plane_observation(pose, PLANE_Y + 0.05, label=3))
        return was_occ, b.expected_occupancy()

    was_occ, p = run(0.3)
    cleared = was_occ & (p < 0.5)
    assert cleared.sum() > 0.9 * was_occ.sum()
    was_occ_plain, p_plain = run(1.0)  # pure evidence counting keeps the stale surface
    assert (was_occ_plain & (p_plain < 0.5)).sum() < 0.1 * was_occ_plain.sum()


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), cap=st.floats(2.5, 40.0), margin=st.integers(0, 2))
def test_cap_evidence_shrinks_disturbed_evidence_and_keeps_the_side_of_one_half(seed, cap, margin):
    from msmem_core.msas import cap_evidence

    rng = np.random.default_rng(seed)
    b = EvidentialMap.empty(GRID, NUM_CLASSES)
    b.alpha[:] = 1 + rng.gamma(1.0, 20.0, GRID.shape).astype(np.float32)
    b.beta[:] = 1 + rng.gamma(1.0, 20.0, GRID.shape).astype(np.float32)
    b.eta[:] = 1 + rng.gamma(0.5, 10.0, b.eta.shape).astype(np.float32)
    changed = np.zeros(GRID.shape, bool)
    changed[5:8, 4:6, 3:9] = True
    out = cap_evidence(b, changed, cap, margin)
    region = np.zeros(GRID.shape, bool)
    region[5 - margin:8 + margin, 4 - margin:6 + margin, 3 - margin:9 + margin] = True
    s_in, s_out = (out.alpha + out.beta)[region], (out.alpha + out.beta)[~region]
    assert np.all(s_in <= cap * (1 + 1e-5))  # above the cap: shrunk to it; below: as it was
    np.testing.assert_array_equal(s_out, (b.alpha + b.beta)[~region])  # outside: untouched
    np.testing.assert_array_equal(out.eta[:, ~region], b.eta[:, ~region])
    assert out.alpha.min() >= 1
    assert out.beta.min() >= 1
    assert out.eta.min() >= 1
    p_before, p_after = b.alpha / (b.alpha + b.beta), out.alpha / (out.alpha + out.beta)
    assert np.array_equal(p_before > 0.5, p_after > 0.5)
    np.testing.assert_array_equal(np.argmax(out.eta, axis=0), np.argmax(b.eta, axis=0))
    reset = cap_evidence(b, changed, 2.0, margin)  # cap 2: back to the prior
    assert np.all(reset.alpha[region] == 1)
    assert np.all(reset.beta[region] == 1)
    assert np.all(reset.eta[:, region] == 1)
    np.testing.assert_array_equal(reset.alpha[~region], b.alpha[~region])


def test_a_delta_against_its_base_keeps_exactly_the_voxels_that_change():
    """``BeliefDelta.against``: a voxel stays when any of alpha, beta or one class's evidence differs
    from the base, and only then; applying the result gives the same map as applying the whole delta."""
    from msmem_core.map.belief import BeliefDelta

    base = EvidentialMap.empty(GridSpec(origin_m=(0.0, 0.0, 0.0), voxel_m=0.1, shape=(2, 2, 2)), 4)
    base.alpha[:] = 2.0
    flat = base.alpha.reshape(-1)
    idx = np.array([0, 1, 2, 3, 5], dtype=np.int64)
    alpha = flat[idx].copy()
    beta = base.beta.reshape(-1)[idx].copy()
    eta = base.eta.reshape(4, -1)[:, idx].copy()
    alpha[1] = 3.0  # voxel 1: alpha changes
    beta[2] = 4.0  # voxel 2: beta changes
    eta[3, 3] = 7.0  # voxel 3: only the last class's evidence changes
    delta = BeliefDelta(idx, alpha, beta, eta)  # voxels 0 and 5: unchanged
    kept = delta.against(base)
    np.testing.assert_array_equal(kept.idx, [1, 2, 3])
    np.testing.assert_array_equal(kept.alpha, [3.0, 2.0, 2.0])
    np.testing.assert_array_equal(kept.beta, [1.0, 4.0, 1.0])
    np.testing.assert_array_equal(kept.eta[:, 2], [1.0, 1.0, 1.0, 7.0])
    got, want = kept.apply(base), delta.apply(base)
    np.testing.assert_array_equal(got.alpha, want.alpha)
    np.testing.assert_array_equal(got.beta, want.beta)
    np.testing.assert_array_equal(got.eta, want.eta)


def test_entropies_are_computed_in_float64_whatever_the_input():
    from msmem_core.map.belief import bernoulli_entropy, categorical_entropy

    p = np.array([1e-4, 0.3, 0.5, 1.0], dtype=np.float32)
    h = bernoulli_entropy(p)
    assert h.dtype == np.float64
    want = -(p.astype(np.float64) * np.log(p.astype(np.float64))
             + np.where(p < 1, (1 - p.astype(np.float64)) * np.log(np.maximum(1 - p.astype(np.float64), 1e-300)), 0))
    np.testing.assert_allclose(h, want, rtol=1e-12)
    assert categorical_entropy(np.ones((3, 2), dtype=np.float32)).dtype == np.float64


# ----------------------------------------------------------------------------- memory estimate
def test_memory_estimate_bounds_the_measured_peak():
    """bytes_per_voxel is the traced peak of a belief, its updated copy and the semantic entropy,
    rounded up: within 12 % above it (measured 571 of 616 bytes per voxel)."""
    import tracemalloc

    from msmem_core.map.belief import bytes_per_voxel

    grid = GridSpec(voxel_m=0.01, shape=(40, 40, 20))
    tracemalloc.start()
    try:
        b = EvidentialMap.empty(grid)
        updated = b.copy()  # held, as an update holds the old belief and the new one
        updated.total_semantic_entropy()
        peak = tracemalloc.get_traced_memory()[1] / grid.size
    finally:
        tracemalloc.stop()
    assert 0.88 * bytes_per_voxel(NUM_CLASSES) <= peak <= bytes_per_voxel(NUM_CLASSES)


def test_memory_limit_is_half_the_physical_memory(monkeypatch):
    from pathlib import Path

    import msmem_core.map.belief as belief_mod

    meminfo = Path("/proc/meminfo")
    if meminfo.exists():  # an independent reading of the machine's memory
        total = int(meminfo.read_text().split("MemTotal:")[1].split()[0]) * 1024
        assert abs(belief_mod.memory_limit_bytes() - total / 2) < 0.01 * total

    def no_sysconf(name: str) -> int:
        raise ValueError(name)

    assert isinstance(belief_mod.memory_limit_bytes(), int)
    monkeypatch.setattr(belief_mod.os, "sysconf", no_sysconf)
    assert belief_mod.memory_limit_bytes() == 4 << 30


def test_grid_memory_check_refuses_only_grids_above_the_limit(monkeypatch):
    import msmem_core.map.belief as belief_mod
    from msmem_core.errors import UserError

    grid = GridSpec(voxel_m=0.01, shape=(10, 10, 10))
    need = grid.size * belief_mod.bytes_per_voxel(NUM_CLASSES)
    monkeypatch.setattr(belief_mod, "memory_limit_bytes", lambda: need)
    assert belief_mod.check_grid_memory(grid) is grid  # exactly at the limit: accepted
    monkeypatch.setattr(belief_mod, "memory_limit_bytes", lambda: need - 1)
    with pytest.raises(UserError, match=r"^grid of 10 x 10 x 10 = 1,000 voxels of 10 mm needs about 0\.0 GiB .* "
                                        r"limit of 0\.0 GiB \(half of physical memory\); use a larger grid\.voxel_m"):
        belief_mod.check_grid_memory(grid)
    # the estimate is per class count: a 15-class grid at the limit is refused with 200 classes
    monkeypatch.setattr(belief_mod, "memory_limit_bytes", lambda: need)
    with pytest.raises(UserError, match="needs about"):
        EvidentialMap.empty(grid, num_classes=200)
    assert EvidentialMap.empty(grid).num_classes == NUM_CLASSES
    assert belief_mod._gib(2**30) == "1.0 GiB"
    assert belief_mod._gib(2**40 - 2**20) == "1024.0 GiB"
    assert belief_mod._gib(2**40) == "1.0 TiB"
    assert belief_mod._gib(3 * 2**41) == "6.0 TiB"


def test_expected_distributions_vacuity_and_known_classes_of_hand_computed_voxels():
    grid = GridSpec(voxel_m=0.1, shape=(2, 1, 1))
    b = EvidentialMap(grid, np.array([3.0, 1.0], np.float32).reshape(2, 1, 1),
                      np.array([1.0, 1.0], np.float32).reshape(2, 1, 1),
                      np.array([[1.0, 1.0], [6.0, 1.0], [1.0, 1.0]], np.float32).reshape(3, 2, 1, 1))
    np.testing.assert_allclose(b.expected_occupancy().ravel(), [0.75, 0.5])
    np.testing.assert_allclose(b.class_probs().reshape(3, 2).T, [[1 / 8, 6 / 8, 1 / 8], [1 / 3, 1 / 3, 1 / 3]])
    np.testing.assert_allclose(b.vacuity().ravel(), [3 / 8, 1.0])
    assert b.argmax_class(0.9).ravel().tolist() == [1, -1]  # the prior's class is unknown
    assert b.argmax_class(0.375).ravel().tolist() == [-1, -1]  # vacuity at tau_chi: unknown
    assert b.argmax_class(0.376).ravel().tolist() == [1, -1]
    np.testing.assert_allclose(b.semantic_entropy().ravel(),
                               [scipy.stats.entropy([1, 6, 1]), np.log(3)], rtol=1e-6)


@pytest.mark.parametrize("bad", ["alpha", "beta", "eta"])
def test_evidence_whose_shape_does_not_match_the_grid_is_refused(bad):
    grid = GridSpec(voxel_m=0.1, shape=(2, 3, 4))
    arrays = {"alpha": np.ones((2, 3, 4), np.float32), "beta": np.ones((2, 3, 4), np.float32),
              "eta": np.ones((5, 2, 3, 4), np.float32)}
    arrays[bad] = np.ones((5, 2, 3, 5) if bad == "eta" else (2, 3, 5), np.float32)
    with pytest.raises(ValueError, match=r"do not match grid \(2, 3, 4\)"):
        EvidentialMap(grid, **arrays)


def test_the_ray_record_is_copied_saved_cleared_by_predictions_and_read_as_never_seen(tmp_path):
    from msmem_core.map.belief import BeliefDelta

    grid = GridSpec(origin_m=(0.0, 0.0, 0.0), voxel_m=0.1, shape=(3, 2, 2))
    b = EvidentialMap.empty(grid, 4)
    b.eta[1, 0, 0, 0] = 30.0  # one voxel seen often: low vacuity
    np.testing.assert_array_equal(b.never_seen(0.9), b.vacuity() >= 0.9)  # no record: the vacuity decides
    assert b.never_seen(0.9).sum() == 11
    obs = np.zeros(grid.shape, dtype=bool)
    obs[2, 1, 1] = True
    rec = EvidentialMap(grid, b.alpha, b.beta, b.eta, obs)
    np.testing.assert_array_equal(rec.never_seen(0.9), ~obs)  # with one, the record decides
    c = rec.copy()
    c.observed[0, 0, 0] = True
    assert not rec.observed[0, 0, 0]  # a copy owns its record
    rec.save(tmp_path / "b.npz")
    np.testing.assert_array_equal(EvidentialMap.load(tmp_path / "b.npz").observed, obs)
    b.save(tmp_path / "a.npz")
    assert EvidentialMap.load(tmp_path / "a.npz").observed is None
    flat = np.ravel_multi_index((2, 1, 1), grid.shape)
    d = BeliefDelta(np.array([flat]), np.array([5.0], np.float32), np.array([1.0], np.float32),
                    np.ones((4, 1), np.float32))
    assert not d.apply(rec).observed[2, 1, 1]  # a predicted change is not an observation
    assert rec.observed[2, 1, 1]
    assert d.apply(b).observed is None
    with pytest.raises(ValueError, match="observed"):
        EvidentialMap(grid, b.alpha, b.beta, b.eta, np.zeros((3, 2), dtype=bool))
    with pytest.raises(ValueError, match="observed"):
        EvidentialMap(grid, b.alpha, b.beta, b.eta, np.zeros(grid.shape, dtype=np.uint8))
