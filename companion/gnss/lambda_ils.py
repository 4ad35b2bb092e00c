"""Integer least squares for carrier-phase ambiguities: LAMBDA decorrelation and MLAMBDA search.

Given float ambiguities ``a`` (n) with covariance ``Q`` (n x n), find the integer vectors ``z``
minimising ``(a - z)^T Q^-1 (a - z)``, the ``m`` best of them with their squared norms.

* **Decorrelation** (Teunissen 1995; de Jonge & Tiberius 1996, "The LAMBDA method for integer
  ambiguity estimation: implementation aspects"): ``Q = L^T diag(D) L`` with ``L`` unit lower
  triangular, reduced by integer Gauss transformations and symmetric permutations into
  ``Qz = Z^T Q Z`` whose conditional variances ``D`` are as flat as possible (``Z`` unimodular, so
  the integers map one to one).
* **Search** (Chang, Yang & Zhou 2005, "MLAMBDA: a modified LAMBDA method"): depth-first
  enumeration with the search ellipsoid shrunk to the m-th best norm found so far, zig-zag
  around each conditional estimate.  The same algorithm as RTKLIB's ``lambda.c``, written here
  from the papers: numpy arrays, 0-based, ``L[i, j]`` row i column j.
* **Validation helpers**: the ratio test (second best over best norm) and the bootstrapped
  success rate ``prod_i (2 Phi(1 / (2 sqrt(D_i))) - 1)`` (Teunissen 1998), a lower bound of the
  integer least-squares success rate computed from the decorrelated conditional variances.

Pure numpy, no state; tested against brute-force enumeration and a published example.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def ldl(Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Q = L^T diag(D) L``, L unit lower triangular (the LAMBDA ordering: from the last row up)."""
    A = np.array(Q, dtype=float, copy=True)
    n = A.shape[0]
    L = np.zeros((n, n))
    D = np.zeros(n)
    for i in range(n - 1, -1, -1):
        D[i] = A[i, i]
        if not D[i] > 0.0:
            raise np.linalg.LinAlgError("ambiguity covariance not positive definite")
        a = math.sqrt(D[i])
        L[i, :i + 1] = A[i, :i + 1] / a
        for j in range(i):
            A[j, :j + 1] -= L[i, :j + 1] * L[i, j]
        L[i, :i + 1] /= L[i, i]
    return L, D


def _round(x: float) -> float:
    """Half up, as the papers' and RTKLIB's ROUND (Python's round() is half-to-even)."""
    return math.floor(x + 0.5)


def _gauss(L: np.ndarray, Z: np.ndarray, i: int, j: int) -> None:
    mu = _round(L[i, j])
    if mu != 0:
        L[i:, j] -= mu * L[i:, i]
        Z[:, j] -= mu * Z[:, i]


def _perm(L: np.ndarray, D: np.ndarray, j: int, delta: float, Z: np.ndarray) -> None:
    eta = D[j] / delta
    lam = D[j + 1] * L[j + 1, j] / delta
    D[j] = eta * D[j + 1]
    D[j + 1] = delta
    a0 = L[j, :j].copy()
    a1 = L[j + 1, :j].copy()
    L[j, :j] = -L[j + 1, j] * a0 + a1
    L[j + 1, :j] = eta * a0 + lam * a1
    L[j + 1, j] = lam
    L[j + 2:, [j, j + 1]] = L[j + 2:, [j + 1, j]]
    Z[:, [j, j + 1]] = Z[:, [j + 1, j]]


def reduce(L: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Decorrelate in place (L, D become those of ``Z^T Q Z``); returns the integer matrix Z."""
    n = len(D)
    Z = np.eye(n)
    j = k = n - 2
    while j >= 0:
        if j <= k:
            for i in range(j + 1, n):
                _gauss(L, Z, i, j)
        delta = D[j] + L[j + 1, j] ** 2 * D[j + 1]
        if delta + 1e-6 < D[j + 1]:
            _perm(L, D, j, delta, Z)
            k = j
            j = n - 2
        else:
            j -= 1
    return Z


def _sgn(x: float) -> float:
    return -1.0 if x <= 0.0 else 1.0


def search(L: np.ndarray, D: np.ndarray, zs: np.ndarray, m: int = 2,
           max_loops: int = 100000) -> tuple[np.ndarray, np.ndarray]:
    """MLAMBDA search: the ``m`` best integer vectors (columns, n x m) and their squared norms,
    best first.  ``max_loops`` bounds the work (an ill-conditioned problem raises)."""
    n = len(D)
    S = np.zeros((n, n))
    dist = np.zeros(n)
    zb = np.zeros(n)
    z = np.zeros(n)
    step = np.zeros(n)
    zn = np.zeros((n, m))
    s = np.full(m, np.inf)
    nn = imax = 0
    maxdist = np.inf
    k = n - 1
    zb[k] = zs[k]
    z[k] = _round(zb[k])
    y = zb[k] - z[k]
    step[k] = _sgn(y)
    for _ in range(max_loops):
        newdist = dist[k] + y * y / D[k]
        if newdist < maxdist:
            if k != 0:
                k -= 1
                dist[k] = newdist
                S[k, :k + 1] = S[k + 1, :k + 1] + (z[k + 1] - zb[k + 1]) * L[k + 1, :k + 1]
                zb[k] = zs[k] + S[k, k]
                z[k] = _round(zb[k])
                y = zb[k] - z[k]
                step[k] = _sgn(y)
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
                step[0] = -step[0] - _sgn(step[0])
        else:
            if k == n - 1:
                break
            k += 1
            z[k] += step[k]
            y = zb[k] - z[k]
            step[k] = -step[k] - _sgn(step[k])
    else:
        raise RuntimeError("LAMBDA search did not finish: ambiguity covariance too ill-conditioned")
    order = np.argsort(s)
    return zn[:, order], s[order]


@dataclass
class IlsResult:
    fixed: np.ndarray          # n x m integer candidates in the original ambiguities, best first
    sqnorm: np.ndarray         # m squared norms (a - z)^T Q^-1 (a - z), ascending
    success_rate: float        # bootstrapped success rate of the decorrelated problem

    @property
    def ratio(self) -> float:
        """Ratio test statistic: second best over best squared norm (inf when the best is exact)."""
        if len(self.sqnorm) < 2:
            return float("inf")
        return float(self.sqnorm[1] / self.sqnorm[0]) if self.sqnorm[0] > 0 else float("inf")


def bootstrap_success_rate(D: np.ndarray) -> float:
    """prod (2 Phi(1 / (2 sqrt(d))) - 1) over the conditional variances of the decorrelated problem."""
    p = 1.0
    for d in D:
        p *= math.erf(1.0 / (2.0 * math.sqrt(2.0 * d)))      # 2 Phi(x) - 1 = erf(x / sqrt 2)
    return p


def lambda_ils(a: np.ndarray, Q: np.ndarray, m: int = 2) -> IlsResult:
    """The ``m`` best integer solutions of the float ambiguities ``a`` with covariance ``Q``."""
    a = np.asarray(a, dtype=float)
    L, D = ldl(Q)
    Z = reduce(L, D)
    zs = Z.T @ a
    E, s = search(L, D, zs, m)
    F = np.linalg.solve(Z.T, E)          # back to the original ambiguities (Z unimodular: integers)
    return IlsResult(np.round(F), s, bootstrap_success_rate(D))


__all__ = ["ldl", "reduce", "search", "lambda_ils", "bootstrap_success_rate", "IlsResult"]
