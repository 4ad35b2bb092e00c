"""Horizontal protection level (HPL, m): a bound that the true horizontal position error stays
inside with a stated probability, computed with every solution.

Two parts; the HPL is the larger of them.

**Fault-free (covariance) part.**  With a zero-mean Gaussian horizontal error of covariance
``P_h`` (2x2, north/east) and ``sigma_major^2`` its largest eigenvalue (the error ellipse's major
axis), ``P(|e_h| > K sigma_major) <= P(chi2_2 > K^2) = exp(-K^2 / 2)``: the circular Gaussian of
variance ``sigma_major^2`` on both axes dominates every ellipse inside it, and its squared radius
over sigma^2 is chi-square with 2 degrees of freedom (the Rayleigh bound).  So
``HPL_ff = K(p) sigma_major`` with ``K(p) = sqrt(chi2_ppf(1 - p, 2))`` holds with probability at
least ``1 - p`` (``p`` = ``integrity_risk``; 1e-5 gives K = 4.80, 1e-7 gives 5.68).  It is exact
for a circular error and conservative for an elongated one.  While coasting (no GNSS) it is
evaluated on the propagated covariance, so it grows with it.

**Fault (solution-separation) part** (Brenner 1996, *Integrated GPS/inertial fault detection
availability*; Blanch et al. 2012, ARAIM), on the pseudorange rows the filter fused at the last
epoch, with the prior covariance ``P`` they were gated against.  For the all-in-view update and
the update that leaves satellite ``i`` out, with ``S = H P H^T + R``, ``L = S^-1`` and
``M = C_h P H^T`` (``C_h`` picks north/east position from the error state):

* the inverse of ``S`` without row and column ``i``, embedded back, is ``L - l_i l_i^T / L_ii``
  (``l_i`` = column i of L), so the separation of the two horizontal estimates is
  ``Delta_i = u_i (l_i^T z) / L_ii`` with ``u_i = M l_i``, and its covariance (the subset's
  covariance minus the all-in-view one, Brenner's result for Kalman filters) is the rank-one
  ``D_i = u_i u_i^T / L_ii``.  Cost: one m x m inverse per epoch (m ~ 10), nothing per subset.
* The normalised separation ``|l_i^T z| / sqrt(L_ii)`` is the row's leave-one-out residual,
  the statistic the filter's gate (:meth:`~companion.nav.filter.ErrorStateKalmanFilter.gate`)
  already tests at ``K_det = sqrt(chi2_ppf(gate_probability, 1))``: a satellite bias that passes
  the gate moves the all-in-view horizontal solution by at most ``T_i = K_det |u_i| / sqrt(L_ii)``.
* ``HPL_i = T_i + K_md sigma_major(P_h + D_i)``: the largest undetected separation plus the
  subset solution's own fault-free bound, with ``K_md = K(missed_detection)``.
  ``HPL_ss = max_i HPL_i``.  Between epochs ``T_i`` and ``D_i`` are held and ``P_h`` is the
  current (propagated) one.

Assumptions: errors Gaussian and the filter's covariance honest (what the integrity monitor,
:mod:`.integrity`, watches); at most one faulty satellite at a time; the separation is taken on
the pseudorange rows alone against the prior covariance (the engine fuses TDCP in the same
update; carrier rows constrain the velocity, not the absolute position); the held ``D_i`` is not
propagated (the prior's growth is in ``P_h``).  Loose coupling (receiver fixes) has no
pseudorange rows: the HPL is the covariance part only.  This is not a certified integrity
algorithm: it states what the filter's own model implies, nothing about faults outside it
(a wrong initial heading, a contradicting IMU: those are the divergence monitor's job).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .chi2 import chi2_ppf
from .filter import spd_inverse


def k_factor_h(probability: float) -> float:
    """K such that a 2-D zero-mean Gaussian error exceeds ``K * sigma_major`` with probability at
    most ``probability`` (Rayleigh / chi-square with 2 degrees of freedom)."""
    p = float(probability)
    if not 0.0 < p < 1.0:
        raise ValueError(f"probability must be in (0, 1), got {p!r}")
    return math.sqrt(chi2_ppf(1.0 - p, 2))


def sigma_major_m(P_h: np.ndarray) -> float:
    """Square root of the largest eigenvalue of a 2x2 covariance (the error ellipse's semi-major axis)."""
    a, b, c = float(P_h[0, 0]), 0.5 * (float(P_h[0, 1]) + float(P_h[1, 0])), float(P_h[1, 1])
    lam = 0.5 * (a + c) + math.hypot(0.5 * (a - c), b)
    return math.sqrt(lam) if lam > 0.0 else 0.0


def sigma_major_batch_m(P_h: np.ndarray) -> np.ndarray:
    """:func:`sigma_major_m` of each 2x2 covariance of a stack (m, 2, 2), the same arithmetic."""
    a, c = P_h[:, 0, 0], P_h[:, 1, 1]
    b = 0.5 * (P_h[:, 0, 1] + P_h[:, 1, 0])
    lam = 0.5 * (a + c) + np.hypot(0.5 * (a - c), b)
    return np.sqrt(np.maximum(lam, 0.0))


@dataclass
class SolutionSeparation:
    """Solution separation of one epoch's rows (see the module docstring), per row."""

    labels: list
    separation_m: np.ndarray        # |Delta_i|: all-in-view minus leave-i-out, horizontal, m
    sigma_separation_m: np.ndarray  # its standard deviation along u_i, m
    threshold_m: np.ndarray         # T_i = k_detect * sigma_separation
    test_ratio: np.ndarray          # separation / threshold: > 1 means satellite i is detected
    D_h: np.ndarray                 # (m, 2, 2): covariance of the separation (subset minus all-in-view)
    P_h_post: np.ndarray            # (2, 2): all-in-view horizontal covariance after the update

    @property
    def detected(self) -> bool:
        return bool(len(self.test_ratio)) and bool(np.max(self.test_ratio) > 1.0)

    @property
    def worst(self) -> int | None:
        return int(np.argmax(self.test_ratio)) if len(self.test_ratio) else None


def solution_separation(H: np.ndarray, z: np.ndarray, r_var: np.ndarray, P: np.ndarray, C_h: np.ndarray,
                        k_detect: float, labels=None) -> SolutionSeparation:
    """Leave-one-out solution separation of a Kalman update with rows ``H`` (m x n), innovations
    ``z``, uncorrelated noise variances ``r_var``, prior covariance ``P`` (n x n); ``C_h`` (2 x n)
    maps the error state onto horizontal (north, east) position."""
    H = np.asarray(H, float)
    z = np.asarray(z, float)
    m = len(z)
    PHt = P @ H.T
    S = H @ PHt
    S.flat[::len(S) + 1] += np.asarray(r_var, float)
    L = spd_inverse(S)
    L = 0.5 * (L + L.T)
    M = C_h @ PHt                          # (2, m)
    U = M @ L                              # column i: u_i = M l_i
    d = L.diagonal().copy()
    w = L @ z                              # l_i^T z
    ok = d > 0.0
    all_ok = bool(ok.all())
    d_safe = d if all_ok else np.where(ok, d, 1.0)
    u0, u1 = U[0], U[1]
    u_norm = np.hypot(u0, u1)
    inv_sqrt_d = 1.0 / np.sqrt(d_safe)
    abs_w = np.abs(w)
    sig = u_norm * inv_sqrt_d
    sep = sig * (abs_w * inv_sqrt_d)       # |u_i| |w_i| / d_i
    ratio = abs_w * inv_sqrt_d / k_detect
    D = np.empty((m, 2, 2))                # u_i u_i^T / d_i
    D[:, 0, 0] = u0 * u0 / d_safe
    D[:, 0, 1] = D[:, 1, 0] = u0 * u1 / d_safe
    D[:, 1, 1] = u1 * u1 / d_safe
    if not all_ok:                         # a row the others fully determine: no separation
        sep, sig, ratio = np.where(ok, sep, 0.0), np.where(ok, sig, 0.0), np.where(ok, ratio, 0.0)
        D[~ok] = 0.0
    thr = k_detect * sig
    P_h_post = C_h @ P @ C_h.T - U @ M.T   # M L M^T
    return SolutionSeparation(list(labels) if labels is not None else [str(i) for i in range(m)],
                              sep, sig, thr, ratio, D, 0.5 * (P_h_post + P_h_post.T))


@dataclass
class ProtectionLevels:
    """The HPL of one solution and its parts (m)."""

    hpl_m: float
    hpl_cov_m: float
    hpl_ss_m: float = math.nan           # NaN: no pseudorange epoch since the (re)initialisation
    ss_rows: int = 0
    ss_t_gps: float = math.nan           # GPS time of the epoch the separation part comes from
    ss_max_ratio: float = math.nan       # largest separation test ratio of that epoch


class ProtectionLevel:
    """Holds the last epoch's solution-separation terms; :meth:`levels` gives the HPL for the
    current horizontal covariance."""

    def __init__(self, integrity_risk: float = 1e-5, missed_detection: float = 1e-3, k_detect: float = 3.29):
        self.k_ff = k_factor_h(integrity_risk)
        self.k_md = k_factor_h(missed_detection)
        self.k_detect = float(k_detect)
        self.last: SolutionSeparation | None = None
        self._t_gps = math.nan

    def reset(self) -> None:
        """After a re-initialisation the old epoch says nothing about the new state."""
        self.last = None
        self._t_gps = math.nan

    def epoch(self, H, z, r_var, P, C_h, t_gps: float, labels=None) -> SolutionSeparation:
        """The fused pseudorange rows of one epoch, against the prior covariance ``P``."""
        self.last = solution_separation(H, z, r_var, P, C_h, self.k_detect, labels)
        self._t_gps = float(t_gps)
        return self.last

    def levels(self, P_h: np.ndarray) -> ProtectionLevels:
        """HPL for the current horizontal (north, east) covariance ``P_h``."""
        cov = self.k_ff * sigma_major_m(P_h)
        ss = self.last
        if ss is None or not len(ss.threshold_m):
            return ProtectionLevels(cov, cov)
        hpl_ss = float(np.max(ss.threshold_m + self.k_md * sigma_major_batch_m(P_h + ss.D_h)))
        return ProtectionLevels(max(cov, hpl_ss), cov, hpl_ss, len(ss.threshold_m), self._t_gps,
                                float(np.max(ss.test_ratio)))


__all__ = [
    "ProtectionLevel",
    "ProtectionLevels",
    "SolutionSeparation",
    "k_factor_h",
    "sigma_major_m",
    "solution_separation",
]
