"""Numba kernel of the default per-voxel information (``IGConfig`` ``gain: expected-reduction``).

:func:`voxel_information` is, voxel by voxel, what ``IGService._information`` computes with numpy from
:func:`msmem_core.map.ig.occupancy_reduction` and :func:`msmem_core.map.ig.class_reduction`: the same
operations in the same order (sums over the classes in class order, as numpy's reduction over the
leading axis adds them), so on a CPU where numpy's ``log`` is the C library's (x86 without AVX-512)
the two agree bit for bit; elsewhere to the last bits of ``log`` (tests/test_ig_gain.py). One pass
over the voxels instead of a dozen temporary arrays: the objective evaluates it on the changed voxels
of every push and grasp candidate.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit, prange
from numpy.typing import NDArray

_CHUNK = 256
"""Voxels per task of the parallel kernels."""


@njit(cache=True, fastmath=False, inline="always")
def _xlogx(x: float) -> float:
    return x * math.log(x) if x > 0.0 else 0.0


@njit(cache=True, fastmath=False, inline="always")
def _bernoulli(x: float) -> float:
    return -(_xlogx(x) + _xlogx(1.0 - x))


@njit(cache=True, fastmath=False)
def _sum(x, n, pairwise):
    """The sum of ``x[:n]`` (n >= 1) as numpy's reduction adds it: one after the other when the summed
    axis is the outer loop, numpy's pairwise sum (eight running sums, then the rest) when it is the
    inner one; in ``x``'s precision (float32 values add in float32, as numpy adds them)."""
    if not pairwise or n < 8:
        r = x[0]  # numpy starts from 0: the same sum (no -0.0 here)
        for i in range(1, n):
            r += x[i]
        return r
    r0, r1, r2, r3, r4, r5, r6, r7 = x[0], x[1], x[2], x[3], x[4], x[5], x[6], x[7]
    i = 8
    while i < n - n % 8:
        r0 += x[i]
        r1 += x[i + 1]
        r2 += x[i + 2]
        r3 += x[i + 3]
        r4 += x[i + 4]
        r5 += x[i + 5]
        r6 += x[i + 6]
        r7 += x[i + 7]
        i += 8
    r = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        r += x[i]
        i += 1
    return r


@njit(cache=True, fastmath=False, inline="always")
def _entropy_at(eta, v, pairwise, e, xl):
    """Column ``v``'s entropy (``e``: float32 scratch, ``xl``: float64 scratch, one per class)."""
    nc = eta.shape[0]
    for c in range(nc):
        e[c] = eta[c, v]
    s = _sum(e, nc, pairwise)
    for c in range(nc):
        xl[c] = _xlogx(np.float64(e[c] / s))
    return -_sum(xl, nc, pairwise)


@njit(cache=True, fastmath=False)
def _class_entropy(eta, idx, pairwise, out):  # serial: the term calls it on a few hundred voxels at a time
    e = np.empty(eta.shape[0], dtype=np.float32)
    xl = np.empty(eta.shape[0])
    for i in range(out.shape[0]):
        out[i] = _entropy_at(eta, idx[i] if idx.shape[0] else i, pairwise, e, xl)  # idx[i], or i without idx


def class_entropy(eta: NDArray[np.floating]) -> NDArray[np.float64]:
    """float64 [M]: ``belief.categorical_entropy`` of float32 Dirichlet evidence ``eta`` [C, M], the same
    values (float32 sums and division, float64 ``x log x`` summed in numpy's order for the array's
    layout; tests/test_ig_gain.py) in one pass instead of five temporary arrays. Other dtypes
    and shapes go to numpy."""
    eta = np.asarray(eta)
    if eta.dtype != np.float32 or eta.ndim != 2 or eta.shape[0] == 0:
        from msmem_core.map.belief import categorical_entropy

        return categorical_entropy(eta)
    out = np.empty(eta.shape[1])
    _class_entropy(eta, np.zeros(0, dtype=np.int64), sums_pairwise(eta), out)
    return out


@njit(cache=True, fastmath=False, parallel=True)
def _class_entropy_flags(eta, pairwise, out):
    m = out.shape[0]
    for chunk in prange((m + _CHUNK - 1) // _CHUNK):
        e = np.empty(eta.shape[0], dtype=np.float32)
        xl = np.empty(eta.shape[0])
        for i in range(chunk * _CHUNK, min(m, (chunk + 1) * _CHUNK)):
            out[i] = _entropy_at(eta, i, pairwise[i], e, xl)


def class_entropies(etas: Sequence[NDArray[np.float32]]) -> list[NDArray[np.float64]]:
    """``[class_entropy(e) for e in etas]`` (the same arrays: each voxel's sums in its own array's
    order) from one parallel pass over all of them."""
    etas = [np.asarray(e) for e in etas]
    if len(etas) < 2 or any(e.dtype != np.float32 or e.ndim != 2 or e.shape[0] != etas[0].shape[0] or e.shape[0] == 0
                            for e in etas):
        return [class_entropy(e) for e in etas]
    sizes = [e.shape[1] for e in etas]
    flags = np.repeat(np.array([sums_pairwise(e) for e in etas], dtype=bool), sizes)
    out = np.empty(int(sum(sizes)))
    _class_entropy_flags(np.concatenate(etas, axis=1), flags, out)
    return np.split(out, np.cumsum(sizes)[:-1])


def class_entropy_at(eta: NDArray[np.float32], idx: NDArray[np.int64]) -> NDArray[np.float64]:
    """``class_entropy(eta)[idx]`` for float32 ``eta`` [C, N], computed at ``idx`` only (with the sums
    in the order numpy adds them over the whole of ``eta``, which differs from ``eta[:, idx]``'s)."""
    eta = np.asarray(eta)
    idx = np.asarray(idx, dtype=np.int64)
    if not len(idx):
        return np.zeros(0)
    if eta.dtype != np.float32 or eta.ndim != 2 or eta.shape[0] == 0:
        return class_entropy(eta)[idx]
    out = np.empty(len(idx))
    _class_entropy(eta, idx, sums_pairwise(eta), out)
    return out


@njit(cache=True, fastmath=False, parallel=True)
def _voxel_information(alpha, beta, eta, p, walls, w, classes, pairwise, out):
    nc = eta.shape[0] - 1  # the object classes (row 0 is the background)
    m_one = 1.0 * ((1.0 + w) * math.log(1.0 + w) - _xlogx(1.0))
    n_all = p.shape[0]
    for chunk in prange((n_all + _CHUNK - 1) // _CHUNK):
        es = np.empty(nc)
        els = np.empty(nc)
        ms = np.empty(nc)
        for i in range(chunk * _CHUNK, min(n_all, (chunk + 1) * _CHUNK)):
            if walls[i]:
                out[i] = 0.0
                continue
            pi = np.float64(p[i])
            if pi <= 0.0 or pi >= 1.0:
                h = 0.0
            else:
                a = np.float64(alpha[i])
                b = np.float64(beta[i])
                n = a + b
                q = a / n
                after = q * _bernoulli((a + w) / (n + w)) + (1.0 - q) * _bernoulli(a / (n + w))
                h = max(_bernoulli(q) - after, 0.0)
            if classes:
                if pi == 0.0:  # a finite class part (positive evidence) times p = 0 adds 0
                    finite = True
                    for c in range(nc):
                        if not eta[c + 1, i] > 0.0:
                            finite = False
                            break
                    if finite:
                        out[i] = np.float32(h)
                        continue
                for c in range(nc):
                    e = np.float64(eta[c + 1, i])
                    if e == 1.0:  # the prior's evidence: the values of the branch below, without its logarithms
                        es[c] = 1.0
                        els[c] = 0.0
                        ms[c] = m_one
                    else:
                        el = _xlogx(e)
                        ew = e + w
                        es[c] = e
                        els[c] = el
                        ms[c] = e * (ew * math.log(ew) - el)
                pw = pairwise[i]  # numpy's order of the class sums for this voxel's array
                s = _sum(es, nc, pw)
                total = _sum(els, nc, pw)
                moved = _sum(ms, nc, pw)
                expected = math.log(s + w) - (s * total + moved) / (s * (s + w))
                h = h + pi * max(math.log(s) - total / s - expected, 0.0)
            out[i] = np.float32(h)


def sums_pairwise(a: NDArray[np.floating]) -> bool:
    """Whether numpy's ``a.sum(axis=0)`` of a 2-D array adds pairwise (the summed axis is the one its
    loop runs along: the smaller stride, or a single column) rather than one row after the other."""
    return a.shape[1] == 1 or abs(a.strides[0]) < abs(a.strides[1])


def voxel_information(alpha: NDArray[np.floating], beta: NDArray[np.floating], eta: NDArray[np.floating],
                      p: NDArray[np.float32], walls: NDArray[np.bool_], w: float, classes: bool) -> NDArray[np.float32]:
    """float32 [N]: per voxel the expected entropy drop of one more observation of evidence ``w``, from
    ``Beta(alpha, beta)`` occupancy evidence and Dirichlet class evidence ``eta`` [C, N] (row 0 the
    background, left out), at clamped occupancy ``p``: 0 on ``walls``, no occupancy part where ``p``
    is clamped to 0 or 1, and with ``classes`` the class part weighted by ``p``."""
    eta = np.asarray(eta)
    return voxel_information_of(alpha, beta, eta, p, walls, w, classes, np.full(len(p), sums_pairwise(eta)))


def voxel_information_of(alpha: NDArray[np.floating], beta: NDArray[np.floating], eta: NDArray[np.floating],
                         p: NDArray[np.float32], walls: NDArray[np.bool_], w: float, classes: bool,
                         pairwise: NDArray[np.bool_]) -> NDArray[np.float32]:
    """:func:`voxel_information` of voxels gathered from several arrays: ``pairwise`` [N] says, per
    voxel, whether its own array's class sums were pairwise (``sums_pairwise``), so that each voxel has
    the value :func:`voxel_information` gives it in its own array."""
    out = np.empty(len(p), dtype=np.float32)
    _voxel_information(np.asarray(alpha), np.asarray(beta), np.asarray(eta), np.asarray(p),
                       np.asarray(walls, dtype=np.bool_), float(w), bool(classes), np.asarray(pairwise, dtype=np.bool_),
                       out)
    return out
