"""The FE-vMF loss (paper eq. fevmf_loss): evidential Beta terms against scipy, the vMF NLL, and
why averaging over the GT grasps of a contact lets kappa express several feasible directions."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from msmem_grasp.fevmf import FEVMF, FEVMFConfig
from msmem_grasp.learn.losses import (
    GraspTargets,
    LossConfig,
    assign_targets,
    beta_expected_ce,
    beta_kl_uniform,
    evidential_beta_loss,
    total_loss,
    vmf_nll,
)
from scipy import integrate, stats

pytestmark = pytest.mark.usefixtures("one_torch_thread")
F64 = torch.float64
PARAMS = [(1.0, 1.0), (1.0, 7.5), (3.2, 1.4), (20.0, 2.0), (0.6, 0.9), (150.0, 40.0)]


def _t(*v: float) -> torch.Tensor:
    return torch.tensor(v, dtype=F64)


@pytest.mark.parametrize(("a", "b"), PARAMS)
def test_beta_kl_to_uniform_matches_numeric_integration(a, b):
    ours = beta_kl_uniform(_t(a), _t(b)).item()
    # KL(p || U(0, 1)) = int p log p = -(differential entropy)
    assert ours == pytest.approx(-stats.beta(a, b).entropy(), rel=1e-9, abs=1e-12)
    quad, _ = integrate.quad(lambda q: stats.beta.pdf(q, a, b) * stats.beta.logpdf(q, a, b), 0, 1, limit=200)
    assert ours == pytest.approx(quad, rel=1e-6, abs=1e-8)


@pytest.mark.parametrize(("a", "b"), PARAMS)
def test_digamma_cross_entropy_matches_monte_carlo(a, b):
    q = stats.beta(a, b).rvs(size=400_000, random_state=np.random.default_rng(0))
    q = np.clip(q, 1e-300, 1 - 1e-16)
    for y in (0.0, 1.0):
        samples = -(y * np.log(q) + (1 - y) * np.log1p(-q))
        mc, se = samples.mean(), samples.std() / math.sqrt(len(q))
        ours = beta_expected_ce(_t(a), _t(b), _t(y)).item()
        assert abs(ours - mc) < 5 * se + 1e-9


def test_kl_removes_the_correct_evidence_and_keeps_the_misleading_one():
    alpha = _t(5.0, 5.0).requires_grad_()
    beta = _t(3.0, 3.0).requires_grad_()
    y = _t(1.0, 0.0)
    _ce, kl = evidential_beta_loss(alpha, beta, y, kl_weight=1.0)
    kl.sum().backward()
    assert alpha.grad[0] == 0
    assert beta.grad[0] > 0
    assert beta.grad[1] == 0
    assert alpha.grad[1] > 0
    assert kl[0].item() == pytest.approx(beta_kl_uniform(_t(1.0), _t(3.0)).item())
    _ce, kl0 = evidential_beta_loss(_t(1.0), _t(1.0), _t(1.0), kl_weight=1.0)
    assert kl0.item() == pytest.approx(0.0, abs=1e-12)  # no evidence, no penalty


def test_vmf_nll_decreases_as_mu_turns_towards_the_target():
    target = _t(0.0, 0.0, 1.0)[None, None]
    mask = torch.ones(1, 1, dtype=torch.bool)
    angles = torch.linspace(math.pi, 0.0, 30, dtype=F64)
    mus = torch.stack([torch.sin(angles), torch.zeros_like(angles), torch.cos(angles)], 1)
    for kappa in (0.1, 5.0, 200.0):
        nll = torch.stack([vmf_nll(mu[None], _t(kappa), target, mask)[0] for mu in mus])
        assert (nll[1:] < nll[:-1]).all()


def test_averaging_over_gt_grasps_lets_low_kappa_express_several_directions():
    # two feasible approach directions at one contact, 90 degrees apart
    t = torch.stack([_t(1.0, 0.0, 0.0), _t(0.0, 1.0, 0.0)])[None]
    mask = torch.ones(1, 2, dtype=torch.bool)
    midway = torch.nn.functional.normalize(_t(1.0, 1.0, 0.0), dim=0)[None]
    pick_one = _t(1.0, 0.0, 0.0)[None]
    hedge = vmf_nll(midway, _t(2.5), t, mask).item()
    confident = vmf_nll(pick_one, _t(200.0), t, mask).item()
    assert hedge < confident
    # and the best kappa midway is moderate: A(kappa*) = cos 45 deg
    kappas = torch.logspace(-2, 3, 400, dtype=F64)
    best = kappas[torch.argmin(torch.stack([vmf_nll(midway, k, t, mask)[0] for k in kappas]))].item()
    assert 2.0 < best < 5.0
    # padding entries are ignored
    t_pad = torch.cat([t, torch.ones(1, 1, 3, dtype=F64)], 1)
    mask_pad = torch.tensor([[True, True, False]])
    assert vmf_nll(midway, _t(2.5), t_pad, mask_pad).item() == pytest.approx(hedge)


def _targets(n: int, pos: list[int]) -> GraspTargets:
    g = 3
    a = torch.zeros(len(pos), g, 3, dtype=F64)
    a[..., 2] = -1.0
    b = torch.zeros(len(pos), g, 3, dtype=F64)
    b[..., 0] = 1.0
    mask = torch.zeros(len(pos), g, dtype=torch.bool)
    mask[:, 0] = True
    mask[0, :2] = True
    return GraspTargets(n, torch.tensor(pos), a, b, torch.full((len(pos), g), 0.04, dtype=F64), mask)


def test_total_loss_trains_fevmf_end_to_end():
    torch.manual_seed(0)
    model = FEVMF(FEVMFConfig(dim=16, layers=2, heads=2, patch_size=32, head_hidden=16)).to(F64)
    pts = torch.rand(200, 3, dtype=F64) * 0.2
    targets = _targets(200, [3, 50, 120])
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    first = None
    for step in range(40):
        terms = total_loss(model(pts), targets, epoch=step)
        opt.zero_grad()
        terms["total"].backward()
        assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
        opt.step()
        first = first if first is not None else {k: v.item() for k, v in terms.items()}
    assert set(terms) == {"approach", "baseline", "affordance_ce", "affordance_kl", "width", "total"}
    for key in ("approach", "baseline", "affordance_ce", "width"):
        assert terms[key].item() < first[key]
    assert first["affordance_kl"] == 0.0  # epoch 0: KL annealed out


def test_kl_weight_is_annealed():
    torch.manual_seed(0)
    model = FEVMF(FEVMFConfig(dim=16, layers=1, heads=2, patch_size=32, head_hidden=16)).to(F64)
    out = model(torch.rand(50, 3, dtype=F64))
    targets = _targets(50, [1])
    cfg = LossConfig(anneal_epochs=4)
    kl = [total_loss(out, targets, e, cfg)["affordance_kl"].item() for e in (0, 1, 2, 4, 8)]
    assert kl[0] == 0.0
    assert kl[2] == pytest.approx(2 * kl[1])
    assert kl[3] == pytest.approx(4 * kl[1])
    assert kl[4] == pytest.approx(kl[3])


def test_no_positives_gives_zero_orientation_terms_with_a_graph():
    model = FEVMF(FEVMFConfig(dim=16, layers=1, heads=2, patch_size=32, head_hidden=16)).to(F64)
    out = model(torch.rand(40, 3, dtype=F64))
    none = torch.zeros(0, 1, 3, dtype=F64)
    empty = GraspTargets(40, torch.zeros(0, dtype=torch.long), none, none, none[..., 0], none[..., 0].bool())
    terms = total_loss(out, empty, epoch=3)
    assert terms["approach"].item() == 0.0
    assert terms["width"].item() == 0.0
    terms["total"].backward()


def test_assign_targets_labels_points_near_gt_contacts():
    points = _t(0.0, 0.0, 0.0, 0.0, 0.0, 0.003, 0.1, 0.0, 0.0).view(3, 3)
    contacts = _t(0.0, 0.0, 0.0015, 0.0, 0.0, -0.0015, 0.5, 0.5, 0.5).view(3, 3)
    approach = torch.eye(3, dtype=F64)
    baseline = torch.eye(3, dtype=F64)[[1, 2, 0]]
    width = _t(0.01, 0.02, 0.03)
    t = assign_targets(points, contacts, approach, baseline, width, radius_m=0.002, max_grasps=4)
    assert t.positive_index.tolist() == [0, 1]
    assert t.mask.tolist() == [[True, True, False, False], [True, False, False, False]]
    torch.testing.assert_close(t.width[0, :2].sort().values, _t(0.01, 0.02))
    torch.testing.assert_close(t.approach[1, 0], approach[0])
    assert t.label.tolist() == [1.0, 1.0, 0.0]


# ---------------------------------------------------------------- precision at large evidence
def test_beta_kl_uniform_is_minus_the_differential_entropy_in_float32_too():
    from msmem_grasp.learn.losses import beta_kl_uniform
    from scipy import stats

    for a, b in ((3.0, 5.0), (40.0, 2.0), (1e4, 3e4)):
        kl = beta_kl_uniform(torch.tensor([a], dtype=torch.float32), torch.tensor([b], dtype=torch.float32))
        assert float(kl[0]) == pytest.approx(-stats.beta(a, b).entropy(), rel=1e-5, abs=1e-5)
    # Beta(1e8, 1e8) is a normal with variance 1 / (4 (2a + 1)): KL = -0.5 log(2 pi e var) = 8.83
    a = torch.tensor([1e8], dtype=torch.float32)
    var = 1.0 / (4.0 * (2e8 + 1.0))
    assert float(beta_kl_uniform(a, a)[0]) == pytest.approx(-0.5 * math.log(2 * math.pi * math.e * var), rel=1e-4)
    x = torch.tensor([1e6], dtype=torch.float32, requires_grad=True)
    beta_kl_uniform(x, torch.tensor([3e6])).sum().backward()
    assert x.grad is not None
    assert float(x.grad[0]) != 0.0


def test_expected_angle_matches_a_high_precision_reference_at_every_concentration():
    import mpmath as mp
    from msmem_grasp.metrics import ASYMPTOTIC_KAPPA, expected_angle_deg

    mp.mp.dps = 30

    def reference(kappa: float) -> float:
        k = mp.mpf(kappa)
        f = lambda w: mp.acos(w) * k * mp.e ** (k * (w - 1)) / (1 - mp.e ** (-2 * k))  # noqa: E731
        cuts = sorted({-1.0, 1.0, *(float(1 - c / k) for c in (30.0, 3.0, 0.3) if c / k < 2)})
        return float(mp.degrees(mp.quad(f, cuts)))

    for kappa in (0.05, 1.0, 10.0, 1e3, 1e4, 1e6):
        assert expected_angle_deg(kappa) == pytest.approx(reference(kappa), rel=1e-5), kappa
    assert expected_angle_deg(1e4) == pytest.approx(0.718, abs=1e-3)  # was 0.0003 before the fix
    above = expected_angle_deg(ASYMPTOTIC_KAPPA * 10)
    assert above == pytest.approx(reference(ASYMPTOTIC_KAPPA * 10), rel=1e-5)
    with pytest.raises(ValueError, match="kappa"):
        expected_angle_deg(0.0)
