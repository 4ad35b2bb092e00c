"""Chi-square quantiles without scipy.stats (which costs about 1 s and 40 MB to import at start-up).

:func:`chi2_ppf` is the inverse of the chi-square CDF with ``dof`` degrees of freedom, the gate
thresholds of the filter (leave-one-out innovation test), of RAIM (global test) and of the IMU
cluster (window test).  Method: the Wilson-Hilferty cube-root normal approximation
(``x = k (1 - 2/(9k) + z sqrt(2/(9k)))^3``, Johnson, Kotz & Balakrishnan, *Continuous Univariate
Distributions* vol. 1, eq. 18.24) as the start, refined by safeguarded Newton steps on the log of
the regularized incomplete gamma function of the tail that holds the probability mass
(``Q(k/2, x/2) = 1 - p`` for p >= 0.5, ``P(k/2, x/2) = p`` below), so the answer keeps its full
relative accuracy out to p = 1 - 1e-12.  ``P`` and ``Q`` come from their power series and Lentz's
continued fraction (Numerical Recipes, 3rd ed., section 6.2).  Checked against
``scipy.stats.chi2.ppf`` in ``tests/test_chi2.py``.

Pure Python and stdlib ``math`` only: called at construction time, never on the IMU-rate path.
"""
from __future__ import annotations

import math

_EPS = 1e-15
_TINY = 1e-300


def _gamma_series_p(a: float, x: float) -> float:
    """Regularized lower incomplete gamma P(a, x) by its power series (converges fast for x < a+1)."""
    term = total = 1.0 / a
    ap = a
    for _ in range(10_000):
        ap += 1.0
        term *= x / ap
        total += term
        if abs(term) < abs(total) * _EPS:
            break
    return total * math.exp(-x + a * math.log(x) - math.lgamma(a))


def _gamma_cf_q(a: float, x: float) -> float:
    """Regularized upper incomplete gamma Q(a, x) by Lentz's continued fraction (for x >= a+1)."""
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, 10_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = _TINY if abs(d) < _TINY else d
        c = b + an / c
        c = _TINY if abs(c) < _TINY else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    return h * math.exp(-x + a * math.log(x) - math.lgamma(a))


def chi2_cdf_sf(x: float, dof: float) -> tuple[float, float]:
    """(CDF, survival function) of the chi-square distribution at x; the smaller one is accurate."""
    if x <= 0.0:
        return 0.0, 1.0
    a, h = 0.5 * dof, 0.5 * x
    if h < a + 1.0:
        p = _gamma_series_p(a, h)
        return p, 1.0 - p
    q = _gamma_cf_q(a, h)
    return 1.0 - q, q


def _log_pdf(x: float, dof: float) -> float:
    a = 0.5 * dof
    return (a - 1.0) * math.log(x) - 0.5 * x - a * math.log(2.0) - math.lgamma(a)


def _normal_ppf(p: float) -> float:
    """Standard normal quantile to ~1e-9 (Acklam's rational approximation); only a starting value."""
    a = (-3.969683028665376e+01, 2.209460984245205e+02, -2.759285104469687e+02,
         1.383577518672690e+02, -3.066479806614716e+01, 2.506628277459239e+00)
    b = (-5.447609879822406e+01, 1.615858368580409e+02, -1.556989798598866e+02,
         6.680131188771972e+01, -1.328068155288572e+01)
    c = (-7.784894002430293e-03, -3.223964580411365e-01, -2.400758277161838e+00,
         -2.549732539343734e+00, 4.374664141464968e+00, 2.938163982698783e+00)
    d = (7.784695709041462e-03, 3.224671290700398e-01, 2.445134137142996e+00, 3.754408661907416e+00)
    if p < 0.02425 or p > 1.0 - 0.02425:
        q = math.sqrt(-2.0 * math.log(min(p, 1.0 - p)))
        z = (((((c[0] * q + c[1]) * q + c[2]) * q + c[3]) * q + c[4]) * q + c[5]) / \
            ((((d[0] * q + d[1]) * q + d[2]) * q + d[3]) * q + 1.0)
        return z if p < 0.5 else -z
    q = p - 0.5
    r = q * q
    return (((((a[0] * r + a[1]) * r + a[2]) * r + a[3]) * r + a[4]) * r + a[5]) * q / \
        (((((b[0] * r + b[1]) * r + b[2]) * r + b[3]) * r + b[4]) * r + 1.0)


def chi2_ppf(p: float, dof: float) -> float:
    """Quantile x with P(chi2_dof <= x) = p (``scipy.stats.chi2.ppf(p, dof)``), for 0 <= p <= 1 and
    dof > 0; as in scipy, p = 0 gives 0 and p = 1 gives inf (a gate that never rejects)."""
    p, dof = float(p), float(dof)
    if not (0.0 <= p <= 1.0):
        raise ValueError(f"chi2_ppf: probability must be in [0, 1], got {p!r}")
    if not (dof > 0.0 and math.isfinite(dof)):
        raise ValueError(f"chi2_ppf: degrees of freedom must be > 0, got {dof!r}")
    if p == 0.0 or p == 1.0:
        return 0.0 if p == 0.0 else math.inf
    upper = p >= 0.5                     # solve on the tail that holds the mass: log Q = log(1-p) ...
    log_target = math.log1p(-p) if upper else math.log(p)   # ... or log P = log p

    def residual(x: float) -> tuple[float, float]:
        """(log tail(x) - log target, its derivative in x)."""
        cdf, sf = chi2_cdf_sf(x, dof)
        tail = sf if upper else cdf
        tail = max(tail, _TINY)
        dlog = math.exp(_log_pdf(x, dof)) / tail
        return math.log(tail) - log_target, (-dlog if upper else dlog)

    z = _normal_ppf(p)
    s = 2.0 / (9.0 * dof)
    x = dof * max(1.0 - s + z * math.sqrt(s), 0.05) ** 3
    lo, hi = 0.0, math.inf               # bracket: residual has the sign of 'upper' below x ...
    for _ in range(200):
        f, df = residual(x)
        if f == 0.0:
            return x
        if (f > 0.0) == upper:           # x is below the quantile
            lo = x
        else:
            hi = x
        step = f / df if df != 0.0 else 0.0
        x_new = x - step
        if not (lo < x_new < hi) or step == 0.0:     # Newton left the bracket: bisect (or expand)
            x_new = 0.5 * (lo + hi) if math.isfinite(hi) else 2.0 * x + 1.0
        if abs(x_new - x) <= 4e-16 * x:
            return x_new
        x = x_new
    return x


__all__ = ["chi2_ppf", "chi2_cdf_sf"]
