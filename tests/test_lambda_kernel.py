"""The compiled LAMBDA (companion.gnss.lambda_kernel) is the reference (companion.gnss.lambda_ils)
bit for bit: candidates, squared norms, success rate, and the same exceptions."""
import numpy as np
import pytest

from companion.gnss import lambda_ils as reference
from companion.gnss import lambda_kernel

pytest.importorskip("numba")
pytestmark = pytest.mark.skipif(lambda_kernel.compiled() is None, reason="kernels disabled (COMPANION_NUMBA=0)")


def _problem(rng, n):
    """Float ambiguities with a strongly correlated covariance, as DD ambiguities after a few
    epochs (conditional variances spanning orders of magnitude)."""
    A = rng.normal(size=(n, n)) @ np.diag(10.0 ** rng.uniform(-2, 1, n))
    Q = A @ A.T * 0.01 + np.eye(n) * 1e-4
    return rng.normal(scale=20.0, size=n), Q


@pytest.mark.parametrize("n", [2, 5, 12, 20])
def test_compiled_lambda_is_the_reference_bit_for_bit(n):
    rng = np.random.default_rng(n)
    for _ in range(20):
        a, Q = _problem(rng, n)
        for m in (2, 3):
            got, ref = lambda_kernel.lambda_ils(a, Q, m), reference.lambda_ils(a, Q, m)
            assert np.array_equal(got.fixed, ref.fixed)
            assert np.array_equal(got.sqnorm, ref.sqnorm)
            assert got.success_rate == ref.success_rate


def test_compiled_lambda_raises_as_the_reference():
    Q = np.diag([1.0, -1.0, 1.0])
    for f in (lambda_kernel.lambda_ils, reference.lambda_ils):
        with pytest.raises(np.linalg.LinAlgError):
            f(np.zeros(3), Q)
