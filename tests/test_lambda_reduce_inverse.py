"""The compiled reduction with its inverse (companion.gnss.lambda_kernel.reduce_inverse): the
reference reduction's Z, L and D bit for bit, and Z^-1 exactly Z's inverse (integers)."""
import numpy as np
import pytest

from companion.gnss import lambda_ils as reference
from companion.gnss import lambda_kernel

pytest.importorskip("numba")
pytestmark = pytest.mark.skipif(lambda_kernel.compiled() is None, reason="kernels disabled (COMPANION_NUMBA=0)")


@pytest.mark.parametrize("n", [2, 7, 20, 36])
def test_reduce_inverse_is_the_reference_reduction_and_its_exact_inverse(n):
    rng = np.random.default_rng(100 + n)
    k = lambda_kernel.compiled()
    for _ in range(10):
        A = rng.normal(size=(n, n)) @ np.diag(10.0 ** rng.uniform(-2, 1, n))
        Q = A @ A.T * 0.01 + np.eye(n) * 1e-4
        L0, D0 = reference.ldl(Q)
        Z0 = reference.reduce(L0, D0)
        L, D, ok = k.ldl(Q.copy())
        assert ok
        Z, Zi = k.reduce_inverse(L, D, 2.0)
        assert np.array_equal(Z, Z0) and np.array_equal(L, L0) and np.array_equal(D, D0)
        assert np.array_equal(Zi @ Z, np.eye(n))          # integers: exact
        assert np.array_equal(Zi, np.round(Zi))
