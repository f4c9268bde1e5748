"""The vMF distribution on S^2: exact against scipy from kappa = 1e-6 to 1e4 and against mpmath from 0 to
1e300 (both sides of the series switches), sampling as the exact inverse CDF and in distribution, right-handed
frames for every mu, broadcasting and dtypes, finite gradients at kappa -> 0."""

from __future__ import annotations

import math

import mpmath as mp
import numpy as np
import pytest
import torch
from msmem_grasp import vmf
from scipy.stats import kstest, vonmises_fisher
from torch import Tensor

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


# --- high-precision references (mpmath, 50 digits; mp.workdps leaves mpmath's global precision alone) --

_DPS = 50


def _mp_log_c_exact(k: float | mp.mpf) -> mp.mpf:
    """log C(kappa) = log kappa - log 4pi - log sinh kappa, at the caller's precision."""
    k = mp.mpf(k)
    return mp.log(k) - mp.log(4 * mp.pi) - mp.log(mp.sinh(k))


def _mp_log_c(k: float) -> float:
    """log C(kappa), -log 4pi at kappa = 0."""
    with mp.workdps(_DPS):
        return float(-mp.log(4 * mp.pi) if k == 0 else _mp_log_c_exact(k))


def _mp_a(k: float) -> float:
    """A(kappa) = coth kappa - 1/kappa (with enough digits for the cancellation at tiny kappa)."""
    if k == 0:
        return 0.0
    with mp.workdps(_DPS + 2 * max(0, -math.floor(math.log10(k)))):
        k = mp.mpf(k)
        return float(mp.coth(k) - 1 / k)


def _mp_cdf(w: float, k: float) -> float:
    """F(w) = (e^{kappa (w+1)} - 1) / (e^{2 kappa} - 1) on [-1, 1], (w+1)/2 at kappa = 0."""
    with mp.workdps(_DPS):
        w, k = mp.mpf(w), mp.mpf(k)
        return float((w + 1) / 2 if k == 0 else mp.expm1(k * (w + 1)) / mp.expm1(2 * k))


def _mp_quantile(u: float, k: float) -> float:
    """The w with F(w) = u: w = -1 + log(1 + u (e^{2 kappa} - 1)) / kappa."""
    with mp.workdps(_DPS):
        u, k = mp.mpf(u), mp.mpf(k)
        return float(2 * u - 1 if k == 0 else -1 + mp.log1p(u * mp.expm1(2 * k)) / k)


# --- log C -----------------------------------------------------------------------------------------


def test_normaliser_matches_mpmath_on_both_sides_of_the_series_switch():
    # the series branch (kappa < 1e-3) is good to an ulp of |log C| ~ 2.5, the closed form to a few
    series_k = [0.0, 1e-12, 1e-8, 1e-6, 1e-4, 5e-4, 9e-4, 9.99e-4, 1e-3 * (1 - 1e-12)]
    closed_k = [1e-3, 1e-3 * (1 + 1e-12), 1.001e-3, 2e-3, 1e-2, 0.1, 1.0, 10.0, 100.0, 1e4, 1e6]
    s = vmf.log_normaliser(torch.tensor(series_k, dtype=F64)).numpy()
    np.testing.assert_allclose(s, [_mp_log_c(k) for k in series_k], rtol=0, atol=1e-15)
    c = vmf.log_normaliser(torch.tensor(closed_k, dtype=F64)).numpy()
    np.testing.assert_allclose(c, [_mp_log_c(k) for k in closed_k], rtol=1e-15, atol=2e-15)


def test_normaliser_huge_kappa_and_its_gradient():
    k = torch.tensor([1e8, 1e300], dtype=F64, requires_grad=True)
    v = vmf.log_normaliser(k)
    # log C = log k - k - log 2pi + O(e^{-2k})
    expected = [math.log(1e8) - 1e8 - math.log(2 * math.pi), -1e300]
    np.testing.assert_allclose(v.detach().numpy(), expected, rtol=1e-15)
    v.sum().backward()
    np.testing.assert_allclose(k.grad.numpy(), [1e-8 - 1.0, -1.0], rtol=1e-15)  # 1/k - coth k


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_normaliser_and_mean_resultant_keep_the_float_dtype(dtype):
    k = torch.tensor([0.0, 5e-4, 0.05, 2.0], dtype=dtype)
    for f, ref in ((vmf.log_normaliser, _mp_log_c), (vmf.mean_resultant, _mp_a)):
        out = f(k)
        assert out.dtype == dtype
        assert out.shape == k.shape
        np.testing.assert_allclose(out.to(F64).numpy(), [ref(x) for x in k.tolist()],
                                   rtol=1e-6 if dtype == torch.float32 else 1e-14, atol=1e-12)


def test_integer_and_python_kappa_use_the_default_dtype():
    default = torch.get_default_dtype()
    for kappa in (torch.tensor([0, 1, 3]), [0, 1, 3]):
        c = vmf.log_normaliser(kappa)
        a = vmf.mean_resultant(kappa)
        assert c.dtype == default
        assert a.dtype == default
        np.testing.assert_allclose(c.double().numpy(), [_mp_log_c(k) for k in (0, 1, 3)], rtol=1e-6)
        np.testing.assert_allclose(a.double().numpy(), [_mp_a(k) for k in (0, 1, 3)], rtol=1e-6, atol=1e-12)
    assert vmf.log_normaliser(2.5).item() == pytest.approx(_mp_log_c(2.5), rel=1e-6)
    assert vmf.mean_resultant(2.5).item() == pytest.approx(_mp_a(2.5), rel=1e-6)


# --- log p -----------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_log_prob_broadcasts_over_leading_dimensions(dtype):
    rng = np.random.default_rng(5)
    x = _unit(rng.normal(size=(4, 5, 3)))
    mu = _unit(rng.normal(size=(5, 3)))
    kappa = np.array([0.0, 0.7, 12.0, 300.0])[:, None]  # [4, 1]
    out = vmf.log_prob(torch.tensor(x, dtype=dtype), torch.tensor(mu, dtype=dtype), torch.tensor(kappa, dtype=dtype))
    assert out.shape == (4, 5)
    assert out.dtype == dtype
    ref = np.array([[-math.log(4 * math.pi) if k == 0 else vonmises_fisher(mu[j], k).logpdf(x[i, j])
                     for j, k in enumerate(np.broadcast_to(kappa[i], 5))] for i in range(4)])
    np.testing.assert_allclose(out.to(F64).numpy(), ref, rtol=1e-5 if dtype == torch.float32 else 1e-10,
                               atol=1e-4 if dtype == torch.float32 else 1e-10)


def test_log_prob_is_uniform_at_kappa_zero_and_peaks_at_mu():
    mu = torch.tensor([0.0, -0.6, 0.8], dtype=F64)
    x = torch.tensor([[0.0, -0.6, 0.8], [0.0, 0.6, -0.8], [1.0, 0.0, 0.0]], dtype=F64)
    np.testing.assert_allclose(vmf.log_prob(x, mu, torch.tensor(0.0, dtype=F64)).numpy(), -math.log(4 * math.pi))
    k = 5.0
    lp = vmf.log_prob(x, mu, torch.tensor(k, dtype=F64)).numpy()
    np.testing.assert_allclose(lp, _mp_log_c(k) + k * np.array([1.0, -1.0, 0.0]), rtol=1e-14)


# --- A(kappa) --------------------------------------------------------------------------------------


def test_mean_resultant_float64_matches_mpmath_around_its_switch():
    # series below 1e-2 (accurate to ~1e-16 relative), coth k - 1/k above (cancels ~1e-12 near 1e-2)
    series_k = [1e-300, 1e-12, 1e-6, 1e-4, 1e-3, 5e-3, 9e-3, 9.9e-3, 9.999e-3]
    closed_k = [1e-2, 1.0001e-2, 0.02, 0.05, 0.1, 0.2, 0.29, 0.31, 1.0, 3.0, 30.0, 1e3, 1e8]
    s = vmf.mean_resultant(torch.tensor(series_k, dtype=F64)).numpy()
    np.testing.assert_allclose(s, [_mp_a(k) for k in series_k], rtol=1e-15)
    c = vmf.mean_resultant(torch.tensor(closed_k, dtype=F64)).numpy()
    np.testing.assert_allclose(c, [_mp_a(k) for k in closed_k], rtol=5e-12)


def test_mean_resultant_float32_series_is_accurate_up_to_its_switch_at_0_3():
    k = torch.tensor([1e-3, 0.01, 0.05, 0.1, 0.2, 0.25, 0.29, 0.2999, 0.3, 0.31, 0.5, 1.0])
    a = vmf.mean_resultant(k)
    assert a.dtype == torch.float32
    ref = np.array([_mp_a(x) for x in k.tolist()])  # at the float32 kappa values
    below = (k < 0.3).numpy()
    # the series in float32: within ~2.5 ulp of A(kappa) <= 0.1 (ulp 7.5e-9)
    np.testing.assert_allclose(a.numpy()[below].astype(np.float64), ref[below], rtol=0, atol=2e-8)
    # the closed form above the switch loses ~eps/kappa to cancellation
    np.testing.assert_allclose(a.numpy()[~below].astype(np.float64), ref[~below], rtol=2e-6)


def test_mean_resultant_is_the_derivative_of_log_sinh_k_over_k():
    # A = d/dk log(sinh k / k) = -d log C / dk; central differences of the mpmath log C
    for k in (3e-3, 0.05, 0.7, 4.0):
        with mp.workdps(_DPS):
            h = mp.mpf(k) * mp.mpf("1e-12")
            fd = -(_mp_log_c_exact(k + h) - _mp_log_c_exact(k - h)) / (2 * h)
        assert vmf.mean_resultant(torch.tensor(k, dtype=F64)).item() == pytest.approx(float(fd), rel=1e-10)


# --- orthonormal frame -----------------------------------------------------------------------------


def _frame_mus() -> np.ndarray:
    axes = np.concatenate([np.eye(3), -np.eye(3)])
    a = 0.9
    edge = []
    for s0 in (1.0, -1.0):
        for d in (-1e-9, 0.0, 1e-9, 0.05):
            x = s0 * (a + d)
            rest = math.sqrt(1 - x * x)
            edge += [[x, -rest, 0.0], [x, 0.6 * rest, -0.8 * rest], [x, 0.0, rest]]
    diag = [[1.0, 1.0, 0.0], [1.0, -1.0, 0.0], [-1.0, 1.0, 1.0], [0.0, 1.0, 1.0], [-1.0, -1.0, -1.0]]
    rand = np.random.default_rng(11).normal(size=(11, 3))
    return _unit(np.concatenate([axes, np.array(edge), np.array(diag), rand]))


def _check_frame(mu: Tensor, e1: Tensor, e2: Tensor, tol: float) -> None:
    assert e1.shape == mu.shape
    assert e2.shape == mu.shape
    assert e1.dtype == mu.dtype
    assert e2.dtype == mu.dtype
    m, a, b = (t.to(F64).reshape(-1, 3) for t in (mu, e1, e2))
    one = torch.ones(len(m), dtype=F64)
    zero = torch.zeros(len(m), dtype=F64)
    torch.testing.assert_close(a.norm(dim=-1), one, atol=tol, rtol=0)
    torch.testing.assert_close(b.norm(dim=-1), one, atol=tol, rtol=0)
    torch.testing.assert_close((a * b).sum(-1), zero, atol=tol, rtol=0)
    torch.testing.assert_close((a * m).sum(-1), zero, atol=tol, rtol=0)
    torch.testing.assert_close((b * m).sum(-1), zero, atol=tol, rtol=0)
    # right-handed: e1 x e2 = mu
    torch.testing.assert_close(torch.linalg.cross(a, b, dim=-1), m, atol=tol, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_orthonormal_basis_is_a_right_handed_frame_for_every_direction(dtype):
    mus = torch.tensor(_frame_mus(), dtype=dtype)
    assert len(mus) % 2 == 0
    assert len(mus) != 3
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    _check_frame(mus, *vmf.orthonormal_basis(mus), tol=tol)  # [N, 3]
    batched = mus.reshape(2, -1, 3)  # [2, N/2, 3]
    _check_frame(batched, *vmf.orthonormal_basis(batched), tol=tol)
    col = mus[:, None, :]  # [N, 1, 3]
    _check_frame(col, *vmf.orthonormal_basis(col), tol=tol)
    for mu in mus[[0, 4, 8, 20]]:  # single vectors [3]
        _check_frame(mu, *vmf.orthonormal_basis(mu), tol=tol)


def test_orthonormal_basis_is_computed_per_row():
    # each batch row gets the same frame as alone (no mixing across the batch)
    mus = torch.tensor(_frame_mus(), dtype=F64)
    e1, e2 = vmf.orthonormal_basis(mus.reshape(2, -1, 3))
    for i, mu in enumerate(mus):
        f1, f2 = vmf.orthonormal_basis(mu)
        torch.testing.assert_close(e1.reshape(-1, 3)[i], f1, atol=1e-15, rtol=0)
        torch.testing.assert_close(e2.reshape(-1, 3)[i], f2, atol=1e-15, rtol=0)


# --- sampling --------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sample_is_the_exact_inverse_cdf_of_the_generator_uniforms(dtype):
    """The documented sampler: w = mu.x = F^{-1}(u) for the first uniform draw u (F the CDF of w), the
    tangent part at azimuth 2 pi u' (second draw) in the ``orthonormal_basis`` frame of mu/|mu|."""
    n = 60
    kappas = [0.0, 1e-13, 1e-6, 0.3, 2.0, 40.0, 1e5]
    raw_mu = torch.tensor([[[0.0, 0.0, 2.0]], [[-0.3, 0.5, -0.1]]], dtype=dtype)  # [2, 1, 3], not unit
    kappa = torch.tensor(kappas, dtype=dtype)
    x = vmf.sample(raw_mu, kappa, n, generator=torch.Generator().manual_seed(123))
    assert x.shape == (n, 2, len(kappas), 3)
    assert x.dtype == dtype
    g = torch.Generator().manual_seed(123)
    u = torch.rand((n, 2, len(kappas)), generator=g, dtype=dtype)
    u2 = torch.rand((n, 2, len(kappas)), generator=g, dtype=dtype)
    mu = torch.tensor(_unit(raw_mu.to(F64).numpy()))[:, 0]  # [2, 3]
    x64 = x.to(F64)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(x64.norm(dim=-1), torch.ones(x.shape[:-1], dtype=F64), atol=tol, rtol=0)
    w = torch.einsum("nbkc,bc->nbk", x64, mu)
    w_ref = torch.tensor([[[_mp_quantile(u[i, b, j].item(), k) for j, k in enumerate(kappas)]
                           for b in range(2)] for i in range(n)], dtype=F64)
    torch.testing.assert_close(w, w_ref, atol=tol, rtol=0)
    e1, e2 = vmf.orthonormal_basis(mu)
    phi = 2 * math.pi * u2.to(F64)
    r = torch.sqrt((1 - w_ref) * (1 + w_ref))
    e1, e2 = e1[None, :, None], e2[None, :, None]
    tangent = r[..., None] * (torch.cos(phi)[..., None] * e1 + torch.sin(phi)[..., None] * e2)
    torch.testing.assert_close(x64 - w[..., None] * mu[None, :, None], tangent, atol=10 * tol, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_sample_maps_a_zero_uniform_draw_to_the_antipode(dtype, monkeypatch):
    """torch.rand can return exactly 0 (p = 2^-24 per float32 draw). u = 0 is F^{-1}(0) = -1: the sample is
    -mu, finite and of unit norm for every kappa, also where e^{-2 kappa} underflows."""
    real_rand = torch.rand
    calls = []

    def rand_with_a_zero(*args, **kwargs):
        out = real_rand(*args, **kwargs)
        out[0] = 0.0  # the first sample's uniforms (both draws, so the order of the draws does not matter)
        calls.append(out.shape)
        return out

    monkeypatch.setattr(torch, "rand", rand_with_a_zero)
    mu = torch.tensor([0.0, 0.6, -0.8], dtype=dtype)
    huge = 1e300 if dtype == F64 else 1e30
    kappa = torch.tensor([0.0, 1e-13, 0.5, 5.0, 100.0, 1e5, huge], dtype=dtype)
    x = vmf.sample(mu, kappa, 8, generator=torch.Generator().manual_seed(2))
    monkeypatch.undo()
    assert calls == [(8, 7), (8, 7)]
    assert torch.isfinite(x).all()
    tol = 1e-6 if dtype == torch.float32 else 1e-14
    torch.testing.assert_close(x.norm(dim=-1), torch.ones(8, 7, dtype=dtype), atol=tol, rtol=0)
    # w = -1 up to rounding (F^{-1} is ill-conditioned at u = 0: ~eps e^{2 kappa} / kappa for moderate
    # kappa), the tangent part is sqrt(1 - w^2) ~ sqrt(2 (1 + w))
    tol_w = 1e-3 if dtype == torch.float32 else 1e-11
    torch.testing.assert_close(x[0] @ mu, -torch.ones(7, dtype=dtype), atol=tol_w, rtol=0)
    torch.testing.assert_close(x[0], -mu.expand(7, 3), atol=2 * math.sqrt(tol_w), rtol=0)


def test_sample_is_exact_for_huge_kappa():
    mu = torch.tensor([[0.0, -1.0, 0.0], [0.6, 0.0, -0.8]], dtype=F64)
    x = vmf.sample(mu, torch.tensor(1e300, dtype=F64), 50, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(x, mu.expand(50, 2, 3), atol=1e-15, rtol=0)
    # 1 - w ~ Exp(kappa) for large kappa: E[1 - w] = 1 - A(kappa) = 1/kappa
    k = 1e6
    n = 20_000
    x = vmf.sample(mu[1], torch.tensor(k, dtype=F64), n, generator=torch.Generator().manual_seed(1))
    d = (1 - x @ mu[1]).numpy() * k
    assert abs(d.mean() - 1.0) < 5 / math.sqrt(n)
    assert kstest(d, "expon").pvalue > 1e-3


def test_sample_broadcasts_mu_and_kappa():
    g = torch.Generator().manual_seed(4)
    mu = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 0.6, 0.8], [-0.8, 0.6, 0.0]], dtype=F64)
    x = vmf.sample(mu, torch.tensor(5.0, dtype=F64), 4000, generator=g)  # [4, 3] mu, scalar kappa
    assert x.shape == (4000, 4, 3)
    w = (x * mu).sum(-1)
    np.testing.assert_allclose(w.mean(0).numpy(), _mp_a(5.0), atol=5 * 0.25 / math.sqrt(4000))
    kappas = torch.tensor([0.0, 1.0, 30.0], dtype=F64)
    x = vmf.sample(mu[2], kappas, 4000, generator=g)  # [3] mu, [3] kappa: batch (3,)
    assert x.shape == (4000, 3, 3)
    w = x @ mu[2]
    np.testing.assert_allclose(w.mean(0).numpy(), [_mp_a(k) for k in kappas.tolist()], atol=5 * 0.6 / math.sqrt(4000))
    x = vmf.sample(mu[3], 2.0, 5, generator=g)  # python float kappa, unbatched
    assert x.shape == (5, 3)


def test_sample_kappa_takes_the_dtype_of_mu():
    mu64 = torch.tensor([0.0, 0.6, 0.8], dtype=F64)
    a = vmf.sample(mu64, 0.1, 100, generator=torch.Generator().manual_seed(9))
    b = vmf.sample(mu64, torch.tensor(0.1, dtype=F64), 100, generator=torch.Generator().manual_seed(9))
    assert a.dtype == F64
    assert torch.equal(a, b)
    mu32 = mu64.float()
    c = vmf.sample(mu32, torch.tensor(0.7, dtype=F64), 100, generator=torch.Generator().manual_seed(9))
    d = vmf.sample(mu32, torch.tensor(0.7, dtype=torch.float32), 100, generator=torch.Generator().manual_seed(9))
    assert c.dtype == torch.float32
    assert torch.equal(c, d)


def test_sample_azimuth_is_uniform_about_mu():
    mu = torch.tensor(_unit(np.array([0.95, -0.2, 0.1])), dtype=F64)  # |mu_x| > 0.9: the other helper axis
    n = 20_000
    x = vmf.sample(mu, torch.tensor(3.0, dtype=F64), n, generator=torch.Generator().manual_seed(21))
    # azimuth in an independent frame around mu
    a = _unit(np.cross(mu.numpy(), [0.0, 0.0, 1.0]))
    b = np.cross(mu.numpy(), a)
    az = np.arctan2(x.numpy() @ b, x.numpy() @ a)
    assert kstest(az, "uniform", args=(-math.pi, 2 * math.pi)).pvalue > 1e-3


# --- CDF of w --------------------------------------------------------------------------------------


def test_cosine_cdf_matches_the_closed_form():
    w = np.linspace(-1.0, 1.0, 41)
    for k in (1e-13, 1e-9, 1e-4, 0.3, 1.0, 7.5, 80.0, 700.0, 5000.0):
        ours = vmf.cosine_cdf(torch.tensor(w, dtype=F64), torch.tensor(k, dtype=F64)).numpy()
        ref = np.array([_mp_cdf(t, k) for t in w])
        np.testing.assert_allclose(ours, ref, rtol=1e-11, atol=1e-300)
    # kappa = 0: uniform w; kappa -> inf: a step at w = 1
    np.testing.assert_allclose(vmf.cosine_cdf(torch.tensor(w), torch.tensor(0.0)).numpy(), (w + 1) / 2, atol=1e-7)
    step = vmf.cosine_cdf(torch.tensor(w, dtype=F64), torch.tensor(1e300, dtype=F64)).numpy()
    np.testing.assert_array_equal(step, (w == 1.0).astype(float))


def test_cosine_cdf_is_zero_below_and_one_above_the_support():
    w = torch.tensor([-3.0, -1.5, -1.0, 1.0, 1.5, 3.0], dtype=F64)
    for k in (0.0, 1e-13, 1e-3, 1.0, 10.0):
        np.testing.assert_array_equal(vmf.cosine_cdf(w, torch.tensor(k, dtype=F64)).numpy(), [0, 0, 0, 1, 1, 1])


def test_cosine_cdf_broadcasts_and_keeps_dtype():
    w = torch.linspace(-1, 1, 9, dtype=torch.float32)[:, None]
    kappa = torch.tensor([0.0, 0.5, 20.0], dtype=F64)
    out = vmf.cosine_cdf(w, kappa)
    assert out.shape == (9, 3)
    assert out.dtype == torch.float32
    ref = np.array([[_mp_cdf(t, k) for k in kappa.tolist()] for t in w[:, 0].tolist()])
    np.testing.assert_allclose(out.numpy(), ref, rtol=1e-5, atol=1e-7)
    # a python float kappa is taken at w's precision
    w64 = torch.linspace(-1, 1, 9, dtype=F64)
    a = vmf.cosine_cdf(w64, 0.1)
    assert a.dtype == F64
    np.testing.assert_allclose(a.numpy(), [_mp_cdf(t, 0.1) for t in w64.tolist()], rtol=1e-14, atol=1e-16)


@pytest.mark.parametrize("kappa", [1e-4, 0.3, 2.0, 20.0])
def test_cdf_mean_is_the_mean_resultant(kappa):
    # E[w] = 1 - int_{-1}^{1} F(w) dw = A(kappa)
    t, wt = np.polynomial.legendre.leggauss(200)
    f = vmf.cosine_cdf(torch.tensor(t, dtype=F64), torch.tensor(kappa, dtype=F64)).numpy()
    assert 1.0 - (wt * f).sum() == pytest.approx(vmf.mean_resultant(torch.tensor(kappa, dtype=F64)).item(), rel=1e-9)
