"""FE-UMGF fusion (plugins/msmem_grasp/fusion.py): checks added from mutation testing (docs/explanation/reliability.md,
"Mutation testing of the math"). References are hand-computed values or brute-force loops."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
from msmem_grasp.fevmf import GraspPrediction
from msmem_grasp.fusion import FusionConfig, GraspBuffer, GraspHypotheses, project_approach_np

from msmem_core.map.belief import EvidentialMap
from msmem_core.world.grid import GridSpec

FIELDS = ("contact", "mu_a_hat", "kappa_a_hat", "mu_b", "kappa_b", "alpha", "beta", "width")


def one(contact: tuple[float, float, float], b: tuple[float, float, float] = (1.0, 0.0, 0.0), *,
        a_hat: tuple[float, float, float] = (0.0, 0.0, 1.0), kappa_a_hat: float = 5.0, kappa_b: float = 5.0,
        alpha: float = 2.0, beta: float = 2.0, width: float = 0.04) -> GraspHypotheses:
    """A single grasp; b and a_hat are normalised."""
    bv, av = np.array([b], float), np.array([a_hat], float)
    return GraspHypotheses(np.array([contact], float), av / np.linalg.norm(av), np.array([kappa_a_hat]),
                           bv / np.linalg.norm(bv), np.array([kappa_b]), np.array([alpha]), np.array([beta]),
                           np.array([width]))


def test_the_projected_approach_scales_the_given_kappa() -> None:
    theta = np.deg2rad(30.0)  # a_hat 30 deg from b = z: |P_b a_hat| = sin 30 deg = 0.5
    a_hat = np.array([[np.sin(theta), 0.0, np.cos(theta)]])
    b = np.array([[0.0, 0.0, 1.0]])
    a, kappa = project_approach_np(a_hat, b, np.array([4.0]))
    np.testing.assert_allclose(a, [[1.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(kappa, [2.0])
    _, kappa_unit = project_approach_np(a_hat, b)  # no kappa given: kappa_a_hat = 1
    np.testing.assert_allclose(kappa_unit, [0.5])
    g = GraspHypotheses(np.zeros((1, 3)), a_hat, np.array([4.0]), b, np.ones(1), np.ones(1), np.ones(1), np.ones(1))
    a2, kappa2 = g.approach()
    np.testing.assert_allclose(a2, [[1.0, 0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(kappa2, [2.0])


def test_an_approach_parallel_to_b_falls_back_to_a_unit_orthogonal_direction_for_every_b() -> None:
    s = np.sqrt(0.5)
    b = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [s, s, 0.0], [s, 0.0, s],
                  [0.0, s, s], [0.9, np.sqrt(0.19), 0.0], [0.95, 0.0, -np.sqrt(1 - 0.95**2)]])
    a, kappa = project_approach_np(b.copy(), b, np.full(len(b), 3.0))
    np.testing.assert_allclose(np.linalg.norm(a, axis=1), 1.0)
    np.testing.assert_allclose(np.einsum("nk,nk->n", a, b), 0.0, atol=1e-12)
    np.testing.assert_allclose(kappa, 0.0, atol=1e-12)


def test_predictions_keep_every_field_of_the_fe_vmf_output() -> None:
    n = 3
    mu = torch.nn.functional.normalize(torch.arange(1.0, 10.0).reshape(n, 3), dim=-1)
    pred = GraspPrediction(mu_a_hat=mu, kappa_a_hat=torch.tensor([2.0, 3.0, 4.0]), mu_b=torch.roll(mu, 1, 0),
                           kappa_b=torch.tensor([5.0, 6.0, 7.0]), alpha=torch.tensor([1.5, 2.5, 3.5]),
                           beta=torch.tensor([1.0, 2.0, 8.0]), width=torch.tensor([0.02, 0.03, 0.05]))
    g = GraspHypotheses.from_prediction(np.arange(9.0).reshape(n, 3), pred)
    for name in FIELDS[1:]:
        value = getattr(g, name)
        assert value.dtype == np.float64, name
        np.testing.assert_allclose(value, getattr(pred, name).double().numpy(), err_msg=name)
    np.testing.assert_array_equal(g.contact, np.arange(9.0).reshape(n, 3))


def test_poses_have_the_frame_b_a_cross_b_a_centred_between_the_fingers() -> None:
    g = one((0.1, 0.2, 0.3), b=(1.0, 0.0, 0.0), a_hat=(0.0, 0.0, 1.0), width=0.04)
    pose = g.poses()[0]
    expected = np.array([[1.0, 0.0, 0.0, 0.12], [0.0, 1.0, 0.0, 0.2], [0.0, 0.0, 1.0, 0.3], [0.0, 0.0, 0.0, 1.0]])
    np.testing.assert_allclose(pose, expected, atol=1e-12)


def test_empty_hypotheses_have_no_rows_in_any_field() -> None:
    for g in (GraspHypotheses.empty(), GraspHypotheses.concat([])):
        assert len(g) == 0
        assert g.contact.shape == g.mu_a_hat.shape == g.mu_b.shape == (0, 3)
        for name in ("kappa_a_hat", "kappa_b", "alpha", "beta", "width"):
            assert getattr(g, name).shape == (0,), name


def test_hits_are_integer_counts_and_steps_count_updates() -> None:
    buf = GraspBuffer()
    assert buf.steps == 0
    assert buf.hits.dtype == np.int64
    g = one((0.05, 0.05, 0.05))
    for step in (1, 2, 3):
        buf.update(g)
        assert buf.steps == step
        assert buf.hits.dtype == np.int64
    np.testing.assert_array_equal(buf.hits, [3])
    buf.clear()
    assert (buf.steps, len(buf), buf.hits.dtype) == (0, 0, np.int64)


def test_the_fused_width_is_the_evidence_weighted_mean_after_decay() -> None:
    buf = GraspBuffer(FusionConfig(decay=0.5))
    buf.update(one((0.05, 0.05, 0.05), alpha=3.0, beta=1.0, width=0.04))  # S = 4
    buf.update(one((0.052, 0.05, 0.05), alpha=1.0, beta=5.0, width=0.08))  # S = 6, joins it
    # (0.5 * 4 * 0.04 + 6 * 0.08) / (0.5 * 4 + 6) = 0.56 / 8
    np.testing.assert_allclose(buf.width, [0.07])
    np.testing.assert_allclose(buf.hypotheses().width, [0.07])
    np.testing.assert_allclose(buf.alpha, [2.5])
    np.testing.assert_allclose(buf.beta, [5.5])


def test_a_weak_unmatched_grasp_keeps_its_width() -> None:
    buf = GraspBuffer(FusionConfig(decay=0.1))
    weak = one((0.05, 0.05, 0.05), alpha=1.0, beta=1.0, width=0.04)
    other = one((0.15, 0.05, 0.05), width=0.06)
    buf.update(GraspHypotheses.concat([weak, other]))
    buf.update(other)  # the weak one decays to S = 0.2 while another cluster fuses
    np.testing.assert_allclose(buf.alpha + buf.beta, [0.2, 0.4 + 4.0])
    np.testing.assert_allclose(buf.width, [0.04, 0.06])
    np.testing.assert_allclose(buf.hypotheses().width, [0.04, 0.06])


def test_a_buffered_grasp_with_a_small_baseline_concentration_still_matches() -> None:
    buf = GraspBuffer(FusionConfig(decay=0.5))
    g = one((0.05, 0.05, 0.05), b=(1.0, 2.0, 2.0), kappa_b=0.5)  # |eta_b| = 0.5, then 0.25 after decay
    buf.update(g)
    stats = buf.update(g)
    assert (stats.matched, stats.added, stats.size) == (1, 0, 1)
    np.testing.assert_allclose(np.linalg.norm(buf.eta_b, axis=1), [0.75])


def test_a_grasp_from_the_other_contact_needs_its_baseline_within_the_angle() -> None:
    c, w = np.array([0.05, 0.05, 0.05]), 0.05
    for deg, matched in ((45.0, 0), (100.0, 0), (15.0, 1)):  # cos(b, b'') = cos(180 deg - deg)
        t = np.deg2rad(deg)
        u = np.array([np.cos(t), np.sin(t), 0.0])  # b rotated by deg about z
        # named from its other contact: b' = -u, contact c + w u, so c' + w b' = c exactly
        buf = GraspBuffer(FusionConfig(decay=1.0))
        buf.update(one(tuple(c), b=(1.0, 0.0, 0.0), width=w))
        stats = buf.update(one(tuple(c + w * u), b=tuple(-u), width=w))
        assert (stats.matched, stats.flipped) == (matched, matched), deg


def test_baselines_must_agree_strictly_above_min_abs_cos() -> None:
    y = np.sqrt(1 - 0.86**2)
    for bx, by, matched in ((0.86, y, 0), (0.8601, y, 1)):  # cos(b, b') = 0.86 exactly is not "above" 0.86
        buf = GraspBuffer(FusionConfig(decay=1.0, min_abs_cos=0.86))
        buf.update(one((0.05, 0.05, 0.05), b=(1.0, 0.0, 0.0), kappa_b=2.0))
        new = one((0.05, 0.05, 0.05), b=(1.0, 0.0, 0.0))
        new = GraspHypotheses(new.contact, new.mu_a_hat, new.kappa_a_hat, np.array([[bx, by, 0.0]]),
                              new.kappa_b, new.alpha, new.beta, new.width)  # not renormalised: the dot is bx
        assert buf.update(new).matched == matched, bx


def test_confirming_keeps_the_first_buffered_grasp_when_it_is_seen_again() -> None:
    g = GraspHypotheses.concat([one((0.03 + 0.03 * i, 0.05, 0.05)) for i in range(3)])
    buf = GraspBuffer(FusionConfig(decay=1.0))
    buf.update(g)
    stats = buf.update(g.subset(np.array([0])), confirm=True)
    assert (stats.dropped_unconfirmed, len(buf)) == (2, 1)
    np.testing.assert_allclose(buf.contact, g.contact[:1])
    np.testing.assert_array_equal(buf.hits, [2])


def test_update_stats_count_new_matched_flipped_added_and_drops() -> None:
    g = GraspHypotheses.concat([one((0.03 + 0.03 * i, 0.05, 0.05), width=0.05) for i in range(3)])
    buf = GraspBuffer(FusionConfig(decay=1.0))
    stats = buf.update(g)
    assert (stats.new, stats.matched, stats.flipped, stats.added, stats.dropped_stale, stats.dropped_capacity,
            stats.size, stats.dropped_unconfirmed) == (3, 0, 0, 3, 0, 0, 3, 0)
    direct = g.subset(np.array([0]))
    flipped = GraspHypotheses(g.opposite[1:2], g.mu_a_hat[1:2], g.kappa_a_hat[1:2], -g.mu_b[1:2], g.kappa_b[1:2],
                              g.alpha[1:2], g.beta[1:2], g.width[1:2])
    far = one((0.5, 0.5, 0.5))
    stats = buf.update(GraspHypotheses.concat([direct, flipped, far]))
    assert (stats.new, stats.matched, stats.flipped, stats.added, stats.dropped_stale, stats.dropped_capacity,
            stats.size) == (3, 2, 1, 1, 0, 0, 4)


GRID = GridSpec(origin_m=(0.0, 0.0, 0.0), voxel_m=0.01, shape=(7, 8, 9))


def test_an_empty_buffer_is_on_no_surface() -> None:
    belief = EvidentialMap.empty(GRID)
    buf = GraspBuffer()
    keep = buf.on_surface(belief)
    assert keep.shape == (0,)
    assert keep.dtype == np.bool_
    stats = buf.update(GraspHypotheses.empty(), belief)
    assert (stats.dropped_stale, stats.size) == (0, 0)


@pytest.mark.parametrize("radius", [0, 1, 2])
def test_on_surface_matches_a_brute_force_search_of_the_voxel_neighbourhood(radius: int) -> None:
    rng = np.random.default_rng(radius)
    belief = EvidentialMap.empty(GRID)
    belief.beta[:] = 21.0  # believed free everywhere, the grid's border included ...
    occupied = rng.integers(0, GRID.shape, size=(4, 3))  # ... but four occupied voxels
    for i, j, k in occupied:
        belief.alpha[i, j, k], belief.beta[i, j, k] = 21.0, 1.0
    p = belief.expected_occupancy()
    # every voxel of the grid and one layer around it, at its centre
    ijk = np.array(list(itertools.product(*(range(-1, n + 1) for n in GRID.shape))))
    contacts = (ijk + 0.5) * GRID.voxel_m
    buf = GraspBuffer(FusionConfig(surface_radius_voxels=radius))
    buf.contact = contacts
    buf.alpha = np.ones(len(contacts))
    expected = np.zeros(len(contacts), dtype=bool)
    for n, idx in enumerate(ijk):
        if np.all(idx >= 0) and np.all(idx < GRID.shape):
            expected[n] = any(p[tuple(v)] > 0.5 for v in occupied if np.max(np.abs(v - idx)) <= radius)
    got = buf.on_surface(belief)
    assert 0 < expected.sum() < len(expected)
    np.testing.assert_array_equal(got, expected)


def test_state_is_a_copy_of_every_buffer_array() -> None:
    buf = GraspBuffer(FusionConfig(decay=1.0))
    buf.update(GraspHypotheses.concat([one((0.05, 0.05, 0.05)), one((0.15, 0.05, 0.05), width=0.06)]))
    state = buf.state()
    assert set(state) == {"contact", "eta_a", "eta_b", "alpha", "beta", "width", "hits"}
    for name, value in state.items():
        np.testing.assert_array_equal(value, getattr(buf, name), err_msg=name)
        assert value is not getattr(buf, name)
    np.testing.assert_allclose(state["eta_b"], [[5.0, 0.0, 0.0]] * 2)
    np.testing.assert_array_equal(state["hits"], [1, 1])


def test_capacity_keeps_the_older_grasp_among_equal_evidence() -> None:
    n, cap = 60, 25
    s = np.array([2.0, 4.0, 6.0])[np.arange(n) * 7 % 3]  # many ties
    g = GraspHypotheses(np.c_[np.arange(n) * 0.05, np.zeros((n, 2))], np.tile([0.0, 0.0, 1.0], (n, 1)), np.ones(n),
                        np.tile([1.0, 0.0, 0.0], (n, 1)), np.ones(n), s / 2, s / 2, np.full(n, 0.04))
    buf = GraspBuffer(FusionConfig(max_grasps=cap))
    stats = buf.update(g)
    kept = sorted(sorted(range(n), key=lambda i: -s[i])[:cap])  # Python's sort is stable: the earlier wins a tie
    assert (stats.dropped_capacity, stats.size) == (n - cap, cap)
    np.testing.assert_allclose(buf.contact, g.contact[kept])
