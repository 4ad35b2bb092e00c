"""companion.nav.chi2: chi-square quantiles without scipy.stats, against scipy.stats.chi2.ppf."""
from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import chi2

from companion.nav.chi2 import chi2_cdf_sf, chi2_ppf


def test_ppf_matches_scipy_over_the_gate_range():
    """dof 1..100, p in [0.9, 0.9999]: the range of the filter, RAIM and cluster gates."""
    worst = 0.0
    for dof in range(1, 101):
        for p in np.linspace(0.9, 0.9999, 25):
            ours, ref = chi2_ppf(p, dof), float(chi2.ppf(p, dof))
            worst = max(worst, abs(ours - ref) / ref)
    assert worst < 1e-11, worst


@pytest.mark.parametrize("p, dof", [
    (0.999, 1),            # filter leave-one-out gate (gate_probability default)
    (1 - 1e-3, 1), (1 - 1e-3, 28),   # RAIM global test, nsat - 4 degrees of freedom
    (1 - 1e-6, 120),       # IMU cluster: 6 x window 20
    (1 - 1e-12, 3), (1e-6, 5), (0.025, 900), (0.975, 900), (0.5, 1), (0.5, 0.5), (0.7, 2.5),
])
def test_ppf_matches_scipy_where_it_is_used_and_beyond(p, dof):
    assert chi2_ppf(p, dof) == pytest.approx(float(chi2.ppf(p, dof)), rel=1e-11)


def test_ppf_inverts_cdf_and_closed_forms():
    # dof 2 is exponential with mean 2: x = -2 ln(1 - p)
    for p in (0.9, 0.99, 0.9999):
        assert chi2_ppf(p, 2) == pytest.approx(-2.0 * math.log1p(-p), rel=1e-13)
        cdf, sf = chi2_cdf_sf(chi2_ppf(p, 7), 7)
        assert sf == pytest.approx(1.0 - p, rel=1e-10)
    assert chi2_cdf_sf(0.0, 3) == (0.0, 1.0)


def test_ppf_ends_as_scipy():
    assert chi2_ppf(0.0, 3) == 0.0 == chi2.ppf(0.0, 3)
    assert chi2_ppf(1.0, 3) == math.inf == chi2.ppf(1.0, 3)


@pytest.mark.parametrize("p, dof", [(-0.1, 1), (1.1, 1), (float("nan"), 1), (0.9, 0), (0.9, -1),
                                    (0.9, float("inf"))])
def test_ppf_refuses_out_of_domain(p, dof):
    with pytest.raises(ValueError, match="chi2_ppf"):
        chi2_ppf(p, dof)
