"""Galileo and BeiDou satellites for the simulator: real broadcast ephemerides of a base station in
Hiroshima (2022-12-13), moved onto a simulated epoch.

GEONET's 2005 navigation file (:data:`sitl.sky.GEONET_NAV`) has GPS only.  The Galileo (RTCM 1046,
I/NAV) and BeiDou (1042, D1/D2: MEO, IGSO and GEO) ephemerides of qzsl6tool's OEM729 stream
(``sitl/data/20221213-010900-eph.rtcm``: its ephemeris frames, unmodified; PROVENANCE.md) are
relabelled by one common time shift ``dt``: every time moves by ``dt`` and the longitude of the node
absorbs the earth's rotation over the change of the time of week, so the ECEF orbit and clock at
``t + dt`` are the recorded ones at ``t``.  ``dt`` is ``t0_sim - RECORDING_T_GPS`` rounded down to
a whole :data:`SHIFT_GRID_S` and the moved node longitude is rounded to its broadcast resolution, so
the moved ephemerides are exactly what RTCM 1046 / 1042 carry (toe and toc on their 60-s / 8-s
grids: ``sitl.rtcm_eph_encode``; the live flight's base sends them, the service decodes the very
orbits the simulator used).  The sky over Japan at the scenario start is then the one over Japan
(Hiroshima, 5 deg west of GEONET 0759) at most 2 minutes after the recording's start.

In the GpsEphemeris representation (``week`` in GPS weeks, times of week in the system's own time,
BDT = GPST - 14 s) a BeiDou ephemeris moved to 2005 has a week before BDT's origin (GPS week 1356):
consistent for the orbit and clock equations, but not encodable as a BeiDou broadcast week.
"""
from __future__ import annotations

import dataclasses
import math
from importlib import resources
from pathlib import Path

from companion.gnss.ephemeris import _GM_OMEGA
from companion.messages import SECONDS_PER_WEEK, SYSTEM_TO_GPS_S, GpsEphemeris, gps_time

#: the ephemeris frames (1042, 1046) of tests/data/qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm
HIROSHIMA_EPH = Path(str(resources.files("sitl") / "data" / "20221213-010900-eph.rtcm"))
#: GPS week of the recording (the RTCM ephemeris weeks are truncated; resolved against this)
RECORDING_WEEK = 2240
#: the recording's first observation epoch (MSM, GPS time): the instant the moved sky reproduces
RECORDING_T_GPS = gps_time(RECORDING_WEEK, 176962.0)
#: revision of the moved sky (part of sitl.fly's cache key): 2 = shift on SHIFT_GRID_S, node on its grid
SKY_REVISION = 2
#: the common shift is a whole multiple of this (s): Galileo toe/toc are sent in 60-s units, BeiDou's
#: in 8-s units (RTCM DF293/DF304, DF493/DF505), so a shift on the 120-s grid keeps them encodable
SHIFT_GRID_S = 120.0
#: broadcast angles are sent in units of 2^-31 semicircles (ICD pi)
_ANGLE_LSB_RAD = 2.0 ** -31 * 3.1415926535898


def _on_angle_grid(x_rad: float) -> float:
    """``x_rad`` wrapped into [-pi, pi) and rounded to the broadcast 2^-31-semicircle grid."""
    k = round(x_rad / _ANGLE_LSB_RAD) % (1 << 32)
    if k >= 1 << 31:
        k -= 1 << 32
    return k * _ANGLE_LSB_RAD


def recorded_ephemerides(path=HIROSHIMA_EPH, systems: str = "EC") -> list[GpsEphemeris]:
    """The recording's ephemerides of ``systems``, as the companion's RTCM decoder gives them
    (Galileo I/NAV: its clock and BGD(E1,E5b) serve E1 and E1/E5b users)."""
    from companion.io.rtcm import decode_rtcm_file

    msgs, _ = decode_rtcm_file(str(path), week_hint=RECORDING_WEEK)
    return [m for m in msgs if isinstance(m, GpsEphemeris) and m.sat[0] in systems]


def move_ephemeris(eph: GpsEphemeris, dt_s: float) -> GpsEphemeris:
    """``eph`` with toe, toc and week moved by ``dt_s`` (continuous GPS time) and the node longitude
    shifted so that the ECEF orbit at the same ``t - toe`` is unchanged.

    The orbit equations use ``Omega = Omega0 + (Omega_dot - omega_e) tk - omega_e toe_s`` (GEO: the
    same before the final rotation by omega_e tk) with ``toe_s`` the time of week, so Omega0 shifts
    by ``omega_e (toe_s,new - toe_s,old)``: that is ``omega_e dt`` only if the week number does not
    change (omega_e x 1 week is 0.12 rad modulo 2 pi, not 0).  The new node longitude is rounded to
    the broadcast resolution (2^-31 semicircles, < 5 cm along the orbit)."""
    off = SYSTEM_TO_GPS_S.get(eph.sat[0], 0.0)
    t_sys = eph.t_oe_gps + dt_s - off                     # new toe, system time, continuous
    week = int(math.floor(t_sys / SECONDS_PER_WEEK))
    toe = t_sys - week * SECONDS_PER_WEEK
    toc = eph.t_oc_gps + dt_s - off - week * SECONDS_PER_WEEK   # same week as toe (may leave [0, W))
    omega_e = _GM_OMEGA.get(eph.sat[0], _GM_OMEGA["G"])[1]
    om = _on_angle_grid(eph.omega0_rad + omega_e * (toe - eph.toe_s))
    return dataclasses.replace(eph, week=week, toe_s=toe, toc_s=toc, omega0_rad=om)


def moved_ephemerides(t0_gps: float, systems: str = "EC", path=HIROSHIMA_EPH) -> list[GpsEphemeris]:
    """The recording's ephemerides of ``systems`` moved so that ``t0_gps`` sees the sky of
    :data:`RECORDING_T_GPS` plus less than :data:`SHIFT_GRID_S` (one common shift for every
    satellite, on that grid)."""
    dt = math.floor((float(t0_gps) - RECORDING_T_GPS) / SHIFT_GRID_S) * SHIFT_GRID_S
    return [move_ephemeris(e, dt) for e in recorded_ephemerides(path, systems)]
