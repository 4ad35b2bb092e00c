"""Free-inertial error propagation of the mechanization, and the analytic Schuler solution.

Used by the INS error-analysis tool (``python -m sitl ins-errors``) and the tests: a stationary
IMU at a chosen point, error-free increments from :func:`~.strapdown.invert_step`, initial
errors and constant sensor biases injected, the mechanization run free-inertially.  The vertical
channel is unstable in any free INS; like every real system (baro, or the analytic solution's own
assumption) we hold it: after each step the height error and vertical velocity are removed.

Analytic solution (seed 004 eqs 1-2; level errors, earth-rate coupling neglected), nu = sqrt(g/R):
    dV_e(t) = -Phi_y(0) R sin(nu t) + dV_x(0) cos(nu t) - xi_y R (1 - cos(nu t)) + B_x sin(nu t)/nu
    dV_n(t) = -Phi_x(0) R sin(nu t) + dV_y(0) cos(nu t) + xi_x R (1 - cos(nu t)) + B_y sin(nu t)/nu
Seed 004 writes it with its own platform's axis pairing; :func:`schuler_velocity_error` restates
it for NED axes with this project's attitude-error convention (same terms, signs derived).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .earth import (C_n_e, geodetic_to_ecef, normal_gravity_mps2,
                    radii_of_curvature, rotation_from_rotvec)
from .strapdown import invert_step, strapdown_step


@dataclass
class FreeInertialCase:
    name: str
    lat_deg: float = 0.0
    lon_deg: float = 0.0
    h_m: float = 0.0
    dv0_n_mps: tuple = (0.0, 0.0, 0.0)          # initial velocity error, NED
    tilt0_n_rad: tuple = (0.0, 0.0, 0.0)        # initial attitude error about N, E, D
    accel_bias_n_mps2: tuple = (0.0, 0.0, 0.0)  # accelerometer bias expressed in NED (body = NED here)
    gyro_bias_n_radps: tuple = (0.0, 0.0, 0.0)  # gyro drift expressed in NED
    hours: float = 2.0
    rate_hz: float = 10.0


def schuler_frequencies(lat_rad: float, h_m: float = 0.0) -> tuple[float, float]:
    """Schuler angular frequencies (north channel, east channel), rad/s.

    nu = sqrt(g/R), with R the meridian radius M for north errors and the prime-vertical radius N
    for east errors (they differ by 0.7 % at the equator, enough to matter over two hours)."""
    m, n = radii_of_curvature(lat_rad)
    g = normal_gravity_mps2(lat_rad, h_m)
    return math.sqrt(g / (m + h_m)), math.sqrt(g / (n + h_m))


def schuler_velocity_error(case: FreeInertialCase, t_s: np.ndarray) -> np.ndarray:
    """Analytic (north, east) velocity error, estimate minus truth, of a stationary INS.

    Derived for NED axes with C(est) = (I + [psi x]) C(true): at rest the computed specific force
    errs by psi x f = (-g psi_e, g psi_n, 0), gravity at the wrong position restores with nu^2,
    and a gyro drift w makes psi grow as w t.  Valid where the earth-rate coupling of the tilts
    vanishes (tilt and drift about north at the equator) or for times short against a day.
    """
    lat = math.radians(case.lat_deg)
    nu_n, nu_e = schuler_frequencies(lat, case.h_m)
    g = normal_gravity_mps2(lat, case.h_m)
    dvn0, dve0, _ = case.dv0_n_mps
    phi_n, phi_e, _ = case.tilt0_n_rad
    bn, be, _ = case.accel_bias_n_mps2
    wn, we, _ = case.gyro_bias_n_radps
    sn, cn = np.sin(nu_n * t_s), np.cos(nu_n * t_s)
    se, ce = np.sin(nu_e * t_s), np.cos(nu_e * t_s)
    dvn = dvn0 * cn + (bn - g * phi_e) * sn / nu_n - g * we * (1.0 - cn) / nu_n ** 2
    dve = dve0 * ce + (be + g * phi_n) * se / nu_e + g * wn * (1.0 - ce) / nu_e ** 2
    return np.column_stack([dvn, dve])


def run_free_inertial(case: FreeInertialCase):
    """Integrate the mechanization from the case's initial errors.  Returns (t_s, dv_ne (N,2), dpos_ne (N,2))."""
    lat, lon = math.radians(case.lat_deg), math.radians(case.lon_deg)
    r_true = geodetic_to_ecef(lat, lon, case.h_m)
    Cne = C_n_e(lat, lon)
    C_true = Cne  # body axes aligned with NED
    v0 = np.zeros(3)
    tau = 1.0 / case.rate_hz
    # the stationary truth over one interval: the body stays fixed in ECEF
    dtheta_true, dv_true = invert_step(r_true, v0, C_true, v0, C_true, tau)
    dtheta = dtheta_true + np.array(case.gyro_bias_n_radps) * tau
    dv = dv_true + np.array(case.accel_bias_n_mps2) * tau
    # initial errors (psi about ECEF axes = Cne @ tilt in NED)
    C = rotation_from_rotvec(Cne @ np.array(case.tilt0_n_rad)) @ C_true
    v = Cne @ np.array(case.dv0_n_mps, float)
    r = r_true.copy()
    up_e = -Cne[:, 2]
    n_steps = int(round(case.hours * 3600.0 * case.rate_hz))
    decim = max(1, int(case.rate_hz))
    ts, dvs, dps = [0.0], [Cne.T @ v], [np.zeros(3)]
    for k in range(1, n_steps + 1):
        r, v, C = strapdown_step(r, v, C, dtheta, dv, tau)
        # hold the vertical channel (as an altimeter would)
        dr = r - r_true
        r = r - up_e * float(dr @ up_e)
        v = v - up_e * float(v @ up_e)
        if k % decim == 0:
            ts.append(k * tau)
            dvs.append(Cne.T @ v)
            dps.append(Cne.T @ (r - r_true))
    t = np.array(ts)
    dv_n = np.array(dvs)
    dp_n = np.array(dps)
    return t, dv_n[:, :2], dp_n[:, :2]


def fit_sinusoid_period(t_s: np.ndarray, y: np.ndarray, period_guess_s: float) -> tuple[float, float]:
    """Least-squares fit of y = a cos(w t) + b sin(w t) + c over w: returns (period s, amplitude)."""
    from scipy.optimize import least_squares

    def resid(p):
        w = p[0]
        A = np.column_stack([np.cos(w * t_s), np.sin(w * t_s), np.ones_like(t_s)])
        coef, *_ = np.linalg.lstsq(A, y, rcond=None)
        return A @ coef - y

    w0 = 2 * math.pi / period_guess_s
    sol = least_squares(resid, [w0], x_scale=[w0 * 0.1])
    w = sol.x[0]
    A = np.column_stack([np.cos(w * t_s), np.sin(w * t_s), np.ones_like(t_s)])
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    return 2 * math.pi / w, math.hypot(coef[0], coef[1])
