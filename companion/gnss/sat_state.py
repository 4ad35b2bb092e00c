"""Satellite state for the per-epoch preparation: the broadcast orbit and clock of
:mod:`.ephemeris` in plain floats, with each ephemeris's constants computed once.

:func:`.ephemeris.satellite_state` and :func:`.ephemeris.transmit_time` are the readable
references; this module evaluates the *same expressions in the same order* (so the results are
identical bit for bit, tests/test_sat_state.py), without what they repeat per call: the mean
motion, the system's constants, toe/toc in GPS seconds, the GEO test, three Kepler set-ups per
satellite and two numpy arrays per state.  A satellite's transmit time depends on the receiver
(rover and base see it ~10 us apart per 3 km of baseline, plus their clock offsets), so there is
nothing exact to share between the two receivers' states; what they share is the ephemeris's
:class:`OrbitConstants`.

The constants are a pure function of the ephemeris: a cache hit and a recomputation give the same
numbers, so the cache cannot change a result (replays stay bit for bit).  It is keyed by object
identity and holds the ephemeris itself (an identity cannot be reused while it is held); it is
bounded (:data:`MAX_CACHED`: cleared when full).  :mod:`.sat_state_kernel` is the same state
compiled, which :func:`companion.gnss.prepare.prepare_epoch` calls when the engine's kernels run.
"""
from __future__ import annotations

import math

import numpy as np

from ..messages import SPEED_OF_LIGHT_MPS, GpsEphemeris
from .ephemeris import _GM_OMEGA, REL_F, _beidou_geo_to_ecef, is_beidou_geo
from .sat_state_kernel import constants_vector

#: ephemerides whose constants are kept (a day of four constellations is ~3000)
MAX_CACHED = 4096
_HALF_WEEK_S = 302400.0
_WEEK_S = 604800.0


class OrbitConstants:
    """What :mod:`.ephemeris` derives from one ephemeris at every call, computed once."""

    __slots__ = ("eph", "t_oe", "t_oc", "a", "e", "sqrt_a", "n", "m0", "sq", "omega_e", "geo", "rel",
                 "af0", "af1", "af2", "omega_arg", "cus", "cuc", "crs", "crc", "cis", "cic", "i0", "idot",
                 "omega0", "omega_dot", "omega_rate", "omega_e_toe", "vec")

    def __init__(self, eph: GpsEphemeris):
        self.eph = eph
        self.t_oe = eph.t_oe_gps
        self.t_oc = eph.t_oc_gps
        gm, omega_e = _GM_OMEGA.get(eph.sat[0], _GM_OMEGA["G"])
        a = eph.sqrt_a * eph.sqrt_a
        self.a = a
        self.e = eph.e
        self.sqrt_a = eph.sqrt_a
        self.n = math.sqrt(gm / (a * a * a)) + eph.delta_n_radps
        self.m0 = eph.m0_rad
        self.sq = math.sqrt(1.0 - eph.e * eph.e)
        self.omega_e = omega_e
        self.geo = is_beidou_geo(eph.sat)
        self.rel = REL_F * eph.e * eph.sqrt_a
        self.af0, self.af1, self.af2 = eph.af0_s, eph.af1_sps, eph.af2_sps2
        self.omega_arg = eph.omega_rad
        self.cus, self.cuc, self.crs, self.crc = eph.cus_rad, eph.cuc_rad, eph.crs_m, eph.crc_m
        self.cis, self.cic, self.i0, self.idot = eph.cis_rad, eph.cic_rad, eph.i0_rad, eph.idot_radps
        self.omega0, self.omega_dot = eph.omega0_rad, eph.omega_dot_radps
        # as ephemeris.satellite_state groups them: (omega_dot - omega_e) and omega_e * toe
        self.omega_rate = eph.omega_dot_radps - omega_e
        self.omega_e_toe = omega_e * eph.toe_s
        self.vec = constants_vector(self)       # for the compiled state (.sat_state_kernel)


_cache: dict[int, OrbitConstants] = {}


def orbit_constants(eph: GpsEphemeris) -> OrbitConstants:
    """The (cached) constants of ``eph``."""
    k = _cache.get(id(eph))
    if k is not None and k.eph is eph:
        return k
    if len(_cache) >= MAX_CACHED:
        _cache.clear()
    k = _cache[id(eph)] = OrbitConstants(eph)
    return k


def _wrap(dt: float) -> float:
    if dt > _HALF_WEEK_S:
        return dt - _WEEK_S
    if dt < -_HALF_WEEK_S:
        return dt + _WEEK_S
    return dt


def _kepler(k: OrbitConstants, tk: float) -> float:
    """Eccentric anomaly at ``tk`` s from toe (ephemeris._eccentric_anomaly)."""
    m = k.m0 + k.n * tk
    e = k.e
    e_anom = m
    sin, cos = math.sin, math.cos
    for _ in range(30):
        d = (e_anom - e * sin(e_anom) - m) / (1.0 - e * cos(e_anom))
        e_anom -= d
        if abs(d) < 1e-14:
            break
    return e_anom


def clock_bias_s(k: OrbitConstants, t_gps: float) -> float:
    """Satellite clock bias (s) at ``t_gps``, relativistic term included (ephemeris.satellite_clock)."""
    dt = _wrap(t_gps - k.t_oc)
    bias = k.af0 + k.af1 * dt + k.af2 * dt * dt
    return bias + k.rel * math.sin(_kepler(k, _wrap(t_gps - k.t_oe)))


def transmit_time(k: OrbitConstants, t_rx_gps: float, pseudorange_m: float) -> float:
    """GPS transmit time from the receiver tag and the pseudorange (ephemeris.transmit_time)."""
    t_sv = t_rx_gps - pseudorange_m / SPEED_OF_LIGHT_MPS
    bias = clock_bias_s(k, t_sv)
    return t_sv - clock_bias_s(k, t_sv - bias)


def state(k: OrbitConstants, t_gps: float):
    """(x, y, z, vx, vy, vz, clock bias s, clock drift s/s) at ``t_gps``: ephemeris.satellite_state
    as floats (ECEF of the transmit instant, velocity in the rotating frame)."""
    tk = _wrap(t_gps - k.t_oe)
    a, e = k.a, k.e
    e_anom = _kepler(k, tk)
    sin, cos = math.sin, math.cos
    sin_e, cos_e = sin(e_anom), cos(e_anom)
    one_m_ecos = 1.0 - e * cos_e
    e_dot = k.n / one_m_ecos
    sq = k.sq
    nu = math.atan2(sq * sin_e, cos_e - e)
    nu_dot = e_dot * sq / one_m_ecos
    phi = nu + k.omega_arg
    s2, c2 = sin(2.0 * phi), cos(2.0 * phi)
    cus, cuc, crs, crc, cis, cic = k.cus, k.cuc, k.crs, k.crc, k.cis, k.cic
    du = cus * s2 + cuc * c2
    dr = crs * s2 + crc * c2
    di = cis * s2 + cic * c2
    u = phi + du
    r = a * one_m_ecos + dr
    i = k.i0 + di + k.idot * tk
    u_dot = nu_dot * (1.0 + 2.0 * (cus * c2 - cuc * s2))
    r_dot = a * e * sin_e * e_dot + 2.0 * nu_dot * (crs * c2 - crc * s2)
    i_dot = k.idot + 2.0 * nu_dot * (cis * c2 - cic * s2)
    cu, su = cos(u), sin(u)
    x_orb, y_orb = r * cu, r * su
    x_orb_dot = r_dot * cu - y_orb * u_dot
    y_orb_dot = r_dot * su + x_orb * u_dot
    if k.geo:
        omega = k.omega0 + k.omega_dot * tk - k.omega_e_toe
        omega_dot = k.omega_dot
    else:
        omega = k.omega0 + k.omega_rate * tk - k.omega_e_toe
        omega_dot = k.omega_rate
    so, co = sin(omega), cos(omega)
    si, ci = sin(i), cos(i)
    x = x_orb * co - y_orb * ci * so
    y = x_orb * so + y_orb * ci * co
    z = y_orb * si
    vx = x_orb_dot * co - y_orb_dot * ci * so + y_orb * si * so * i_dot - y * omega_dot
    vy = x_orb_dot * so + y_orb_dot * ci * co - y_orb * si * co * i_dot + x * omega_dot
    vz = y_orb_dot * si + y_orb * ci * i_dot
    if k.geo:    # rare: the reference's numpy rotation as it is
        r_e, v_e = _beidou_geo_to_ecef(np.array([x, y, z]), np.array([vx, vy, vz]), k.omega_e * tk, k.omega_e)
        x, y, z = float(r_e[0]), float(r_e[1]), float(r_e[2])
        vx, vy, vz = float(v_e[0]), float(v_e[1]), float(v_e[2])
    dt = _wrap(t_gps - k.t_oc)
    bias = k.af0 + k.af1 * dt + k.af2 * dt * dt + k.rel * sin_e
    drift = k.af1 + 2.0 * k.af2 * dt + k.rel * cos_e * e_dot
    return x, y, z, vx, vy, vz, bias, drift
