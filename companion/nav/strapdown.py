"""ECEF strapdown mechanization (seed 004 eqs 5-7) from angle and velocity increments.

One step over an IMU interval tau, from (r, v, C_b_e) at its start:

* attitude   C(+) = R_e(tau) C(-) R(dtheta)       -- R(dtheta) by Rodrigues (eq 6); R_e(tau) is the
  exact earth-rotation transform, whose first order is eq 5's ``- Omega_e C(-) tau``;
* velocity   v(+) = v(-) + C(-) (dv + dtheta x dv / 2) + (g(r(-)) - 2 Omega_e v(-)) tau   (eq 7, with
  the rotation compensation of the velocity increment);
* position   r(+) = r(-) + (v(-) + v(+)) tau / 2.

:func:`invert_step` solves the same equations for the increments that take one state to the
next; the simulator uses it so that an error-free IMU reproduces the truth to rounding error.
"""
from __future__ import annotations

import functools
import math

import numpy as np

from .earth import OMEGA_IE_RADPS, gravity_ecef, skew


@functools.lru_cache(maxsize=8)
def earth_rotation_transform(tau_s: float) -> np.ndarray:
    """Maps ECEF coordinates at t to ECEF coordinates at t + tau (frame turned by omega*tau).
    Cached: an IMU runs at a handful of fixed intervals.  The returned array must not be modified."""
    a = OMEGA_IE_RADPS * tau_s
    c, s = math.cos(a), math.sin(a)
    out = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    out.flags.writeable = False
    return out


def _rodrigues(x: float, y: float, z: float) -> np.ndarray:
    a2 = x * x + y * y + z * z
    if a2 < 1e-12:  # series to 4th order: exact to rounding for IMU-size increments
        s = 1.0 - a2 / 6.0
        c = 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        s = math.sin(a) / a
        c = (1.0 - math.cos(a)) / a2
    # I + s K + c K^2, written out (K = skew(dtheta)); cheaper than building K and K @ K
    return np.array([
        [1.0 - c * (y * y + z * z), -s * z + c * x * y, s * y + c * x * z],
        [s * z + c * x * y, 1.0 - c * (x * x + z * z), -s * x + c * y * z],
        [-s * y + c * x * z, s * x + c * y * z, 1.0 - c * (x * x + y * y)],
    ])


def strapdown_step(r_e: np.ndarray, v_e: np.ndarray, C_b_e: np.ndarray,
                   dtheta_b, dv_b, tau_s: float, g_e: np.ndarray | None = None):
    """Advance (r_e, v_e, C_b_e) over one IMU interval.  Returns new arrays (inputs untouched).

    ``dtheta_b`` and ``dv_b`` (any 3-sequence) must already be corrected for the estimated sensor
    biases.  ``g_e`` may be passed when the caller already has gravity at ``r_e``.
    """
    r_new, v_new, C_new, _ = strapdown_step_with_force(r_e, v_e, C_b_e, dtheta_b, dv_b, tau_s, g_e)
    return r_new, v_new, C_new


def strapdown_step_with_force(r_e, v_e, C_b_e, dtheta_b, dv_b, tau_s: float, g_e=None):
    """:func:`strapdown_step` that also returns the specific-force velocity increment in ECEF
    (C_b_e (dv + dtheta x dv / 2)), which the covariance propagation needs as f_e * tau."""
    if g_e is None:
        g_e = gravity_ecef(r_e)
    ax, ay, az = dtheta_b
    bx, by, bz = dv_b
    dv_comp = np.array([bx + 0.5 * (ay * bz - az * by),
                        by + 0.5 * (az * bx - ax * bz),
                        bz + 0.5 * (ax * by - ay * bx)])
    w2t = 2.0 * OMEGA_IE_RADPS * tau_s
    # gravity and Coriolis (-2 Omega x v) over the interval
    gc = np.array([g_e[0] * tau_s + w2t * v_e[1], g_e[1] * tau_s - w2t * v_e[0], g_e[2] * tau_s])
    dv_e = C_b_e @ dv_comp
    v_new = v_e + dv_e + gc
    r_new = r_e + (v_e + v_new) * (0.5 * tau_s)
    C_new = earth_rotation_transform(tau_s) @ (C_b_e @ _rodrigues(ax, ay, az))
    return r_new, v_new, C_new, dv_e


def _log_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix (inverse of Rodrigues), for angles well below pi."""
    cos_a = max(-1.0, min(1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0)))
    vee = 0.5 * np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin_a = float(np.linalg.norm(vee))
    a = math.atan2(sin_a, cos_a)
    if a < 1e-6:
        return vee * (1.0 + a * a / 6.0)
    return vee * (a / sin_a)


def invert_step(r0_e, v0_e, C0_b_e, v1_e, C1_b_e, tau_s: float):
    """Increments (dtheta_b, dv_b) that make :func:`strapdown_step` go from state 0 to state 1.

    Position is not an input: the mechanization's trapezoid rule fixes r1 from v0 and v1.
    """
    R = C0_b_e.T @ earth_rotation_transform(tau_s).T @ C1_b_e
    dtheta = _log_rotation(R)
    w = OMEGA_IE_RADPS
    coriolis = np.array([2.0 * w * v0_e[1], -2.0 * w * v0_e[0], 0.0])   # -2 Omega x v
    rhs = C0_b_e.T @ (v1_e - v0_e - (gravity_ecef(r0_e) + coriolis) * tau_s)
    dv = np.linalg.solve(np.eye(3) + 0.5 * skew(dtheta), rhs)
    return dtheta, dv
