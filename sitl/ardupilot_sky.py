"""Sky and error models of ``python -m sitl ardupilot --gnss raw``: the 'uav' scenario's receivers
and atmosphere, moved to SITL's home and SITL's clock.

ArduPilot SITL flies at its home (Canberra) now; our only real broadcast ephemerides are GEONET's
of 2005-04-02.  :func:`reepoch` moves that constellation in time and about the Earth's axis:

* every ephemeris of the 'uav' scenario's set (valid over the run from 2005-04-02 00:20 GPST) has
  toe, toc and week shifted by the same ``shift_s`` (a multiple of 16 s, the LNAV/RTCM resolution
  of toe and toc) and Omega0 changed so that the satellite at ``t + shift_s`` is where it was at
  ``t``, rotated by ``rotation_rad`` east about the Earth's axis: with Omega = Omega0 +
  OmegaDot tk - OmegaE (toe + tk) (IS-GPS-200 Table 20-IV), Omega0' = Omega0 + OmegaE (toe' - toe)
  + rotation (toe, toe' seconds of week).  Orbits, clocks (af0-af2 about toc') and TGD are as
  broadcast, so the sky is the real 2005 one, seen from elsewhere at another time;
* the rotation is the one (whole degrees) that shows SITL's home the most satellites above the
  mask over the run; then every ephemeris is rounded to what LNAV carries
  (:func:`sitl.lnav_encode.quantised`), so the simulator and the companion use the same numbers.

:func:`live_scenario` is the 'uav' scenario (its rover and base receivers, clocks, ionosphere,
troposphere, orbit and satellite-clock errors, mask, Klobuchar coefficients) with that sky, SITL's
home as the trajectory origin, no lever arm (SITL's truth is the body origin, which
``deploy/companion.toml``'s zero lever arm takes as the antenna), no outage, ``rate_hz`` epochs
and a base 3 km south-east of home at its height.  The trajectory itself is SITL's, followed live
(:mod:`sitl.ardupilot_truth`).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from companion.gnss.ephemeris import satellite_state
from companion.messages import SECONDS_PER_WEEK, GpsEphemeris
from companion.nav.earth import OMEGA_IE_RADPS, C_n_e, geodetic_to_ecef

from . import sky
from .lnav_encode import quantised
from .scenario import Scenario, build_scenario

BASE_NED_M = (3000.0 * math.cos(math.radians(135.0)), 3000.0 * math.sin(math.radians(135.0)), 0.0)
BASE_STATION_ID = 1


@dataclass(frozen=True)
class LiveTrajectory:
    """Stands in for a scenario trajectory: only its origin is known in advance."""

    origin_llh: tuple[float, float, float]          # rad, rad, m
    duration_s: float


def reepoch(ephs: list[GpsEphemeris], shift_s: float, rotation_rad: float) -> list[GpsEphemeris]:
    """``ephs`` ``shift_s`` later (a multiple of 16 s) and rotated east by ``rotation_rad``."""
    if abs(shift_s / 16.0 - round(shift_s / 16.0)) > 1e-9:
        raise ValueError("shift_s must be a multiple of 16 s (the resolution of toe and toc)")
    out = []
    for e in ephs:
        t_oe = e.t_oe_gps + shift_s
        week = int(t_oe // SECONDS_PER_WEEK)
        toe = t_oe - week * SECONDS_PER_WEEK
        toc = e.t_oc_gps + shift_s - week * SECONDS_PER_WEEK
        omega0 = e.omega0_rad + OMEGA_IE_RADPS * (toe - e.toe_s) + rotation_rad
        omega0 = (omega0 + math.pi) % (2.0 * math.pi) - math.pi
        out.append(dataclasses.replace(e, week=week, toe_s=toe, toc_s=toc, omega0_rad=omega0))
    return out


def visible_count(ephs, r_rx_e, t_gps: float, mask_rad: float) -> int:
    n = 0
    for e in ephs:
        el, _ = sky.elevation_azimuth(r_rx_e, satellite_state(e, t_gps)[0])
        n += el >= mask_rad
    return n


def best_rotation(ephs, r_rx_e, t0_gps: float, duration_s: float, mask_rad: float,
                  step_deg: int = 5, sample_s: float = 300.0) -> float:
    """The rotation (rad, a multiple of ``step_deg``) with the most satellites above the mask at
    the worst of the sampled times of the run (ties: the larger sum, then the smaller angle)."""
    times = t0_gps + np.arange(0.0, duration_s + 1e-9, sample_s)
    best = None
    for deg in range(0, 360, step_deg):
        rot = reepoch(ephs, 0.0, math.radians(deg))
        counts = [visible_count(rot, r_rx_e, float(t), mask_rad) for t in times]
        key = (min(counts), sum(counts), -deg)
        if best is None or key > best[0]:
            best = (key, math.radians(deg))
    return best[1]


def live_scenario(home_llh: tuple[float, float, float], t0_gps: float, duration_s: float,
                  rate_hz: float = 5.0) -> Scenario:
    """The 'uav' scenario's models at ``home_llh`` (rad, rad, m) from true GPS time ``t0_gps`` for
    ``duration_s`` with ``rate_hz`` epochs (see the module docstring)."""
    uav = build_scenario("uav")
    t_orig = uav.t0_gps                          # 2005-04-02 00:20:00.0063 GPST
    ephs = list(sky.select_ephemerides(sky.geonet_ephemerides(), t_orig, t_orig + duration_s + 60.0).values())
    ephs.sort(key=lambda e: e.sat)
    shift = 16.0 * math.floor((t0_gps - t_orig) / 16.0)
    r_home = geodetic_to_ecef(*home_llh)
    mask = math.radians(uav.mask_deg)
    rot = best_rotation(ephs, r_home, t0_gps - shift, duration_s, mask)
    moved = [quantised(e) for e in reepoch(ephs, shift, rot)]
    base = geodetic_to_ecef(*home_llh) + C_n_e(home_llh[0], home_llh[1]) @ np.asarray(BASE_NED_M)
    return dataclasses.replace(
        uav, name="ardupilot-sitl", description=f"{uav.description}; sky moved to SITL's home and clock "
        f"({math.degrees(rot):.0f} deg east, {shift:.0f} s later), {rate_hz:g} Hz, live trajectory",
        trajectory=LiveTrajectory(tuple(home_llh), float(duration_s)), t0_gps=float(t0_gps),
        duration_s=float(duration_s), ephemerides=tuple(moved), base_r_e=base, base_station_id=BASE_STATION_ID,
        lever_arm_b=(0.0, 0.0, 0.0), gnss_rate_hz=float(rate_hz), rover_outages=(), cycle_slips=(),
        notes={"sky_rotation_deg": math.degrees(rot), "sky_shift_s": shift})


__all__ = ["LiveTrajectory", "reepoch", "best_rotation", "visible_count", "live_scenario"]
