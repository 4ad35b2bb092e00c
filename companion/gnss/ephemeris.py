"""Keplerian broadcast ephemerides (GPS IS-GPS-200 20.3.3.4.3, Galileo OS SIS ICD 5.1.1, BeiDou
B1I ICD 5.2.4.12, QZSS IS-QZSS-PNT): satellite position, velocity and clock.

Each system has its own gravitational constant and earth rotation rate in the orbit equations
(RTKLIB's eph2pos does the same); BeiDou GEO satellites (C01-C05, C59-C63) have their node computed
in an inertial frame and rotated by -5 deg about x, then by the earth rotation since toe.

All times are continuous GPS seconds (see :mod:`companion.messages`).  Positions are ECEF (WGS-84)
at the given transmit time, in the ECEF frame *of that same instant*; rotating them into the
frame of the reception time (the Sagnac / earth-rotation correction) is the caller's job, see
:func:`rotate_to_reception_frame`.
"""
from __future__ import annotations

import math

import numpy as np

from ..messages import SECONDS_PER_WEEK, SPEED_OF_LIGHT_MPS, GpsEphemeris
from ..nav.earth import GM_M3PS2, OMEGA_IE_RADPS
from . import glonass

# Relativistic clock term constant F = -2 sqrt(mu) / c^2  (IS-GPS-200 20.3.3.3.3.1)
REL_F = -4.442807633e-10
# (GM m^3/s^2, earth rotation rad/s) of each system's orbit equations
_GM_OMEGA = {
    "G": (GM_M3PS2, OMEGA_IE_RADPS),
    "J": (GM_M3PS2, OMEGA_IE_RADPS),
    "E": (3.986004418e14, 7.2921151467e-5),
    "C": (3.986004418e14, 7.292115e-5),        # CGCS2000
}
_BDS_GEO_TILT_RAD = math.radians(-5.0)


def is_beidou_geo(sat: str) -> bool:
    """BeiDou GEO satellites: PRN 1-5 (BDS-2) and 59-63 (BDS-3)."""
    if sat[0] != "C":
        return False
    prn = int(sat[1:])
    return prn <= 5 or 59 <= prn <= 63


#: bounds of a broadcast orbit a satellite of these systems can have: sqrt(A) of GPS 5154, Galileo
#: 5440, BeiDou MEO 5282 and IGSO/GEO 6493, QZSS 6493 sqrt(m); eccentricity up to QZSS's 0.075.
#: A record outside them (a hostile or corrupt 1019 / subframe set with a valid CRC) would divide
#: by zero or leave the domain of the anomaly's functions at every epoch of its fit interval
_SQRT_A_RANGE = (4000.0, 7000.0)
_MAX_ECCENTRICITY = 0.5


def implausible(eph: GpsEphemeris) -> str:
    """Why a Keplerian ephemeris cannot be a satellite's, or '' when it can."""
    values = [getattr(eph, f) for f in ("sqrt_a", "e", "i0_rad", "omega0_rad", "omega_rad", "m0_rad",
                                         "delta_n_radps", "idot_radps", "omega_dot_radps", "cuc_rad", "cus_rad",
                                         "crc_m", "crs_m", "cic_rad", "cis_rad", "af0_s", "af1_sps", "af2_sps2",
                                         "tgd_s", "toe_s", "toc_s")]
    if not all(math.isfinite(v) for v in values):
        return "non-finite"
    if not _SQRT_A_RANGE[0] <= eph.sqrt_a <= _SQRT_A_RANGE[1]:
        return "semi-major axis"
    if not 0.0 <= eph.e <= _MAX_ECCENTRICITY:
        return "eccentricity"
    return ""


def _wrap_week(dt_s: float) -> float:
    """Time difference folded into [-half week, half week] (the spec's week-crossover rule)."""
    if dt_s > 302400.0:
        dt_s -= SECONDS_PER_WEEK
    elif dt_s < -302400.0:
        dt_s += SECONDS_PER_WEEK
    return dt_s


def satellite_clock(eph: GpsEphemeris, t_gps: float, e_anomaly_rad: float | None = None) -> tuple[float, float]:
    """(clock bias s, clock drift s/s) of the satellite at ``t_gps``, relativistic term included,
    group delay (TGD) **not** included (L1-only users subtract ``eph.tgd_s``).  A GLONASS ephemeris
    is :func:`companion.gnss.glonass.satellite_clock`'s."""
    if isinstance(eph, glonass.GlonassEphemeris):
        return glonass.satellite_clock(eph, t_gps)
    dt = _wrap_week(t_gps - eph.t_oc_gps)
    bias = eph.af0_s + eph.af1_sps * dt + eph.af2_sps2 * dt * dt
    drift = eph.af1_sps + 2.0 * eph.af2_sps2 * dt
    if e_anomaly_rad is None:
        e_anomaly_rad = _eccentric_anomaly(eph, _wrap_week(t_gps - eph.t_oe_gps))[0]
    bias += REL_F * eph.e * eph.sqrt_a * math.sin(e_anomaly_rad)
    return bias, drift


def _eccentric_anomaly(eph: GpsEphemeris, tk: float) -> tuple[float, float]:
    a = eph.sqrt_a * eph.sqrt_a
    gm = _GM_OMEGA.get(eph.sat[0], _GM_OMEGA["G"])[0]
    n = math.sqrt(gm / (a * a * a)) + eph.delta_n_radps
    m = eph.m0_rad + n * tk
    e_anom = m
    for _ in range(30):
        d = (e_anom - eph.e * math.sin(e_anom) - m) / (1.0 - eph.e * math.cos(e_anom))
        e_anom -= d
        if abs(d) < 1e-14:
            break
    return e_anom, n


def satellite_state(eph: GpsEphemeris, t_gps: float):
    """Satellite (r_e m, v_e m/s, clock bias s, clock drift s/s) at GPS time ``t_gps``.

    Velocity is the time derivative of the ECEF position (rotating frame), from the analytic
    derivative of the orbit equations.  Clock bias includes the relativistic term, not TGD.  A
    GLONASS ephemeris is integrated (:func:`companion.gnss.glonass.satellite_state`).
    """
    if isinstance(eph, glonass.GlonassEphemeris):
        return glonass.satellite_state(eph, t_gps)
    tk = _wrap_week(t_gps - eph.t_oe_gps)
    a = eph.sqrt_a * eph.sqrt_a
    e = eph.e
    omega_e = _GM_OMEGA.get(eph.sat[0], _GM_OMEGA["G"])[1]
    e_anom, n = _eccentric_anomaly(eph, tk)
    sin_e, cos_e = math.sin(e_anom), math.cos(e_anom)
    one_m_ecos = 1.0 - e * cos_e
    e_dot = n / one_m_ecos
    sq = math.sqrt(1.0 - e * e)
    nu = math.atan2(sq * sin_e, cos_e - e)
    nu_dot = e_dot * sq / one_m_ecos
    phi = nu + eph.omega_rad
    s2, c2 = math.sin(2.0 * phi), math.cos(2.0 * phi)
    du = eph.cus_rad * s2 + eph.cuc_rad * c2
    dr = eph.crs_m * s2 + eph.crc_m * c2
    di = eph.cis_rad * s2 + eph.cic_rad * c2
    u = phi + du
    r = a * one_m_ecos + dr
    i = eph.i0_rad + di + eph.idot_radps * tk
    u_dot = nu_dot * (1.0 + 2.0 * (eph.cus_rad * c2 - eph.cuc_rad * s2))
    r_dot = a * e * sin_e * e_dot + 2.0 * nu_dot * (eph.crs_m * c2 - eph.crc_m * s2)
    i_dot = eph.idot_radps + 2.0 * nu_dot * (eph.cis_rad * c2 - eph.cic_rad * s2)
    x_orb, y_orb = r * math.cos(u), r * math.sin(u)
    x_orb_dot = r_dot * math.cos(u) - y_orb * u_dot
    y_orb_dot = r_dot * math.sin(u) + x_orb * u_dot
    geo = is_beidou_geo(eph.sat)
    if geo:   # node in the inertial frame of toe; the earth rotation is applied after the tilt
        omega = eph.omega0_rad + eph.omega_dot_radps * tk - omega_e * eph.toe_s
        omega_dot = eph.omega_dot_radps
    else:
        omega = eph.omega0_rad + (eph.omega_dot_radps - omega_e) * tk - omega_e * eph.toe_s
        omega_dot = eph.omega_dot_radps - omega_e
    so, co = math.sin(omega), math.cos(omega)
    si, ci = math.sin(i), math.cos(i)
    x = x_orb * co - y_orb * ci * so
    y = x_orb * so + y_orb * ci * co
    z = y_orb * si
    vx = x_orb_dot * co - y_orb_dot * ci * so + y_orb * si * so * i_dot - y * omega_dot
    vy = x_orb_dot * so + y_orb_dot * ci * co - y_orb * si * co * i_dot + x * omega_dot
    vz = y_orb_dot * si + y_orb * ci * i_dot
    r_e, v_e = np.array([x, y, z]), np.array([vx, vy, vz])
    if geo:
        r_e, v_e = _beidou_geo_to_ecef(r_e, v_e, omega_e * tk, omega_e)
    bias, drift = satellite_clock(eph, t_gps, e_anom)
    # derivative of the relativistic term, for a consistent drift
    drift += REL_F * e * eph.sqrt_a * cos_e * e_dot
    return r_e, v_e, bias, drift


def _beidou_geo_to_ecef(r_g: np.ndarray, v_g: np.ndarray, angle_rad: float, omega_e: float):
    """BeiDou GEO: rotate by -5 deg about x, then by the earth's rotation angle about z
    (B1I ICD table 5-11).  v_g is the inertial-frame derivative; the rotating frame adds
    -omega_e x r."""
    ct, st = math.cos(_BDS_GEO_TILT_RAD), math.sin(_BDS_GEO_TILT_RAD)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, ct, st], [0.0, -st, ct]])
    cz, sz = math.cos(angle_rad), math.sin(angle_rad)
    rz = np.array([[cz, sz, 0.0], [-sz, cz, 0.0], [0.0, 0.0, 1.0]])
    rot = rz @ rx
    r_e = rot @ r_g
    v_e = rot @ v_g + np.array([omega_e * r_e[1], -omega_e * r_e[0], 0.0])
    return r_e, v_e


def rotate_to_reception_frame(r_e: np.ndarray, v_e: np.ndarray, travel_time_s: float):
    """Express a transmit-time ECEF position/velocity in the ECEF frame of the reception time.

    The earth turns by omega*tau while the signal travels; this is the Sagnac correction.
    """
    a = OMEGA_IE_RADPS * travel_time_s
    c, s = math.cos(a), math.sin(a)
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return rot @ r_e, rot @ v_e


def transmit_time(t_rx_gps: float, pseudorange_m: float, eph: GpsEphemeris) -> float:
    """Signal transmit time in GPS time from the receiver time tag and pseudorange.

    t_rx - P/c is the transmit time on the satellite clock; removing the satellite clock bias
    gives GPS time (the receiver clock error cancels: it is in both t_rx and P).
    """
    t_sv = t_rx_gps - pseudorange_m / SPEED_OF_LIGHT_MPS
    bias, _ = satellite_clock(eph, t_sv)
    bias, _ = satellite_clock(eph, t_sv - bias)
    return t_sv - bias
