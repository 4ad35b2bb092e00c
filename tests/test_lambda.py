"""LAMBDA / MLAMBDA integer least squares (companion.gnss.lambda_ils) against brute-force
enumeration and a published example."""
from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from companion.gnss.lambda_ils import bootstrap_success_rate, lambda_ils, ldl, reduce


def _brute_force(a, Q, m=2, radius=4):
    """The m best integers by enumerating a box around round(a) (the reference)."""
    Qi = np.linalg.inv(Q)
    base = np.round(a)
    best = []
    for d in itertools.product(range(-radius, radius + 1), repeat=len(a)):
        z = base + np.array(d)
        r = a - z
        best.append((float(r @ Qi @ r), tuple(z)))
    best.sort()
    return [np.array(z) for _, z in best[:m]], [q for q, _ in best[:m]]


def test_published_three_dimensional_example():
    """The example of de Jonge & Tiberius (1996) / the LAMBDA toolbox documentation: a highly
    correlated 3-D problem whose integer least-squares solution is (5, 3, 4), not round(a)."""
    a = np.array([5.45, 3.10, 2.97])
    Q = np.array([[6.290, 5.978, 0.544], [5.978, 6.292, 2.340], [0.544, 2.340, 6.288]])
    res = lambda_ils(a, Q, m=2)
    assert res.fixed[:, 0].tolist() == [5.0, 3.0, 4.0]
    assert res.sqnorm[0] == pytest.approx(0.2183, abs=5e-4)
    ref, norms = _brute_force(a, Q, radius=3)
    assert np.array_equal(res.fixed[:, 1], ref[1]) and res.sqnorm == pytest.approx(norms, rel=1e-9)


@pytest.mark.parametrize("seed", range(8))
def test_matches_brute_force_on_random_correlated_problems(seed):
    rng = np.random.default_rng(seed)
    n = 4
    A = rng.standard_normal((n, n))
    Q = A @ A.T * 0.3 + 0.05 * np.eye(n)             # correlated, conditioned like float ambiguities
    a = rng.standard_normal(n) * 3.0
    res = lambda_ils(a, Q, m=3)
    ref, norms = _brute_force(a, Q, m=3, radius=4)
    for k in range(3):
        assert np.array_equal(res.fixed[:, k], ref[k]), (k, res.fixed[:, k], ref[k])
    assert res.sqnorm == pytest.approx(norms, rel=1e-9)
    assert res.ratio == pytest.approx(norms[1] / norms[0])


def test_decorrelation_is_unimodular_and_preserves_the_problem():
    rng = np.random.default_rng(3)
    A = rng.standard_normal((6, 6))
    Q = A @ A.T + 0.01 * np.eye(6)
    L, D = ldl(Q)
    assert np.allclose(L.T @ np.diag(D) @ L, Q)
    Z = reduce(L, D)
    assert abs(abs(np.linalg.det(Z)) - 1.0) < 1e-9 and np.array_equal(Z, np.round(Z))
    assert np.allclose(L.T @ np.diag(D) @ L, Z.T @ Q @ Z)          # the reduced factors are Z^T Q Z's
    # decorrelation flattens the conditional variances: the largest can only come down
    _, D0 = ldl(Q)
    assert D.max() <= D0.max() + 1e-12


def test_bootstrap_success_rate():
    # one ambiguity with sigma 0.1 cycles: P(|e| < 0.5) = erf(0.5 / (0.1 sqrt 2))
    assert bootstrap_success_rate(np.array([0.01])) == pytest.approx(math.erf(0.5 / (0.1 * math.sqrt(2))))
    assert bootstrap_success_rate(np.array([0.01, 0.25])) < bootstrap_success_rate(np.array([0.01]))
    precise = lambda_ils(np.array([1.02, -2.01]), np.diag([1e-4, 1e-4]))
    assert precise.success_rate > 0.999999 and precise.fixed[:, 0].tolist() == [1.0, -2.0]
