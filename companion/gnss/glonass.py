"""GLONASS broadcast ephemerides (ICD GLONASS edition 5.1, A.3.1.2): the satellite state by
numerical integration, its clock, and the FDMA carrier of each frequency channel.

A GLONASS ephemeris is not Keplerian: it is the satellite's PZ-90 position, velocity and the
lunisolar acceleration at ``t_b`` (every 30 min), valid about 15 min either side.  The state at
another time comes from integrating the equations of motion in the rotating earth frame (central
field, J2, centrifugal and Coriolis terms, the broadcast acceleration held constant) by
fourth-order Runge-Kutta as RTKLIB's ``geph2pos``: whole steps of :data:`STEP_S` (60 s) from
``t_b``, then one step of the remainder.  The states on that 60-s grid are kept with the
ephemeris, so a state costs one step once the grid reaches it (a receiver asks for each
satellite at every epoch, for the rover and for the base: the integration from ``t_b`` was
most of the cost of a GLONASS satellite).
PZ-90.11 and WGS-84 (G1762) agree to centimetres, so no frame transformation is applied.

Time: the RINEX record's epoch is ``t_b`` in UTC(SU) - 3 h read as UTC; it becomes GPS time by the
leap seconds (the file header's ``LEAP SECONDS``, or :func:`gps_minus_utc_s`).  Clock: RINEX keeps
``-tau_n`` and ``+gamma_n``, so the satellite clock bias at ``t`` is
``-tau_n + gamma_n (t - t_b)`` (seconds, relativity included).

Carriers (FDMA): L1 = 1602 MHz + k 562.5 kHz, L2 = 1246 MHz + k 437.5 kHz, k in -7..+6 the
broadcast frequency channel; L3 (CDMA) 1202.025 MHz for every satellite.
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass, field

import numpy as np

from ..messages import SPEED_OF_LIGHT_MPS

#: PZ-90 constants of the equations of motion (ICD GLONASS 5.1 table 3.2)
GM_GLO_M3PS2 = 3.9860044e14
J2_GLO = 1.0826257e-3
RE_GLO_M = 6378136.0
OMEGA_GLO_RADPS = 7.292115e-5
#: largest Runge-Kutta step (s)
STEP_S = 60.0
#: how far from t_b an ephemeris is used (s) either side (RTKLIB's MAXDTOE_GLO): the store's window
VALIDITY_H = 1.0

L1_BASE_HZ, L1_STEP_HZ = 1602.0e6, 562.5e3
L2_BASE_HZ, L2_STEP_HZ = 1246.0e6, 437.5e3
L3_HZ = 1202.025e6

#: GPS - UTC from each date on (IERS Bulletin C); the last entry holds until the next leap second
_LEAP_SECONDS = ((_dt.date(1999, 1, 1), 13), (_dt.date(2006, 1, 1), 14), (_dt.date(2009, 1, 1), 15),
                 (_dt.date(2012, 7, 1), 16), (_dt.date(2015, 7, 1), 17), (_dt.date(2017, 1, 1), 18))
_GPS_EPOCH = _dt.date(1980, 1, 6)


def gps_minus_utc_s(t_gps: float) -> int:
    """Leap seconds GPS - UTC at GPS time ``t_gps`` (s since 1980-01-06), from 1999 on."""
    day = _GPS_EPOCH + _dt.timedelta(days=int(t_gps // 86400))
    out = _LEAP_SECONDS[0][1]
    for since, n in _LEAP_SECONDS:
        if day >= since:
            out = n
    return out


@dataclass(eq=False)
class GlonassEphemeris:
    """One GLONASS broadcast ephemeris (from RINEX 3 or RTCM 1020), in the attributes the ephemeris
    store selects by (``sat``, ``t_oe_gps``, ``iode``, ``health``, ``fit_interval_h``)."""

    sat: str                        # 'R05'
    t_oe_gps: float                 # t_b in continuous GPS seconds
    r_e: np.ndarray                 # PZ-90 position at t_b (m)
    v_e: np.ndarray                 # velocity at t_b in the rotating frame (m/s)
    a_e: np.ndarray                 # lunisolar acceleration (m/s^2)
    clock_bias_s: float             # -tau_n
    clock_rate: float               # +gamma_n (s/s)
    frequency_channel: int          # k
    health: int = 0
    iode: int = 0                   # t_b's 15-min slot of the Moscow day (GLONASS has no IODE)
    fit_interval_h: float = 2.0 * VALIDITY_H
    delta_tau_n_s: float = 0.0      # L2 - L1 group delay (RTCM 1020; not in RINEX 3.04)
    age_days: int = 0               # E_n, days since the data were uploaded (RTCM 1020)
    # the broadcast orbit's error for the code weights (m): RINEX and RTCM 1020 carry no URA;
    # RTKLIB's ERREPH_GLO
    ura_m: float = 5.0
    # the integrated states at t_b + k STEP_S (k -> (x, y, z, vx, vy, vz)), filled on demand
    _grid: dict = field(default_factory=dict, init=False, repr=False)


#: bounds of a broadcast state a GLONASS satellite can have (orbit radius 25,510 km, speed 3.95 km/s,
#: lunisolar acceleration under 1e-5 m/s^2; RINEX frequency numbers -7..+13): a record outside
#: them (a hostile or corrupt 1020 / string set) would be integrated into nonsense, or divide by a
#: zero radius
_RADIUS_RANGE_M = (2.4e7, 2.7e7)
_MAX_SPEED_MPS = 5.0e3
_MAX_ACCELERATION_MPS2 = 1.0e-4
_CHANNEL_RANGE = (-7, 13)


def implausible(eph: GlonassEphemeris) -> str:
    """Why a GLONASS ephemeris cannot be a satellite's, or '' when it can."""
    values = (*eph.r_e.tolist(), *eph.v_e.tolist(), *eph.a_e.tolist(), eph.clock_bias_s, eph.clock_rate,
              eph.t_oe_gps)
    if not all(math.isfinite(v) for v in values):
        return "non-finite"
    if not _RADIUS_RANGE_M[0] <= float(np.linalg.norm(eph.r_e)) <= _RADIUS_RANGE_M[1]:
        return "orbit radius"
    if float(np.linalg.norm(eph.v_e)) > _MAX_SPEED_MPS or float(np.linalg.norm(eph.a_e)) > _MAX_ACCELERATION_MPS2:
        return "velocity or acceleration"
    if not _CHANNEL_RANGE[0] <= eph.frequency_channel <= _CHANNEL_RANGE[1]:
        return "frequency channel"
    return ""


def t_b_gps(t_b_units: int, ref_gps: float, leap_seconds: int) -> float:
    """t_b (15-min units of the Moscow day: UTC + 3 h) -> continuous GPS seconds, on the day
    nearest ``ref_gps`` (a receive time)."""
    tod_gps = (int(t_b_units) * 900.0 - 3 * 3600.0 + leap_seconds) % 86400.0
    return tod_gps + 86400.0 * round((ref_gps - tod_gps) / 86400.0)


def carrier_hz(signal: str, channel: int) -> float:
    """Carrier frequency of a GLONASS signal ('L1C', 'L2P', 'L3Q') on frequency channel ``channel``;
    NaN for a band GLONASS does not have."""
    band = signal[1:2]
    if band == "1":
        return L1_BASE_HZ + channel * L1_STEP_HZ
    if band == "2":
        return L2_BASE_HZ + channel * L2_STEP_HZ
    if band == "3":
        return L3_HZ
    return math.nan


def wavelength_m(signal: str, channel: int) -> float:
    return SPEED_OF_LIGHT_MPS / carrier_hz(signal, channel)


def _derivative(x: tuple, acc: tuple) -> tuple:
    """d/dt of the state (x, y, z, vx, vy, vz) in the rotating PZ-90 frame (plain floats: a
    state is integrated in up to 15 steps of 4 evaluations, where numpy's per-call cost dominated)."""
    rx, ry, rz, vx, vy, vz = x
    r2 = rx * rx + ry * ry + rz * rz
    r1 = math.sqrt(r2)
    r3 = r2 * r1
    j2 = 1.5 * J2_GLO * GM_GLO_M3PS2 * RE_GLO_M * RE_GLO_M / (r2 * r3)
    c = -GM_GLO_M3PS2 / r3 - j2 * (1.0 - 5.0 * rz * rz / r2)
    w = OMEGA_GLO_RADPS
    w2 = w * w
    return (vx, vy, vz,
            (c + w2) * rx + 2.0 * w * vy + acc[0],
            (c + w2) * ry - 2.0 * w * vx + acc[1],
            (c - 2.0 * j2) * rz + acc[2])


def _rk4(x: tuple, acc: tuple, h: float) -> tuple:
    k1 = _derivative(x, acc)
    k2 = _derivative(tuple(a + 0.5 * h * b for a, b in zip(x, k1)), acc)
    k3 = _derivative(tuple(a + 0.5 * h * b for a, b in zip(x, k2)), acc)
    k4 = _derivative(tuple(a + h * b for a, b in zip(x, k3)), acc)
    return tuple(a + h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4) for a, b1, b2, b3, b4 in zip(x, k1, k2, k3, k4))


def satellite_clock(eph: GlonassEphemeris, t_gps: float) -> tuple[float, float]:
    """(clock bias s, clock drift s/s) at GPS time ``t_gps``."""
    return eph.clock_bias_s + eph.clock_rate * (t_gps - eph.t_oe_gps), eph.clock_rate


def _grid_state(eph: GlonassEphemeris, k: int, acc: tuple) -> tuple:
    """The state at ``t_b + k STEP_S``, integrated step by step from the nearest one kept."""
    grid = eph._grid
    if not grid:
        grid[0] = (*eph.r_e.tolist(), *eph.v_e.tolist())
    x = grid.get(k)
    if x is None:
        step = 1 if k > 0 else -1
        j = k
        while j not in grid:
            j -= step
        x = grid[j]
        while j != k:
            x = _rk4(x, acc, step * STEP_S)
            j += step
            grid[j] = x
    return x


def satellite_state(eph: GlonassEphemeris, t_gps: float):
    """Satellite (r_e m, v_e m/s, clock bias s, clock drift s/s) at GPS time ``t_gps``: the
    broadcast state integrated from ``t_b`` in whole steps of :data:`STEP_S`, then the remainder."""
    dt = t_gps - eph.t_oe_gps
    acc = tuple(eph.a_e.tolist())
    k = int(abs(dt) // STEP_S) * (1 if dt >= 0.0 else -1)
    x = _grid_state(eph, k, acc)
    rest = dt - k * STEP_S
    if rest != 0.0:
        x = _rk4(x, acc, rest)
    bias, drift = satellite_clock(eph, t_gps)
    return np.array(x[:3]), np.array(x[3:]), bias, drift


def frequency_channels(ephemerides) -> dict[str, int]:
    """GLONASS satellite -> broadcast frequency channel, from its ephemerides (the last one's)."""
    return {e.sat: e.frequency_channel for e in ephemerides if isinstance(e, GlonassEphemeris)}


def with_fdma_wavelengths(epochs, channels: dict[str, int]) -> list:
    """``epochs`` (:class:`~companion.messages.GnssEpoch`) with each GLONASS FDMA observation's
    wavelength from its satellite's channel where it has none: RINEX gives none (a receiver's
    stream does), and the carrier-phase users (smoothing, TDCP, RTK) need it.  Satellites without a
    channel keep NaN (their phase stays unused)."""
    from dataclasses import replace

    def missing(o) -> bool:
        return o.sat[0] == "R" and o.wavelength_m != o.wavelength_m and o.sat in channels

    out = []
    for ep in epochs:
        if any(missing(o) for o in ep.observations):
            ep = replace(ep, observations=tuple(with_channel_wavelength(o, channels[o.sat]) if missing(o) else o
                                                for o in ep.observations))
        out.append(ep)
    return out


def with_channel_wavelength(obs, channel: int):
    """A GLONASS observation with the FDMA wavelength of ``channel`` if it has none (else itself)."""
    if obs.wavelength_m == obs.wavelength_m:
        return obs
    from dataclasses import replace
    return replace(obs, wavelength_m=wavelength_m(obs.signal, channel))


def ephemeris_from_rinex(sat: str, t_b_utc_as_gps: float, leap_s: int, fields: list[float]) -> GlonassEphemeris:
    """A RINEX 3 GLONASS record: ``fields`` = -tau_n, +gamma_n, t_k, then per axis X, X', X'', and
    health / frequency number / age (km, km/s, km/s^2); ``t_b_utc_as_gps``: the record's epoch
    read as if GPS time (it is UTC)."""
    t_b = t_b_utc_as_gps + leap_s
    km = 1000.0
    r = np.array([fields[3], fields[7], fields[11]]) * km
    v = np.array([fields[4], fields[8], fields[12]]) * km
    a = np.array([fields[5], fields[9], fields[13]]) * km
    slot = int(round(((t_b_utc_as_gps + 10800.0) % 86400.0) / 900.0))     # t_b in Moscow time, 15-min units
    return GlonassEphemeris(sat, t_b, r, v, a, fields[0], fields[1], int(round(fields[10])),
                            health=int(round(fields[6])), iode=slot)


__all__ = ["GlonassEphemeris", "implausible", "t_b_gps", "frequency_channels", "with_fdma_wavelengths", "with_channel_wavelength",
           "carrier_hz", "wavelength_m", "satellite_state", "satellite_clock", "ephemeris_from_rinex", "gps_minus_utc_s",
           "STEP_S"]
