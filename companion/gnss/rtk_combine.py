"""Forward and backward post-processed RTK solutions combined per epoch (RTKLIB's 'combined'
solution type): the backward pass has converged ambiguities where the forward one starts or
restarts after an outage, and two independent integer searches that fix the same epoch check each
other.

The two passes use the same observations at an epoch (each pass differs only in the ambiguities
it carries), so their positions are strongly correlated: they are compared, and one is chosen
(or the two averaged when both fixed alike), never fused as independent estimates, which would
halve a covariance that no new information backs.

* both fixed and consistent (the difference within the 0.999 chi-square bound of 3 dof against
  the sum of their covariances): fixed, the mean of the two, the mean covariance;
* one fixed and consistent with the other's float: fixed, that fix;
* a fix inconsistent with the other pass: float (counted); two fixes apart give their midpoint with
  a covariance that covers both, a fix against a float gives the float;
* both float: the one with the smaller covariance (the pass that has converged longer).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from .rtk import Q_FIX, Q_FLOAT, RtkSolution

#: the 0.999 quantile of chi-square with 3 degrees of freedom
AGREE_CHI2_3DOF = 16.27


def _chi2(a: RtkSolution, b: RtkSolution) -> float:
    d = a.r_e - b.r_e
    try:
        return float(d @ np.linalg.solve(a.cov_e + b.cov_e, d))
    except np.linalg.LinAlgError:
        return float("inf")


def combine(forward: list[RtkSolution], backward: list[RtkSolution], counters: dict) -> list[RtkSolution]:
    """One solution per epoch of either pass, in time order; ``counters`` gets the decisions."""
    def count(key: str) -> None:
        counters[key] = counters.get(key, 0) + 1

    fwd = {round(s.t_gps, 3): s for s in forward}
    bwd = {round(s.t_gps, 3): s for s in backward}
    out = []
    for t in sorted(fwd.keys() | bwd.keys()):
        f, b = fwd.get(t), bwd.get(t)
        if f is None or b is None:
            count("combined: one pass only")
            out.append(f if f is not None else b)
            continue
        agree = _chi2(f, b) <= AGREE_CHI2_3DOF
        fixed = [s for s in (f, b) if s.quality == Q_FIX]
        if len(fixed) == 2 and agree:
            count("combined: both passes fixed")
            out.append(dataclasses.replace(f, r_e=0.5 * (f.r_e + b.r_e), cov_e=0.5 * (f.cov_e + b.cov_e),
                                           ratio=min(f.ratio, b.ratio), n_fixed=max(f.n_fixed, b.n_fixed),
                                           success_rate=min(f.success_rate, b.success_rate)))
        elif len(fixed) == 2:
            count("combined: the two passes' fixes disagree (float)")
            d = f.r_e - b.r_e
            out.append(dataclasses.replace(f, r_e=0.5 * (f.r_e + b.r_e),
                                           cov_e=0.5 * (f.cov_e + b.cov_e) + 0.25 * np.outer(d, d),
                                           quality=Q_FLOAT, ratio=0.0, n_fixed=0))
        elif len(fixed) == 1 and agree:
            count("combined: one pass fixed")
            out.append(fixed[0])
        elif len(fixed) == 1:
            count("combined: a fix disagrees with the other pass's float (float)")
            out.append(b if fixed[0] is f else f)
        else:
            count("combined: both passes float")
            out.append(f if np.trace(f.cov_e) <= np.trace(b.cov_e) else b)
    return out


__all__ = ["combine", "AGREE_CHI2_3DOF"]
