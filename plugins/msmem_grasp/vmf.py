"""The von Mises-Fisher distribution on the unit sphere S^2 (paper: Hierarchical Bayesian Grasp
Representation, p(b | mu, kappa) = C(kappa) exp(kappa mu^T b) with C(kappa) = kappa / (4 pi sinh kappa)).

All functions are differentiable torch code, finite (with finite gradients) from kappa = 0 up to
kappa ~ 1e300 in float64, and broadcast over leading dimensions.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

_LOG_2PI = math.log(2.0 * math.pi)
_LOG_4PI = math.log(4.0 * math.pi)
_SERIES_KAPPA = 1e-3
"""Below this concentration log C uses its Taylor series (C -> 1/(4 pi) at kappa = 0)."""


def _series_kappa_a(dtype: torch.dtype) -> float:
    """Below this concentration A(kappa) uses its series: coth k - 1/k cancels ~eps/k^2 relatively."""
    return 1e-2 if dtype == torch.float64 else 0.3


def _log_normaliser_value(kappa: Tensor) -> Tensor:
    small = kappa < _SERIES_KAPPA
    k_big = torch.where(small, torch.full_like(kappa, _SERIES_KAPPA), kappa)
    big = torch.log(k_big) - k_big - torch.log(-torch.expm1(-2.0 * k_big)) - _LOG_2PI
    k2 = torch.where(small, kappa, torch.zeros_like(kappa)) ** 2
    series = -_LOG_4PI - k2 / 6.0 + k2 * k2 / 180.0
    return torch.where(small, series, big)


class _LogNormaliser(torch.autograd.Function):
    """log C with the analytic derivative d log C / d kappa = 1/kappa - coth kappa = -A(kappa).

    Autograd through the closed form would subtract two ~1/kappa terms (20 % error in float32 at
    kappa = 1e-3); A(kappa) is evaluated by its series there instead.
    """

    @staticmethod
    def forward(ctx: torch.autograd.function.FunctionCtx, kappa: Tensor) -> Tensor:
        ctx.save_for_backward(kappa)
        return _log_normaliser_value(kappa)

    @staticmethod
    def backward(ctx: torch.autograd.function.FunctionCtx, grad: Tensor) -> Tensor:
        (kappa,) = ctx.saved_tensors  # type: ignore[attr-defined]
        return -grad * mean_resultant(kappa)


def log_normaliser(kappa: Tensor) -> Tensor:
    """log C(kappa) = log kappa - log 4pi - log sinh kappa, evaluated stably.

    With sinh kappa = e^kappa (1 - e^{-2 kappa}) / 2:
    log C = log kappa - kappa - log(-expm1(-2 kappa)) - log 2pi   (kappa >= 1e-3),
    log C = -log 4pi - kappa^2/6 + kappa^4/180                    (series, kappa < 1e-3).
    Its derivative is -A(kappa) (see ``mean_resultant``), finite at kappa = 0.
    """
    kappa = torch.as_tensor(kappa)
    if not kappa.is_floating_point():
        kappa = kappa.to(torch.get_default_dtype())
    out: Tensor = _LogNormaliser.apply(kappa)
    return out


def log_prob(x: Tensor, mu: Tensor, kappa: Tensor) -> Tensor:
    """log p(x | mu, kappa) = log C(kappa) + kappa mu.x for unit vectors x, mu [..., 3]."""
    return log_normaliser(kappa) + kappa * (mu * x).sum(-1)


def mean_resultant(kappa: Tensor) -> Tensor:
    """A(kappa) = E[mu.x] = coth(kappa) - 1/kappa, with coth k = 1 + 2 / expm1(2k).

    Near 0 the Bernoulli series kappa/3 - kappa^3/45 + 2 kappa^5/945 - kappa^7/4725 + 2 kappa^9/93555.
    """
    kappa = torch.as_tensor(kappa)
    if not kappa.is_floating_point():
        kappa = kappa.to(torch.get_default_dtype())
    thr = _series_kappa_a(kappa.dtype)
    small = kappa < thr
    k_big = torch.where(small, torch.full_like(kappa, thr), kappa)
    big = 1.0 + 2.0 / torch.expm1(2.0 * k_big) - 1.0 / k_big
    k = torch.where(small, kappa, torch.zeros_like(kappa))
    k2 = k * k
    series = k * (1.0 / 3.0 + k2 * (-1.0 / 45.0 + k2 * (2.0 / 945.0 + k2 * (-1.0 / 4725.0 + k2 * 2.0 / 93555.0))))
    return torch.where(small, series, big)


def orthonormal_basis(mu: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors e1, e2 [..., 3] with (e1, e2, mu) a right-handed orthonormal frame."""
    helper = torch.zeros_like(mu)
    use_x = mu[..., 0].abs() < 0.9
    helper[..., 0] = use_x.to(mu.dtype)
    helper[..., 1] = (~use_x).to(mu.dtype)
    e1 = torch.nn.functional.normalize(torch.linalg.cross(helper, mu, dim=-1), dim=-1)
    e2 = torch.linalg.cross(mu, e1, dim=-1)
    return e1, e2


def sample(mu: Tensor, kappa: Tensor, n: int, generator: torch.Generator | None = None) -> Tensor:
    """n samples [n, *batch, 3] of vMF(mu, kappa) by the exact inverse CDF of w = mu.x on S^2.

    F(w) = (e^{kappa w} - e^{-kappa}) / (e^{kappa} - e^{-kappa})  =>  with v = 1 - u in (0, 1]:
    1 - w = -log1p(v expm1(-2 kappa)) / kappa, which is exact for tiny kappa (w -> 2u - 1) and huge
    kappa (1 - w = -log(u) / kappa); the tangent part is uniform on the circle around mu.
    """
    mu = torch.nn.functional.normalize(torch.as_tensor(mu), dim=-1)
    kappa = torch.as_tensor(kappa, dtype=mu.dtype, device=mu.device)
    batch = torch.broadcast_shapes(mu.shape[:-1], kappa.shape)
    mu = mu.expand(*batch, 3)
    kappa = kappa.expand(batch)
    shape = (n, *batch)
    v = 1.0 - torch.rand(shape, generator=generator, dtype=mu.dtype, device=mu.device)  # (0, 1]
    phi = (2.0 * math.pi) * torch.rand(shape, generator=generator, dtype=mu.dtype, device=mu.device)
    tiny = kappa < 1e-12
    k = torch.where(tiny, torch.ones_like(kappa), kappa)
    one_minus_w = -torch.log1p(v * torch.expm1(-2.0 * k)) / k
    one_minus_w = torch.where(tiny, 2.0 * v, one_minus_w).clamp(0.0, 2.0)  # kappa = 0: w = 1 - 2v uniform
    w = 1.0 - one_minus_w
    r = torch.sqrt((one_minus_w * (2.0 - one_minus_w)).clamp_min(0.0))  # sqrt(1 - w^2)
    e1, e2 = orthonormal_basis(mu)
    return w[..., None] * mu + r[..., None] * (torch.cos(phi)[..., None] * e1 + torch.sin(phi)[..., None] * e2)


def cosine_cdf(w: Tensor, kappa: Tensor) -> Tensor:
    """CDF of w = mu.x under vMF(mu, kappa): (e^{kappa(w+1)} - 1) / (e^{2 kappa} - 1), stably."""
    w = torch.as_tensor(w)
    kappa = torch.as_tensor(kappa, dtype=w.dtype)
    tiny = kappa < 1e-12
    k = torch.where(tiny, torch.ones_like(kappa), kappa)
    # multiply numerator and denominator by e^{-kappa}: overflow-free for any kappa
    cdf = torch.exp(k * (w - 1.0)) * (-torch.expm1(-k * (w + 1.0))) / (-torch.expm1(-2.0 * k))
    return torch.where(tiny, (w + 1.0) / 2.0, cdf).clamp(0.0, 1.0)
