"""FE-UMGF: the global grasp buffer fuses evidence and orientation across steps and forgets stale grasps."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from msmem_grasp.fevmf import GraspPrediction
from msmem_grasp.fusion import FusionConfig, GraspBuffer, GraspHypotheses, project_approach_np

from msmem_core.map.belief import EvidentialMap
from msmem_core.world.grid import GridSpec

pytestmark = pytest.mark.usefixtures("one_torch_thread")
GRID = GridSpec(origin_m=(0.0, 0.0, 0.0), voxel_m=0.01, shape=(20, 20, 20))


def grasps(n: int = 5, seed: int = 0, width: float = 0.04) -> GraspHypotheses:
    rng = np.random.default_rng(seed)
    contact = rng.uniform(0.03, 0.15, (n, 3))
    contact[:, 0] = 0.03 + 0.03 * np.arange(n)  # contacts 3 cm apart: no two match each other
    b = rng.normal(size=(n, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    a = rng.normal(size=(n, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return GraspHypotheses(contact, a, rng.uniform(1, 20, n), b, rng.uniform(1, 20, n), rng.uniform(1, 5, n),
                           rng.uniform(1, 5, n), np.full(n, width))


def test_two_identical_predictions_double_the_evidence_and_keep_the_mean() -> None:
    g = grasps()
    buf = GraspBuffer(FusionConfig(decay=1.0))
    buf.update(g)
    buf.update(g)
    fused = buf.hypotheses()
    assert len(fused) == len(g)
    np.testing.assert_allclose(fused.alpha, 2 * g.alpha)
    np.testing.assert_allclose(fused.beta, 2 * g.beta)
    np.testing.assert_allclose(fused.affordance, g.affordance)
    np.testing.assert_allclose(fused.mu_b, g.mu_b, atol=1e-12)
    np.testing.assert_allclose(fused.mu_a_hat, g.mu_a_hat, atol=1e-12)
    np.testing.assert_allclose(fused.kappa_b, 2 * g.kappa_b)  # fused kappa grows
    np.testing.assert_allclose(fused.kappa_a_hat, 2 * g.kappa_a_hat)
    np.testing.assert_allclose(fused.contact, g.contact)
    np.testing.assert_array_equal(buf.hits, 2)


def test_a_confirming_update_keeps_only_the_buffered_grasps_a_new_grasp_matches() -> None:
    g = grasps(5)
    buf = GraspBuffer(FusionConfig(decay=1.0))
    buf.update(g)
    seen_again = g.subset(np.array([1, 3]))  # the post-manipulation view finds two of the five
    stats = buf.update(seen_again, confirm=True)
    assert stats.dropped_unconfirmed == 3
    assert len(buf) == 2
    np.testing.assert_allclose(buf.contact, g.contact[[1, 3]])
    np.testing.assert_allclose(buf.alpha, 2 * g.alpha[[1, 3]])  # confirmed ones fuse as usual
    np.testing.assert_array_equal(buf.hits, 2)
    # a new grasp elsewhere is added; without confirm nothing is dropped
    elsewhere = grasps(1, seed=9)
    elsewhere = GraspHypotheses(elsewhere.contact + 1.0, *[getattr(elsewhere, f) for f in
                                ("mu_a_hat", "kappa_a_hat", "mu_b", "kappa_b", "alpha", "beta", "width")])
    stats = buf.update(elsewhere)
    assert (stats.dropped_unconfirmed, len(buf)) == (0, 3)


def test_decay_is_applied_once_per_step() -> None:
    g = grasps()
    gamma = 0.9
    buf = GraspBuffer(FusionConfig(decay=gamma))
    buf.update(g)
    buf.update(g)  # gamma * old + new
    np.testing.assert_allclose(buf.alpha, gamma * g.alpha + g.alpha)
    buf.update(GraspHypotheses.empty())
    buf.update(GraspHypotheses.empty())
    np.testing.assert_allclose(buf.alpha, gamma**2 * (gamma * g.alpha + g.alpha))
    np.testing.assert_allclose(buf.beta, gamma**2 * (gamma * g.beta + g.beta))
    fused = buf.hypotheses()
    np.testing.assert_allclose(fused.kappa_b, gamma**2 * (gamma + 1) * g.kappa_b)
    np.testing.assert_allclose(fused.affordance, g.affordance)  # decay alone changes no mean
    np.testing.assert_allclose(fused.mu_b, g.mu_b, atol=1e-12)


def test_fusing_different_directions_gives_the_kappa_weighted_mean_and_kappa_of_the_sum() -> None:
    g = grasps(1)
    rot = np.array([[np.cos(0.3), -np.sin(0.3), 0], [np.sin(0.3), np.cos(0.3), 0], [0, 0, 1]])
    h = GraspHypotheses(g.contact + 0.004, g.mu_a_hat, g.kappa_a_hat * 2, g.mu_b @ rot.T, g.kappa_b * 3,
                        g.alpha, g.beta, g.width)
    assert float(np.dot(g.mu_b[0], h.mu_b[0])) > 0.86
    buf = GraspBuffer(FusionConfig(decay=1.0))
    buf.update(g)
    buf.update(h)
    fused = buf.hypotheses()
    eta = g.kappa_b[0] * g.mu_b[0] + h.kappa_b[0] * h.mu_b[0]
    np.testing.assert_allclose(fused.kappa_b, [np.linalg.norm(eta)])
    np.testing.assert_allclose(fused.mu_b[0], eta / np.linalg.norm(eta))
    assert fused.kappa_b[0] > max(g.kappa_b[0], h.kappa_b[0])
    np.testing.assert_allclose(fused.contact, g.contact)  # the cluster keeps its centre


def test_the_same_grasp_named_from_its_other_contact_is_flipped_and_fused() -> None:
    g = grasps(3, width=0.05)
    other = GraspHypotheses(g.opposite, g.mu_a_hat, g.kappa_a_hat, -g.mu_b, g.kappa_b, g.alpha, g.beta, g.width)
    assert np.all(np.linalg.norm(other.contact - g.contact, axis=1) > 0.04)  # too far for a direct match
    buf = GraspBuffer(FusionConfig(decay=1.0))
    buf.update(g)
    stats = buf.update(other)
    assert (stats.matched, stats.flipped, stats.added) == (3, 3, 0)
    fused = buf.hypotheses()
    assert len(fused) == 3
    np.testing.assert_allclose(fused.contact, g.contact)  # contact swapped back to the cluster's
    np.testing.assert_allclose(fused.mu_b, g.mu_b, atol=1e-12)  # b flipped before summing
    np.testing.assert_allclose(fused.kappa_b, 2 * g.kappa_b)
    np.testing.assert_allclose(fused.alpha, 2 * g.alpha)
    np.testing.assert_allclose(fused.mu_a_hat, g.mu_a_hat, atol=1e-12)  # the approach is not flipped


def test_opposite_baseline_at_the_same_contact_or_a_far_contact_does_not_match() -> None:
    g = grasps(2)
    reversed_here = GraspHypotheses(g.contact, g.mu_a_hat, g.kappa_a_hat, -g.mu_b, g.kappa_b, g.alpha, g.beta,
                                    g.width)
    far = GraspHypotheses(g.contact + 0.011 * np.array([0.0, 0.0, 1.0]), g.mu_a_hat, g.kappa_a_hat, g.mu_b,
                          g.kappa_b, g.alpha, g.beta, g.width)
    u = np.cross(g.mu_b, [0.0, 0.0, 1.0])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    turned = GraspHypotheses(g.contact, g.mu_a_hat, g.kappa_a_hat, np.cos(0.6) * g.mu_b + np.sin(0.6) * u,
                             g.kappa_b, g.alpha, g.beta, g.width)  # 34 deg apart: |cos| = 0.825 < 0.86
    for other in (reversed_here, far, turned):
        b = GraspBuffer(FusionConfig(decay=1.0))
        b.update(g)
        stats = b.update(other)
        assert (stats.matched, stats.added, stats.size) == (0, 2, 4)


def test_each_new_grasp_joins_only_its_nearest_cluster_and_all_of_them_are_summed() -> None:
    g = grasps(1)
    buf = GraspBuffer(FusionConfig(decay=1.0))
    buf.update(g)
    near = GraspHypotheses.concat([GraspHypotheses(g.contact + d, g.mu_a_hat, g.kappa_a_hat, g.mu_b, g.kappa_b,
                                                   g.alpha, g.beta, g.width) for d in (0.002, -0.003, 0.005)])
    stats = buf.update(near)
    assert (stats.matched, stats.added) == (3, 0)
    np.testing.assert_allclose(buf.alpha, 4 * g.alpha)
    np.testing.assert_array_equal(buf.hits, [4])


def test_grasps_whose_contact_left_the_believed_surface_are_dropped() -> None:
    belief = EvidentialMap.empty(GRID)
    belief.beta[:] = 21.0  # known free everywhere ...
    belief.alpha[5:8, 5:8, 5:8] = 21.0  # ... but a confident block
    belief.beta[5:8, 5:8, 5:8] = 1.0
    on = np.array([[0.055, 0.055, 0.055], [0.085, 0.06, 0.06]])  # inside the block / one voxel beside it
    off = np.array([[0.15, 0.15, 0.15], [0.5, 0.5, 0.5]])  # in free space / outside the grid
    g = grasps(4)
    g = GraspHypotheses(np.concatenate([on, off]), g.mu_a_hat, g.kappa_a_hat, g.mu_b, g.kappa_b, g.alpha, g.beta,
                        g.width)
    buf = GraspBuffer()
    stats = buf.update(g, belief)
    assert stats.dropped_stale == 2
    np.testing.assert_allclose(buf.contact, on)
    belief.alpha[5:8, 5:8, 5:8] = 1.0
    belief.beta[5:8, 5:8, 5:8] = 1.0  # the block was grasped: back to the prior (p = 0.5), not a surface
    stats = buf.update(GraspHypotheses.empty(), belief)
    assert (stats.dropped_stale, stats.size) == (2, 0)
    buf.update(g, EvidentialMap.empty(GRID))  # nothing believed occupied anywhere: nothing stays
    assert len(buf) == 0


def test_capacity_keeps_the_grasps_with_most_evidence() -> None:
    g = grasps(5)
    buf = GraspBuffer(FusionConfig(max_grasps=3, decay=1.0))
    stats = buf.update(g)
    assert (stats.dropped_capacity, stats.size) == (2, 3)
    s = g.alpha + g.beta
    np.testing.assert_allclose(np.sort(buf.alpha + buf.beta), np.sort(s)[-3:])


def test_predictions_from_fe_vmf_outputs_and_the_projected_approach() -> None:
    n = 4
    torch.manual_seed(0)
    mu = torch.nn.functional.normalize(torch.randn(n, 3), dim=-1)
    pred = GraspPrediction(mu_a_hat=mu, kappa_a_hat=torch.ones(n), mu_b=torch.roll(mu, 1, 0), kappa_b=torch.ones(n),
                           alpha=torch.full((n,), 3.0), beta=torch.ones(n), width=torch.full((n,), 0.03))
    g = GraspHypotheses.from_prediction(np.zeros((n, 3), np.float32), pred)
    assert g.contact.dtype == np.float64
    np.testing.assert_allclose(g.affordance, 0.75)
    np.testing.assert_allclose(g.uncertainty, 0.5)
    a, kappa = g.approach()
    np.testing.assert_allclose(np.einsum("nk,nk->n", a, g.mu_b), 0.0, atol=1e-12)
    ta, tk = pred.approach()
    np.testing.assert_allclose(a, ta.double().numpy(), atol=1e-6)
    np.testing.assert_allclose(kappa, tk.double().numpy(), atol=1e-6)
    poses = g.poses()
    np.testing.assert_allclose(poses[:, :3, 3], 0.015 * g.mu_b)
    a2, k2 = project_approach_np(g.mu_b.copy(), g.mu_b)  # a_hat parallel to b: any orthogonal direction
    np.testing.assert_allclose(np.einsum("nk,nk->n", a2, g.mu_b), 0.0, atol=1e-12)
    np.testing.assert_allclose(k2, 0.0, atol=1e-12)


@pytest.mark.parametrize("seed", [0, 1])
def test_fusing_a_noisy_stream_matches_a_brute_force_loop(seed: int) -> None:
    rng = np.random.default_rng(seed)
    base = grasps(30, seed=seed)
    buf = GraspBuffer(FusionConfig(decay=0.95))
    ref: list[dict[str, np.ndarray]] = []
    for _step in range(4):
        jitter = rng.normal(0, 0.003, base.contact.shape)
        flip = rng.random(len(base)) < 0.3
        c = np.where(flip[:, None], base.opposite, base.contact) + jitter
        b = np.where(flip[:, None], -base.mu_b, base.mu_b)
        new = GraspHypotheses(c, base.mu_a_hat, base.kappa_a_hat, b, base.kappa_b, base.alpha, base.beta, base.width)
        buf.update(new)
        # brute force: same rules, one grasp at a time against the pre-step buffer
        for r in ref:
            for k in ("alpha", "beta", "eta_a", "eta_b"):
                r[k] = 0.95 * r[k]
        pre = [dict(r) for r in ref]
        for i in range(len(new)):
            best, which, sign = np.inf, -1, 1.0
            for j, r in enumerate(pre):
                mu = r["eta_b"] / np.linalg.norm(r["eta_b"])
                cos = float(mu @ new.mu_b[i])
                for pt, sg in ((new.contact[i], 1.0), (new.opposite[i], -1.0)):
                    d = float(np.linalg.norm(pt - r["contact"]))
                    if d <= 0.01 and sg * cos > 0.86 and d < best:
                        best, which, sign = d, j, sg
            if which < 0:
                ref.append({"contact": new.contact[i], "alpha": new.alpha[i], "beta": new.beta[i],
                            "eta_a": new.kappa_a_hat[i] * new.mu_a_hat[i], "eta_b": new.kappa_b[i] * new.mu_b[i]})
            else:
                r = ref[which]
                r["alpha"] = r["alpha"] + new.alpha[i]
                r["beta"] = r["beta"] + new.beta[i]
                r["eta_a"] = r["eta_a"] + new.kappa_a_hat[i] * new.mu_a_hat[i]
                r["eta_b"] = r["eta_b"] + sign * new.kappa_b[i] * new.mu_b[i]
    assert len(buf) == len(ref)
    np.testing.assert_allclose(buf.alpha, [r["alpha"] for r in ref])
    np.testing.assert_allclose(buf.eta_b, [r["eta_b"] for r in ref], atol=1e-9)
    np.testing.assert_allclose(buf.eta_a, [r["eta_a"] for r in ref], atol=1e-9)
