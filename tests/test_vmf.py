"""The vMF distribution on S^2: exact against scipy from kappa = 1e-6 to 1e4, sampling in
distribution, finite gradients at kappa -> 0."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from msmem_grasp import vmf
from scipy.stats import kstest, vonmises_fisher

pytestmark = pytest.mark.usefixtures("one_torch_thread")
KAPPAS = np.logspace(-6, 4, 41)
F64 = torch.float64


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def test_normaliser_matches_scipy_from_1e_6_to_1e4():
    mu = np.array([0.0, 0.0, 1.0])
    ours = vmf.log_normaliser(torch.tensor(KAPPAS, dtype=F64)).numpy()
    ref = np.array([vonmises_fisher(mu, k).logpdf([1.0, 0.0, 0.0]) for k in KAPPAS])  # mu.x = 0: log C
    np.testing.assert_allclose(ours, ref, rtol=1e-6)
    np.testing.assert_allclose(np.exp(ours), [vonmises_fisher(mu, k).pdf([1.0, 0.0, 0.0]) for k in KAPPAS], rtol=1e-6)


def test_log_prob_matches_scipy():
    rng = np.random.default_rng(0)
    mu = _unit(rng.normal(size=3))
    x = _unit(rng.normal(size=(50, 3)))
    for k in KAPPAS[::4]:
        ours = vmf.log_prob(torch.tensor(x), torch.tensor(mu), torch.tensor(k, dtype=F64)).numpy()
        np.testing.assert_allclose(ours, vonmises_fisher(mu, k).logpdf(x), rtol=1e-6, atol=1e-9)


def test_normaliser_is_uniform_at_zero_and_continuous_at_the_series_switch():
    assert vmf.log_normaliser(torch.tensor(0.0, dtype=F64)).item() == pytest.approx(-math.log(4 * math.pi), abs=1e-15)
    k = torch.tensor([1e-3 * (1 - 1e-9), 1e-3, 1e-3 * (1 + 1e-9)], dtype=F64)
    v = vmf.log_normaliser(k)
    assert (v[0] - v[2]).abs().item() < 1e-14


def test_float32_agrees_with_float64():
    k = torch.tensor(KAPPAS)
    for f in (vmf.log_normaliser, vmf.mean_resultant):
        np.testing.assert_allclose(f(k.float()).numpy(), f(k.to(F64)).numpy(), rtol=2e-6)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_gradients_are_finite_and_exact_at_tiny_kappa(dtype):
    k = torch.tensor([0.0, 1e-30, 1e-12, 1e-6, 1e-3, 0.5, 50.0, 1e4], dtype=dtype, requires_grad=True)
    vmf.log_normaliser(k).sum().backward()
    assert torch.isfinite(k.grad).all()
    kd = k.detach().to(F64).numpy()
    big = np.maximum(kd, 1e-2)
    # d log C / dk = 1/k - coth k, or its series -k/3 + k^3/45 near 0
    expected = np.where(kd >= 1e-2, 1.0 / big - 1.0 / np.tanh(big), -kd / 3 + kd**3 / 45)
    np.testing.assert_allclose(k.grad.to(F64).numpy(), expected, rtol=1e-5 if dtype == torch.float32 else 1e-10)
    # log_prob's gradient w.r.t. mu and kappa is finite too
    mu = torch.tensor([0.0, 0.6, 0.8], dtype=dtype, requires_grad=True)
    kappa = torch.tensor(1e-9, dtype=dtype, requires_grad=True)
    vmf.log_prob(torch.tensor([1.0, 0.0, 0.0], dtype=dtype), mu, kappa).backward()
    assert torch.isfinite(mu.grad).all()
    assert torch.isfinite(kappa.grad)


def test_autograd_matches_finite_differences_including_second_order():
    k = torch.tensor([1e-4, 5e-3, 0.5, 3.0, 50.0], dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(vmf.log_normaliser, (k,))
    assert torch.autograd.gradgradcheck(vmf.log_normaliser, (k,))


@pytest.mark.parametrize("kappa", [0.0, 1e-6, 0.5, 3.0, 50.0, 1e4])
def test_samples_follow_the_distribution(kappa):
    n = 20_000
    g = torch.Generator().manual_seed(int(kappa * 1000) % 1000 + 1)
    mu = torch.tensor(_unit(np.array([0.3, -0.5, 0.8])))
    k = torch.tensor(kappa, dtype=F64)
    x = vmf.sample(mu, k, n, generator=g)
    assert x.shape == (n, 3)
    torch.testing.assert_close(x.norm(dim=-1), torch.ones(n, dtype=F64))
    w = x @ mu
    a = vmf.mean_resultant(k).item()
    std = w.std().item()
    assert abs(w.mean().item() - a) < 5 * std / math.sqrt(n) + 1e-12  # E[mu.x] = coth k - 1/k
    p = kstest(w.numpy(), lambda t: vmf.cosine_cdf(torch.as_tensor(t), k).numpy()).pvalue
    assert p > 1e-3
    # the tangential part is uniform around mu: the mean vector points along mu
    tangential = (x - w[:, None] * mu).mean(0)
    assert tangential.norm().item() < 5 * math.sqrt(max(1 - a * a, 1e-12) / n) + 1e-12


def test_sampling_broadcasts_and_is_reproducible():
    mu = torch.nn.functional.normalize(torch.randn(4, 3, dtype=F64), dim=-1)
    kappa = torch.tensor([0.0, 1.0, 10.0, 1e8], dtype=F64)
    a = vmf.sample(mu, kappa, 7, generator=torch.Generator().manual_seed(3))
    b = vmf.sample(mu, kappa, 7, generator=torch.Generator().manual_seed(3))
    assert a.shape == (7, 4, 3)
    assert torch.equal(a, b)
    assert torch.isfinite(a).all()
    assert ((a[:, 3] @ mu[3]) > 1 - 1e-6).all()  # kappa = 1e8 sits on mu


def test_mean_resultant_limits():
    k = torch.tensor([0.0, 1e-8, 1e-2, 1.0, 1e3, 1e300], dtype=F64)
    a = vmf.mean_resultant(k).numpy()
    assert a[0] == 0.0
    assert a[1] == pytest.approx(1e-8 / 3, rel=1e-12)
    assert a[3] == pytest.approx(1 / math.tanh(1.0) - 1.0, rel=1e-14)
    assert a[4] == pytest.approx(1 - 1e-3, rel=1e-14)
    assert a[5] == 1.0
