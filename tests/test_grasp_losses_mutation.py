"""Mutation-driven checks of the FE-vMF loss (plugins/msmem_grasp/learn/losses.py) against independent
references: scipy's von Mises-Fisher and Beta distributions, hand-computed widths and a brute-force
nearest-contact search for the target assignment."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from msmem_grasp.fevmf import GraspPrediction
from msmem_grasp.learn.losses import (
    LossConfig,
    assign_targets,
    beta_kl_uniform,
    evidential_beta_loss,
    total_loss,
    vmf_nll,
)
from scipy import special, stats

pytestmark = pytest.mark.usefixtures("one_torch_thread")
F64 = torch.float64


def _vmf_mean_nll(mu: np.ndarray, kappa: float, targets: np.ndarray) -> float:
    return float(-np.mean(stats.vonmises_fisher(mu, kappa).logpdf(targets)))


def _unit(*v: float) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    return a / np.linalg.norm(a)


def test_vmf_nll_is_the_per_point_mean_over_its_own_valid_targets():
    # two points with 1 and 3 valid targets of 4 (padding filled with junk)
    t = np.zeros((2, 4, 3))
    t[0, 0] = _unit(0.0, 0.0, 1.0)
    t[0, 1:] = _unit(1.0, 0.0, 0.0)  # padding
    t[1, :3] = [_unit(1.0, 0.0, 0.0), _unit(0.0, 1.0, 0.0), _unit(1.0, 1.0, 1.0)]
    t[1, 3] = _unit(0.0, 0.0, -1.0)  # padding
    mask = torch.tensor([[True, False, False, False], [True, True, True, False]])
    mu = np.stack([_unit(0.3, 0.1, 1.0), _unit(1.0, 0.8, 0.2)])
    kappa = np.array([4.0, 2.5])
    ours = vmf_nll(torch.tensor(mu), torch.tensor(kappa), torch.tensor(t), mask)
    assert ours.shape == (2,)
    ref = [_vmf_mean_nll(mu[0], kappa[0], t[0, :1]), _vmf_mean_nll(mu[1], kappa[1], t[1, :3])]
    np.testing.assert_allclose(ours.numpy(), ref, rtol=1e-10)


def test_beta_kl_uniform_returns_the_input_dtype():
    for dtype in (torch.float32, torch.float64):
        kl = beta_kl_uniform(torch.tensor([3.0], dtype=dtype), torch.tensor([5.0], dtype=dtype))
        assert kl.dtype == dtype
        assert float(kl[0]) == pytest.approx(-stats.beta(3.0, 5.0).entropy(), rel=1e-5)


def test_evidential_kl_keeps_only_the_misleading_parameter():
    alpha = torch.tensor([5.0, 5.0, 0.4], dtype=F64)
    beta = torch.tensor([3.0, 3.0, 2.5], dtype=F64)
    y = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    ce, kl = evidential_beta_loss(alpha, beta, y, kl_weight=0.5)
    # y = 1: Beta(1, beta); y = 0: Beta(alpha, 1); KL to U(0, 1) = -differential entropy
    ref_kl = [-stats.beta(1.0, 3.0).entropy(), -stats.beta(5.0, 1.0).entropy(), -stats.beta(0.4, 1.0).entropy()]
    np.testing.assert_allclose(kl.numpy(), 0.5 * np.asarray(ref_kl), rtol=1e-9)
    s = alpha.numpy() + beta.numpy()
    ref_ce = np.where(
        y.numpy() == 1.0,
        special.digamma(s) - special.digamma(alpha.numpy()),
        special.digamma(s) - special.digamma(beta.numpy()),
    )
    np.testing.assert_allclose(ce.numpy(), ref_ce, rtol=1e-12)


def _prediction(n: int) -> GraspPrediction:
    rng = np.random.default_rng(3)
    mu_a = rng.normal(size=(n, 3))
    mu_b = rng.normal(size=(n, 3))
    return GraspPrediction(
        mu_a_hat=torch.tensor(mu_a / np.linalg.norm(mu_a, axis=1, keepdims=True)),
        kappa_a_hat=torch.tensor(rng.uniform(0.5, 20.0, n)),
        mu_b=torch.tensor(mu_b / np.linalg.norm(mu_b, axis=1, keepdims=True)),
        kappa_b=torch.tensor(rng.uniform(0.5, 20.0, n)),
        alpha=torch.tensor(rng.uniform(0.5, 8.0, n)),
        beta=torch.tensor(rng.uniform(0.5, 8.0, n)),
        width=torch.tensor(rng.uniform(0.0, 0.08, n)),
    )


def test_total_loss_terms_and_weighted_sum_match_hand_computed_values():
    n, pos = 6, [1, 4]
    out = _prediction(n)
    rng = np.random.default_rng(5)
    a = rng.normal(size=(2, 3, 3))
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    b = rng.normal(size=(2, 3, 3))
    b /= np.linalg.norm(b, axis=-1, keepdims=True)
    w = np.array([[0.01, 0.07, 0.03], [0.05, 0.02, 0.06]])
    mask = np.array([[True, False, False], [True, True, True]])
    from msmem_grasp.learn.losses import GraspTargets

    batch = GraspTargets(n, torch.tensor(pos), torch.tensor(a), torch.tensor(b), torch.tensor(w), torch.tensor(mask))
    cfg = LossConfig(w_approach=0.7, w_baseline=1.3, w_affordance=2.1, w_width=0.4, anneal_epochs=4.0, max_width_m=0.1)
    terms = total_loss(out, batch, epoch=3.0, config=cfg)

    ref_a = np.mean(
        [_vmf_mean_nll(out.mu_a_hat[p].numpy(), float(out.kappa_a_hat[p]), a[i][mask[i]]) for i, p in enumerate(pos)]
    )
    ref_b = np.mean(
        [_vmf_mean_nll(out.mu_b[p].numpy(), float(out.kappa_b[p]), b[i][mask[i]]) for i, p in enumerate(pos)]
    )
    wp = out.width.numpy()
    ref_w = np.mean([np.mean(np.abs(wp[p] - w[i][mask[i]])) / 0.1 for i, p in enumerate(pos)])
    al, be = out.alpha.numpy(), out.beta.numpy()
    y = np.zeros(n)
    y[pos] = 1.0
    ds = special.digamma(al + be)
    ref_ce = np.mean(np.where(y == 1, ds - special.digamma(al), ds - special.digamma(be)))
    kl = [-stats.beta(1.0, be[i]).entropy() if y[i] else -stats.beta(al[i], 1.0).entropy() for i in range(n)]
    ref_kl = 0.75 * np.mean(kl)
    assert terms["approach"].item() == pytest.approx(ref_a, rel=1e-9)
    assert terms["baseline"].item() == pytest.approx(ref_b, rel=1e-9)
    assert terms["width"].item() == pytest.approx(ref_w, rel=1e-9)
    assert terms["affordance_ce"].item() == pytest.approx(ref_ce, rel=1e-9)
    assert terms["affordance_kl"].item() == pytest.approx(ref_kl, rel=1e-9)
    ref_total = 0.7 * ref_a + 1.3 * ref_b + 2.1 * (ref_ce + ref_kl) + 0.4 * ref_w
    assert terms["total"].item() == pytest.approx(ref_total, rel=1e-9)


def _brute_force(points: np.ndarray, contacts: np.ndarray, radius: float, max_grasps: int):
    d = np.linalg.norm(points[:, None] - contacts[None], axis=-1)
    pos, lists = [], []
    for i, row in enumerate(d):
        near = [j for j in np.argsort(row) if row[j] < radius][:max_grasps]
        if near:
            pos.append(i)
            lists.append(near)
    return pos, lists


@pytest.mark.parametrize("max_grasps", [None, 2])
def test_assign_targets_matches_a_brute_force_search(max_grasps):
    rng = np.random.default_rng(11)
    contacts = rng.uniform(0.0, 0.006, (5, 3))
    points = rng.uniform(-0.001, 0.007, (300, 3))
    points[0] = contacts[-1] + 1e-4  # next to the last contact only
    points[1] = [0.5, 0.5, 0.5]  # far beyond 2 mm (but within 1 m) of every contact
    approach = torch.tensor(rng.normal(size=(5, 3)), dtype=torch.float32)
    baseline = torch.tensor(rng.normal(size=(5, 3)), dtype=torch.float32)
    width = torch.tensor(rng.uniform(0.0, 0.08, 5), dtype=torch.float32)
    kw = {} if max_grasps is None else {"max_grasps": max_grasps}
    g = 32 if max_grasps is None else max_grasps
    t = assign_targets(torch.tensor(points), torch.tensor(contacts), approach, baseline, width, **kw)
    pos, lists = _brute_force(points, contacts, 0.002, g)  # the default radius is 2 mm
    assert 0 in pos
    assert 1 not in pos
    assert any(len(x) > 1 for x in lists)
    assert t.num_points == 300
    assert t.positive_index.tolist() == pos
    assert t.mask.shape == (len(pos), g)
    assert t.mask.dtype == torch.bool
    assert t.approach.shape == t.baseline.shape == (len(pos), g, 3)
    assert t.width.shape == (len(pos), g)
    for x in (t.approach, t.baseline, t.width):
        assert x.dtype == F64  # gathered in the points' dtype
    for r, near in enumerate(lists):
        k = len(near)
        assert t.mask[r].tolist() == [True] * k + [False] * (g - k)
        np.testing.assert_array_equal(t.approach[r, :k].numpy(), approach[near].double().numpy())
        np.testing.assert_array_equal(t.baseline[r, :k].numpy(), baseline[near].double().numpy())
        np.testing.assert_array_equal(t.width[r, :k].numpy(), width[near].double().numpy())


@pytest.mark.parametrize(("n_points", "n_contacts"), [(1, 1), (1, 3), (3, 1)])
def test_assign_targets_with_a_single_point_or_contact(n_points, n_contacts):
    contacts = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=F64)[:n_contacts]
    points = torch.tensor([[0.0, 0.0, 0.001], [0.3, 0.0, 0.0], [0.0, 0.0, 0.5]], dtype=F64)[:n_points]
    eye = torch.eye(3, dtype=F64)[:n_contacts]
    t = assign_targets(points, contacts, eye, eye, torch.full((n_contacts,), 0.05, dtype=F64), max_grasps=4)
    assert t.positive_index.tolist() == [0]
    assert t.mask.tolist() == [[True, False, False, False]]
    assert t.approach[0, 0].tolist() == [1.0, 0.0, 0.0]


@pytest.mark.parametrize(("n_points", "n_contacts"), [(3, 0), (0, 2), (0, 0)])
def test_assign_targets_with_no_points_or_no_contacts(n_points, n_contacts):
    points = torch.rand(n_points, 3, dtype=F64)
    contacts = torch.rand(n_contacts, 3, dtype=F64)
    vec = torch.rand(n_contacts, 3, dtype=F64)
    t = assign_targets(points, contacts, vec, vec, torch.rand(n_contacts, dtype=F64), max_grasps=5)
    assert t.num_points == n_points
    assert t.positive_index.shape == (0,)
    assert t.positive_index.dtype == torch.long
    for x in (t.approach, t.baseline):
        assert x.shape == (0, 5, 3)
        assert x.dtype == F64
    assert t.approach is not t.baseline
    assert t.width.shape == (0, 5)
    assert t.width.dtype == F64
    assert t.mask.shape == (0, 5)
    assert t.mask.dtype == torch.bool
    assert t.label.tolist() == [0.0] * n_points
    # the default number of grasp slots is 32
    assert assign_targets(points, contacts, vec, vec, torch.rand(n_contacts, dtype=F64)).mask.shape == (0, 32)
