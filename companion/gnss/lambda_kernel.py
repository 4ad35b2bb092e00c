"""Compiled LAMBDA (numba): :func:`companion.gnss.lambda_ils.lambda_ils` with its three loops --
the LDL factorisation, the decorrelation and the MLAMBDA search -- compiled.

An RTK epoch in the filter tries LAMBDA several times (partial fixing drops one ambiguity after
another), on 10-20 ambiguities: ~70 permutations and ~500 integer Gauss transformations per
call, each a handful of numpy calls on short rows.  That interpretation was half of the RTK
load's CPU time.  The kernels here are the reference's operations element by element in the same
order (its row operations are element-wise, numba keeps IEEE semantics without ``fastmath``), so
the results are the reference's bit for bit (tests/test_lambda_kernel.py); the sorting, the back
transformation and the success rate stay in numpy.  Without numba (or with ``COMPANION_NUMBA=0``)
:func:`lambda_ils` is the reference itself.
"""
from __future__ import annotations

import math

import numpy as np

from ..nav.imu_kernel import jit_options, numba_or_none
from . import lambda_ils as reference

_kernels = None
_tried = False


def ldl(Q):
    """Reference :func:`~companion.gnss.lambda_ils.ldl`; returns (L, D, ok) instead of raising."""
    A = Q.copy()
    n = A.shape[0]
    L = np.zeros((n, n))
    D = np.zeros(n)
    for i in range(n - 1, -1, -1):
        D[i] = A[i, i]
        if not D[i] > 0.0:
            return L, D, False
        a = math.sqrt(D[i])
        for c in range(i + 1):
            L[i, c] = A[i, c] / a
        for j in range(i):
            lij = L[i, j]
            for c in range(j + 1):
                A[j, c] -= L[i, c] * lij
        lii = L[i, i]
        for c in range(i + 1):
            L[i, c] /= lii
    return L, D, True


def reduce_inverse(L, D, two):
    """Reference :func:`~companion.gnss.lambda_ils.reduce` (with its ``_gauss`` and ``_perm``)
    that also returns ``Z^-1`` (kept by the inverse operations: a Gauss
    transformation of Z's column j by column i adds row j to row i of ``Z^-1``, a permutation of
    columns swaps its rows), so that the candidates go back to the original ambiguities as
    ``Z^-T z`` in exact integer arithmetic instead of a linear solve.  Z, L and D exactly
    the reference's; Z is kept transposed inside (its column operations on contiguous rows) and
    L's column operations run on a transposed copy, the same arithmetic element by element.
    ``two`` = 2.0, passed at run time: the reference's ``x ** 2`` is the C library's pow(x, 2),
    which is not always x * x (1 ulp apart in ~1 of 2000 values with glibc); with a constant
    exponent LLVM would turn it into x * x, with this one it calls pow as CPython does."""
    n = len(D)
    Zt = np.eye(n)
    Zi = np.eye(n)
    Lt = L.T.copy()
    j = k = n - 2
    while j >= 0:
        if j <= k:
            for i in range(j + 1, n):
                mu = math.floor(Lt[j, i] + 0.5)
                if mu != 0:
                    for r in range(i, n):
                        Lt[j, r] -= mu * Lt[i, r]
                    for r in range(n):
                        Zt[j, r] -= mu * Zt[i, r]
                    for c in range(n):
                        Zi[i, c] += mu * Zi[j, c]
        delta = D[j] + Lt[j, j + 1] ** two * D[j + 1]
        if delta + 1e-6 < D[j + 1]:
            eta = D[j] / delta
            lam = D[j + 1] * Lt[j, j + 1] / delta
            D[j] = eta * D[j + 1]
            D[j + 1] = delta
            l10 = Lt[j, j + 1]
            for c in range(j):
                a0 = Lt[c, j]
                a1 = Lt[c, j + 1]
                Lt[c, j] = -l10 * a0 + a1
                Lt[c, j + 1] = eta * a0 + lam * a1
            Lt[j, j + 1] = lam
            for r in range(j + 2, n):
                t = Lt[j, r]
                Lt[j, r] = Lt[j + 1, r]
                Lt[j + 1, r] = t
            for r in range(n):
                t = Zt[j, r]
                Zt[j, r] = Zt[j + 1, r]
                Zt[j + 1, r] = t
            for c in range(n):
                t = Zi[j, c]
                Zi[j, c] = Zi[j + 1, c]
                Zi[j + 1, c] = t
            k = j
            j = n - 2
        else:
            j -= 1
    L[:, :] = Lt.T
    return Zt.T.copy(), Zi


def search(L, D, zs, m, max_loops):
    """Reference :func:`~companion.gnss.lambda_ils.search` before its final sort: (candidates
    n x m, squared norms, finished)."""
    n = len(D)
    S = np.zeros((n, n))
    dist = np.zeros(n)
    zb = np.zeros(n)
    z = np.zeros(n)
    step = np.zeros(n)
    zn = np.zeros((n, m))
    s = np.full(m, np.inf)
    nn = 0
    imax = 0
    maxdist = np.inf
    k = n - 1
    zb[k] = zs[k]
    z[k] = math.floor(zb[k] + 0.5)
    y = zb[k] - z[k]
    step[k] = -1.0 if y <= 0.0 else 1.0
    for _ in range(max_loops):
        newdist = dist[k] + y * y / D[k]
        if newdist < maxdist:
            if k != 0:
                k -= 1
                dist[k] = newdist
                dz = z[k + 1] - zb[k + 1]
                for c in range(k + 1):
                    S[k, c] = S[k + 1, c] + dz * L[k + 1, c]
                zb[k] = zs[k] + S[k, k]
                z[k] = math.floor(zb[k] + 0.5)
                y = zb[k] - z[k]
                step[k] = -1.0 if y <= 0.0 else 1.0
            else:
                if nn < m:
                    if nn == 0 or newdist > s[imax]:
                        imax = nn
                    zn[:, nn] = z
                    s[nn] = newdist
                    nn += 1
                else:
                    if newdist < s[imax]:
                        zn[:, imax] = z
                        s[imax] = newdist
                        imax = int(np.argmax(s))
                    maxdist = s[imax]
                z[0] += step[0]
                y = zb[0] - z[0]
                step[0] = -step[0] - (-1.0 if step[0] <= 0.0 else 1.0)
        else:
            if k == n - 1:
                return zn, s, True
            k += 1
            z[k] += step[k]
            y = zb[k] - z[k]
            step[k] = -step[k] - (-1.0 if step[k] <= 0.0 else 1.0)
    return zn, s, False


class _Compiled:
    def __init__(self, numba):
        jit = numba.njit(**jit_options(numba))
        self.ldl = jit(ldl)
        self.reduce_inverse = jit(reduce_inverse)
        self.search = jit(search)


def compiled():
    global _kernels, _tried
    if not _tried:
        _tried = True
        numba = numba_or_none()
        if numba is not None:
            _kernels = _Compiled(numba)
    return _kernels


def lambda_ils(a: np.ndarray, Q: np.ndarray, m: int = 2, max_loops: int = 100000) -> reference.IlsResult:
    """:func:`companion.gnss.lambda_ils.lambda_ils`, compiled when numba is there (same results,
    same exceptions)."""
    k = compiled()
    if k is None:
        return reference.lambda_ils(a, Q, m)
    a = np.asarray(a, dtype=float)
    L, D, ok = k.ldl(np.array(Q, dtype=float))
    if not ok:
        raise np.linalg.LinAlgError("ambiguity covariance not positive definite")
    Z, Zi = k.reduce_inverse(L, D, 2.0)
    zs = Z.T @ a
    zn, s, finished = k.search(L, D, zs, m, max_loops)
    if not finished:
        raise RuntimeError("LAMBDA search did not finish: ambiguity covariance too ill-conditioned")
    order = np.argsort(s)
    # Z unimodular: Z^-T z is an integer vector, here exactly (the reference solves Z^T F = z and
    # rounds, the same integers while they are far below 2^53)
    F = Zi.T @ zn[:, order]
    return reference.IlsResult(np.round(F), s[order], reference.bootstrap_success_rate(D))
