"""Slowly varying pseudorange errors: what averaging epochs cannot remove.

Orbit and satellite-clock errors, the residual of the ionosphere and troposphere models and the
decorrelation of DGPS corrections change over minutes to hours (``gnss.prepare`` reports their part
of each pseudorange sigma as ``sigma_pseudorange_slow_m``).  Weighting them as white noise lets the
filter average them down epoch after epoch: on the simulated UAV flight its position NEES grew from
2 to 14 (3 expected) over five minutes, even with their variance inflated by the Gauss-Markov rule
for a correlation time of 900 s (which also cost accuracy: 2.5 m instead of 2.0 m horizontal RMS in
tight coupling).  Over a window shorter than its correlation time the error is a bias, and the
filter's memory grows with every epoch it carries the INS through.

The floor here says what a bias allows: the position cannot be known better than a single epoch of
the slow errors alone would give it, ``(H' R_slow^-1 H)^-1`` over position and receiver clock (a
common error of all satellites goes into the clock, as it should).  Adding the missing part to the
position block keeps P positive definite (the sum of two PSD matrices).  The engine applies it to
standalone pseudoranges, whose slow errors are metres; DGPS removes most of them.
"""
from __future__ import annotations

import numpy as np


def slow_error_position_floor(r_ant_e: np.ndarray, r_sat_e: np.ndarray, sigma_slow_m: np.ndarray) -> np.ndarray | None:
    """ECEF position covariance (3x3, m^2) from the slow pseudorange errors of one epoch alone,
    or None when they do not determine it (fewer than 4 satellites, or no slow error modelled)."""
    ok = np.isfinite(sigma_slow_m) & (sigma_slow_m > 0.0)
    if int(np.count_nonzero(ok)) < 4:
        return None
    d = r_sat_e[ok] - r_ant_e
    u = d / np.linalg.norm(d, axis=1)[:, None]
    H = np.hstack([-u, np.ones((len(u), 1))])
    w = 1.0 / sigma_slow_m[ok] ** 2
    N = H.T @ (H * w[:, None])
    try:
        cov = np.linalg.inv(N)
    except np.linalg.LinAlgError:
        return None
    if not np.all(np.isfinite(cov)):
        return None
    return cov[:3, :3]


def raise_to_floor(P: np.ndarray, idx: slice, floor: np.ndarray) -> bool:
    """Add to the block ``P[idx, idx]`` the positive part of ``floor - P[idx, idx]`` (in place).
    Returns whether anything was added."""
    D = floor - P[idx, idx]
    D = 0.5 * (D + D.T)
    vals, vecs = np.linalg.eigh(D)
    if vals[-1] <= 0.0:
        return False
    pos = np.clip(vals, 0.0, None)
    P[idx, idx] += (vecs * pos) @ vecs.T
    return True
