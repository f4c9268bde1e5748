"""Tests of ``msmem_cnabu.learn.losses`` that the mutation run (docs/explanation/reliability.md, "Mutation
testing of the math") showed missing: the dtype of the KL terms, the normalisation by the total weight
when it is below 2, and float64 weights that float32 cannot represent. References are scipy, voxel by
voxel."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.special as sp
import scipy.stats
import torch
from msmem_cnabu.learn.losses import CNABULossConfig, cnabu_loss, dirichlet_kl_uniform, evidential_dirichlet_loss

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _dirichlet_kl(e):
    """KL(Dir(e) || Dir(1)) = -H(Dir(e)) - log Gamma(C) (the uniform Dirichlet's density is Gamma(C))."""
    return -scipy.stats.dirichlet(e).entropy() - sp.gammaln(len(e))


def _reference(a, b, eta, logit, pa, pb, peta, occ, cls, change, valid, focus, cfg, epoch):
    """The loss terms, voxel by voxel in Python floats with scipy (numpy arrays, ``eta`` [B, C, ...])."""
    kl_w = cfg.kl_max * min(1.0, epoch / cfg.anneal_epochs)
    acc = dict.fromkeys(("occ_ce", "occ_kl", "sem_ce", "sem_kl"), 0.0)
    wsum = bce = vsum = 0.0
    for i in np.ndindex(*a.shape):
        p = 1.0 / (1.0 + math.exp(-logit[i])) if logit is not None else 1.0
        al, be = pa[i] + p * (a[i] - pa[i]), pb[i] + p * (b[i] - pb[i])
        e = np.array([peta[(i[0], c, *i[1:])] + p * (eta[(i[0], c, *i[1:])] - peta[(i[0], c, *i[1:])])
                      for c in range(eta.shape[1])])
        w = (1.0 + cfg.focus_weight if focus[i] else 1.0) if valid[i] else 0.0
        wsum += w
        k = int(cls[i])
        acc["occ_ce"] += w * (sp.digamma(al + be) - sp.digamma(al if occ[i] else be))
        acc["occ_kl"] += w * kl_w * -scipy.stats.beta(*((1.0, be) if occ[i] else (al, 1.0))).entropy()
        acc["sem_ce"] += w * (sp.digamma(e.sum()) - sp.digamma(e[k]))
        acc["sem_kl"] += w * kl_w * _dirichlet_kl(np.where(np.arange(len(e)) == k, 1.0, e))
        if logit is not None and valid[i]:
            q = 1.0 / (1.0 + math.exp(-logit[i]))
            bce += -(cfg.change_pos_weight * math.log(q)) if change[i] else -math.log(1.0 - q)
            vsum += 1.0
    out = {k: v / max(wsum, 1.0) for k, v in acc.items()}
    out["total"] = cfg.w_occupancy * (out["occ_ce"] + out["occ_kl"]) + cfg.w_semantic * (out["sem_ce"] + out["sem_kl"])
    if logit is not None:
        out["change_bce"] = bce / max(vsum, 1.0)
        out["total"] += cfg.w_change * out["change_bce"]
    return out


def _batch(seed, shape=(1, 2, 2, 1), c=3):
    rng = np.random.default_rng(seed)
    ev = lambda *s: 1.0 + rng.gamma(1.5, 3.0, size=s)  # noqa: E731
    occ = rng.random(shape) < 0.5
    return {
        "a": ev(*shape), "b": ev(*shape), "eta": ev(shape[0], c, *shape[1:]), "logit": rng.normal(0, 1.5, size=shape),
        "pa": ev(*shape), "pb": ev(*shape), "peta": ev(shape[0], c, *shape[1:]),
        "occ": occ, "cls": np.where(occ, rng.integers(1, c, size=shape), 0), "change": rng.random(shape) < 0.5,
    }


def _check(d, valid, focus, cfg, with_change, epoch=2.0, rel=1e-11):
    t = torch.from_numpy
    logit = d["logit"] if with_change else None
    got = cnabu_loss(t(d["a"]), t(d["b"]), t(d["eta"]), None if logit is None else t(logit), t(d["pa"]), t(d["pb"]),
                     t(d["peta"]), t(d["occ"]), t(d["cls"]), t(d["change"]), t(valid), t(focus), epoch, cfg)
    ref = _reference(d["a"], d["b"], d["eta"], logit, d["pa"], d["pb"], d["peta"], d["occ"], d["cls"], d["change"],
                     valid, focus, cfg, epoch)
    assert set(got) == set(ref)
    for k, v in ref.items():
        assert float(got[k]) == pytest.approx(v, rel=rel, abs=1e-13), k


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_loss_kl_terms_keep_the_evidence_dtype(dtype):
    """dirichlet_kl_uniform works in float64 but returns eta's dtype; so does the misleading-evidence KL,
    also for a half-precision eta (its one-hot must not promote it to float32)."""
    eta = np.array([[2.0, 3.0, 4.0], [40.0, 5.0, 1.0]])  # [B=2, C=3], exact in bfloat16
    y = np.array([0, 2])
    e = torch.tensor(eta, dtype=dtype)[..., None]  # [B, C, X=1]
    tol = {"rel": 1e-5, "abs": 1e-5} if dtype == torch.float32 else {"rel": 1e-2, "abs": 1e-2}
    kl = dirichlet_kl_uniform(e)
    assert kl.dtype == dtype
    for i in range(2):
        assert float(kl[i, 0]) == pytest.approx(_dirichlet_kl(eta[i]), **tol)
    ce, mis = evidential_dirichlet_loss(e, torch.tensor(y)[:, None], 0.5)
    assert ce.dtype == mis.dtype == dtype
    for i in range(2):
        assert float(ce[i, 0]) == pytest.approx(sp.digamma(eta[i].sum()) - sp.digamma(eta[i, y[i]]), **tol)
        reset = np.where(np.arange(3) == y[i], 1.0, eta[i])
        assert float(mis[i, 0]) == pytest.approx(0.5 * _dirichlet_kl(reset), **tol)


@pytest.mark.parametrize("with_change", [True, False])
@pytest.mark.parametrize(("focused", "focus_weight"), [(False, 4.0), (True, 0.5)])
def test_loss_of_one_lone_valid_voxel_is_that_voxels_loss(with_change, focused, focus_weight):
    """A total weight in [1, 2) (one valid voxel of weight 1 or 1.5) divides by itself, not by more:
    the terms are that voxel's own; the change BCE is averaged over the one valid voxel."""
    d = _batch(3)
    valid = np.zeros(d["a"].shape, dtype=bool)
    valid[0, 1, 0, 0] = True
    focus = valid & focused
    cfg = CNABULossConfig(focus_weight=focus_weight, kl_max=0.2, anneal_epochs=4.0)
    _check(d, valid, focus, cfg, with_change)


def test_loss_weights_stay_float64():
    """Focus and change weights that float32 cannot represent (0.3) are applied in float64."""
    d = _batch(5, shape=(2, 2, 2, 1))
    rng = np.random.default_rng(6)
    valid = rng.random(d["a"].shape) < 0.8
    focus = rng.random(d["a"].shape) < 0.5
    d["change"][0, 0, 0, 0], d["change"][0, 0, 1, 0] = True, False  # both BCE branches
    valid[0, 0, :, 0] = True
    cfg = CNABULossConfig(focus_weight=0.3, change_pos_weight=0.3, w_change=1.0, kl_max=0.2, anneal_epochs=4.0)
    assert float(np.float32(0.3)) != 0.3
    _check(d, valid, focus, cfg, with_change=True)
