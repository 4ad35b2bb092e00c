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

from . import imu_kernel
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


def strapdown_step(r_e: np.ndarray, v_e: np.ndarray, C_b_e: np.ndarray,
                   dtheta_b, dv_b, tau_s: float, g_e: np.ndarray | None = None):
    """Advance (r_e, v_e, C_b_e) over one IMU interval.  Returns new arrays (inputs untouched).

    ``dtheta_b`` and ``dv_b`` (any 3-sequence) must already be corrected for the estimated sensor
    biases.  ``g_e`` may be passed when the caller already has gravity at ``r_e``.
    """
    r_new, v_new, C_new, _ = strapdown_step_with_force(r_e, v_e, C_b_e, dtheta_b, dv_b, tau_s, g_e)
    return r_new, v_new, C_new


_EARTH_TURN = {}   # tau -> (cos, sin) of the earth's rotation over the interval


def strapdown_step_with_force(r_e, v_e, C_b_e, dtheta_b, dv_b, tau_s: float, g_e=None):
    """:func:`strapdown_step` that also returns the specific-force velocity increment in ECEF
    (C_b_e (dv + dtheta x dv / 2)) as a tuple, which the covariance propagation needs as f_e * tau.

    Runs the compiled kernel (:mod:`.imu_kernel`, the same arithmetic in the same order) when numba
    is there, else :func:`strapdown_step_with_force_reference`.
    """
    k = imu_kernel.compiled()
    if k is None:
        return strapdown_step_with_force_reference(r_e, v_e, C_b_e, dtheta_b, dv_b, tau_s, g_e)
    if g_e is None:
        g_e = gravity_ecef(r_e)
    ax, ay, az = dtheta_b
    bx, by, bz = dv_b
    gx, gy, gz = g_e.tolist() if hasattr(g_e, "tolist") else g_e
    turn = _EARTH_TURN.get(tau_s)
    if turn is None:
        ang = OMEGA_IE_RADPS * tau_s
        turn = _EARTH_TURN[tau_s] = (math.cos(ang), math.sin(ang))
    r_new, v_new, C_new = np.empty(3), np.empty(3), np.empty((3, 3))
    dv_e = k.strapdown(r_e, v_e, C_b_e, ax, ay, az, bx, by, bz, tau_s, gx, gy, gz, turn[0], turn[1],
                       OMEGA_IE_RADPS, r_new, v_new, C_new)
    return r_new, v_new, C_new, dv_e


def strapdown_step_with_force_reference(r_e, v_e, C_b_e, dtheta_b, dv_b, tau_s: float, g_e=None):
    """The readable reference of :func:`strapdown_step_with_force` (and its fallback without numba).

    Written out in float arithmetic: at IMU rate the 3x3 work is cheaper in plain Python than
    through numpy's per-call overhead (about half the time); the equations are those of the
    module docstring, term for term.
    """
    if g_e is None:
        g_e = gravity_ecef(r_e)
    ax, ay, az = dtheta_b
    bx, by, bz = dv_b
    # velocity increment with rotation compensation, to ECEF
    cx = bx + 0.5 * (ay * bz - az * by)
    cy = by + 0.5 * (az * bx - ax * bz)
    cz = bz + 0.5 * (ax * by - ay * bx)
    (c00, c01, c02), (c10, c11, c12), (c20, c21, c22) = C_b_e.tolist()
    dvx = c00 * cx + c01 * cy + c02 * cz
    dvy = c10 * cx + c11 * cy + c12 * cz
    dvz = c20 * cx + c21 * cy + c22 * cz
    vx, vy, vz = v_e.tolist()
    gx, gy, gz = g_e.tolist() if hasattr(g_e, "tolist") else g_e
    w2t = 2.0 * OMEGA_IE_RADPS * tau_s
    nvx = vx + dvx + gx * tau_s + w2t * vy      # gravity and Coriolis (-2 Omega x v)
    nvy = vy + dvy + gy * tau_s - w2t * vx
    nvz = vz + dvz + gz * tau_s
    rx, ry, rz = r_e.tolist()
    h = 0.5 * tau_s
    r_new = np.array((rx + (vx + nvx) * h, ry + (vy + nvy) * h, rz + (vz + nvz) * h))
    # Rodrigues rotation of the body frame over the interval (seed 004 eq 6)
    a2 = ax * ax + ay * ay + az * az
    if a2 < 1e-12:
        sa = 1.0 - a2 / 6.0
        ca = 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        sa = math.sin(a) / a
        ca = (1.0 - math.cos(a)) / a2
    R00 = 1.0 - ca * (ay * ay + az * az)
    R11 = 1.0 - ca * (ax * ax + az * az)
    R22 = 1.0 - ca * (ax * ax + ay * ay)
    R01 = -sa * az + ca * ax * ay
    R10 = sa * az + ca * ax * ay
    R02 = sa * ay + ca * ax * az
    R20 = -sa * ay + ca * ax * az
    R12 = -sa * ax + ca * ay * az
    R21 = sa * ax + ca * ay * az
    m00 = c00 * R00 + c01 * R10 + c02 * R20
    m01 = c00 * R01 + c01 * R11 + c02 * R21
    m02 = c00 * R02 + c01 * R12 + c02 * R22
    m10 = c10 * R00 + c11 * R10 + c12 * R20
    m11 = c10 * R01 + c11 * R11 + c12 * R21
    m12 = c10 * R02 + c11 * R12 + c12 * R22
    m20 = c20 * R00 + c21 * R10 + c22 * R20
    m21 = c20 * R01 + c21 * R11 + c22 * R21
    m22 = c20 * R02 + c21 * R12 + c22 * R22
    # the ECEF frame turns by omega*tau about z while the body turns (exact, not first order)
    turn = _EARTH_TURN.get(tau_s)
    if turn is None:
        ang = OMEGA_IE_RADPS * tau_s
        turn = _EARTH_TURN[tau_s] = (math.cos(ang), math.sin(ang))
    co, si = turn
    C_new = np.array(((co * m00 + si * m10, co * m01 + si * m11, co * m02 + si * m12),
                      (co * m10 - si * m00, co * m11 - si * m01, co * m12 - si * m02),
                      (m20, m21, m22)))
    return r_new, np.array((nvx, nvy, nvz)), C_new, (dvx, dvy, dvz)


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
