"""Standalone atmosphere models: Klobuchar ionosphere, Saastamoinen troposphere, iono-free combination.

Inputs in radians, metres and continuous GPS seconds; outputs are slant delays in metres
(positive: the pseudorange is longer than the geometric range).
"""
from __future__ import annotations

import math

import numpy as np

from ..messages import GPS_L1_HZ, SECONDS_PER_WEEK, SPEED_OF_LIGHT_MPS

#: standard atmosphere at sea level (RTKLIB / Saastamoinen conventions)
STD_PRESSURE_HPA = 1013.25
STD_TEMPERATURE_K = 288.15
STD_RELATIVE_HUMIDITY = 0.7
#: Klobuchar coefficients used when a file broadcasts none (RTCM streams carry none): RTKLIB's
#: ``ion_default`` (GPS broadcast of 2004-01-01), so both tools see the same model
KLOBUCHAR_DEFAULT = (np.array([0.1118e-07, -0.7451e-08, -0.5961e-07, 0.1192e-06]),
                     np.array([0.1167e+06, -0.2294e+06, -0.1311e+06, 0.1049e+07]))


def klobuchar_delay_m(t_gps: float, lat_rad: float, lon_rad: float, azimuth_rad: float,
                      elevation_rad: float, alpha, beta) -> float:
    """Slant L1 ionospheric group delay in metres (IS-GPS-200 20.3.3.5.2.5).

    ``alpha``/``beta``: the broadcast coefficients (alpha_n s/semicircle^n, beta_n s/semicircle^n).
    For another frequency f scale by (f_L1/f)^2.
    """
    e_sc = max(elevation_rad, 0.0) / math.pi          # elevation, semicircles
    phi_u = lat_rad / math.pi
    lam_u = lon_rad / math.pi
    psi = 0.0137 / (e_sc + 0.11) - 0.022               # earth-centred angle, semicircles
    phi_i = phi_u + psi * math.cos(azimuth_rad)
    phi_i = min(max(phi_i, -0.416), 0.416)
    lam_i = lam_u + psi * math.sin(azimuth_rad) / math.cos(phi_i * math.pi)
    phi_m = phi_i + 0.064 * math.cos((lam_i - 1.617) * math.pi)
    tow = t_gps % SECONDS_PER_WEEK
    t_local = (4.32e4 * lam_i + tow) % 86400.0
    f = 1.0 + 16.0 * (0.53 - e_sc) ** 3
    amp = alpha[0] + phi_m * (alpha[1] + phi_m * (alpha[2] + phi_m * alpha[3]))
    per = beta[0] + phi_m * (beta[1] + phi_m * (beta[2] + phi_m * beta[3]))
    amp = max(amp, 0.0)
    per = max(per, 72000.0)
    x = 2.0 * math.pi * (t_local - 50400.0) / per
    if abs(x) < 1.57:
        t_iono = f * (5e-9 + amp * (1.0 - x * x / 2.0 + x ** 4 / 24.0))
    else:
        t_iono = f * 5e-9
    return SPEED_OF_LIGHT_MPS * t_iono


def standard_atmosphere(h_m: float) -> tuple[float, float, float]:
    """(pressure hPa, temperature K, water-vapour partial pressure hPa) at ellipsoidal height h."""
    h = min(max(h_m, -500.0), 11000.0)
    p = STD_PRESSURE_HPA * (1.0 - 2.2557e-5 * h) ** 5.2568
    t = STD_TEMPERATURE_K - 6.5e-3 * h
    tc = t - 273.15
    # Magnus-type saturation pressure (Saastamoinen / RTKLIB form) times relative humidity
    e = STD_RELATIVE_HUMIDITY * 6.108 * math.exp((17.15 * t - 4684.0) / (t - 38.45)) if tc > -80 else 0.0
    return p, t, e


def saastamoinen_zenith_m(lat_rad: float, h_m: float) -> tuple[float, float]:
    """(hydrostatic, wet) zenith delays in metres, Saastamoinen with the standard atmosphere."""
    p, t, e = standard_atmosphere(h_m)
    denom = 1.0 - 0.00266 * math.cos(2.0 * lat_rad) - 0.00028 * max(h_m, 0.0) / 1e3
    zhd = 0.0022768 * p / denom
    zwd = 0.002277 * (1255.0 / t + 0.05) * e
    return zhd, zwd


def tropo_mapping(elevation_rad: float) -> float:
    """Black & Eisner (1984) mapping 1.001/sqrt(0.002001 + sin^2 E): finite at the horizon."""
    s = math.sin(max(elevation_rad, 0.0))
    return 1.001 / math.sqrt(0.002001 + s * s)


def tropo_delay_m(lat_rad: float, h_m: float, elevation_rad: float) -> float:
    """Slant tropospheric delay in metres (Saastamoinen zenith x Black-Eisner mapping)."""
    if h_m < -1000.0 or h_m > 20000.0:
        return 0.0
    zhd, zwd = saastamoinen_zenith_m(lat_rad, h_m)
    return (zhd + zwd) * tropo_mapping(elevation_rad)


def iono_free(p1, p2, f1_hz: float = GPS_L1_HZ, f2_hz: float = 1227.60e6):
    """Ionosphere-free combination (f1^2 x1 - f2^2 x2) / (f1^2 - f2^2) of two ranges (m)."""
    g1, g2 = f1_hz * f1_hz, f2_hz * f2_hz
    return (g1 * np.asarray(p1) - g2 * np.asarray(p2)) / (g1 - g2)


def iono_free_noise_factor(f1_hz: float = GPS_L1_HZ, f2_hz: float = 1227.60e6) -> float:
    """Noise amplification of :func:`iono_free` for equal, independent noise on both inputs (~2.98)."""
    g1, g2 = f1_hz * f1_hz, f2_hz * f2_hz
    return math.hypot(g1, g2) / (g1 - g2)
