"""Scoring of ``python -m sitl ardupilot`` against SITL's truth (pure functions, no I/O).

Times: every estimate is stamped with the autopilot's boot time of its IMU sample
(VISION_POSITION_ESTIMATE/ODOMETRY ``usec``, GPS_INPUT ``time_usec``), LOCAL_POSITION_NED with
``time_boot_ms``.  SIMSTATE carries no time: it is the physics state when ArduPilot sent it, so
its boot time is its receive time minus the receive-minus-boot offset, taken as the smallest one
seen in ATTITUDE/LOCAL_POSITION_NED within a few seconds (the transport delay floor; a window,
because SITL's clock can drift from ours when the machine is loaded).

Positions: SIMSTATE's latitude/longitude (1e-7 deg, 1.1 cm) are turned into NED about an origin
with ArduPilot's own flat-Earth ``Location::get_distance_NED``, the convention of
VISION_POSITION_ESTIMATE/ODOMETRY and LOCAL_POSITION_NED, so the frames agree exactly.
"""
from __future__ import annotations

import math

import numpy as np

LOCATION_SCALING_FACTOR_M = 0.011131884502145034    # ArduPilot: m per 1e-7 deg of latitude


def ned_from_latlon_e7(lat_e7, lon_e7, origin_lat_e7: float, origin_lon_e7: float) -> np.ndarray:
    """(N, E) in m of points given in 1e-7 deg, about an origin, ArduPilot's flat-Earth way."""
    lat = np.asarray(lat_e7, float)
    lon = np.asarray(lon_e7, float)
    scale = np.maximum(np.cos(np.radians((lat + origin_lat_e7) * 0.5e-7)), 0.01)
    return np.column_stack([(lat - origin_lat_e7) * LOCATION_SCALING_FACTOR_M,
                            (lon - origin_lon_e7) * LOCATION_SCALING_FACTOR_M * scale])


def boot_offset(times_recv: np.ndarray, times_boot: np.ndarray, window_s: float = 5.0):
    """A function t_recv -> (t_recv - t_boot) from the windowed minimum of the observed offsets."""
    tr = np.asarray(times_recv, float)
    off = tr - np.asarray(times_boot, float)
    if tr.size == 0:
        raise ValueError("no boot-time stamped messages to map SIMSTATE's receive times")
    edges = np.arange(tr[0], tr[-1] + window_s, window_s)
    centres, mins = [], []
    for a in edges:
        sel = (tr >= a) & (tr < a + window_s)
        if np.any(sel):
            centres.append(a + 0.5 * window_s)
            mins.append(float(np.min(off[sel])))
    centres, mins = np.array(centres), np.array(mins)
    return lambda t: np.interp(t, centres, mins)


def wrap_pi(a):
    return (np.asarray(a, float) + math.pi) % (2.0 * math.pi) - math.pi


class Truth:
    """SITL truth as functions of autopilot boot time: horizontal NED about an origin, and yaw."""

    def __init__(self, t_boot_s, lat_e7, lon_e7, yaw_rad):
        order = np.argsort(t_boot_s)
        self.t = np.asarray(t_boot_s, float)[order]
        self.lat_e7 = np.asarray(lat_e7, float)[order]
        self.lon_e7 = np.asarray(lon_e7, float)[order]
        # unwrapped, so interpolation across +-180 deg is right
        self.yaw = np.unwrap(np.asarray(yaw_rad, float)[order])

    def covers(self, t) -> np.ndarray:
        t = np.asarray(t, float)
        return (t >= self.t[0]) & (t <= self.t[-1])

    def latlon_e7(self, t):
        return np.interp(t, self.t, self.lat_e7), np.interp(t, self.t, self.lon_e7)

    def ne(self, t, origin_lat_e7: float, origin_lon_e7: float) -> np.ndarray:
        lat, lon = self.latlon_e7(t)
        return ned_from_latlon_e7(lat, lon, origin_lat_e7, origin_lon_e7)

    def yaw_at(self, t) -> np.ndarray:
        return np.interp(t, self.t, self.yaw)


def horizontal_errors(t_s, ne_m, truth: Truth, origin_lat_e7: float, origin_lon_e7: float):
    """(times, |horizontal error| m) of NE positions against the truth, where the truth covers them."""
    t = np.asarray(t_s, float)
    ne = np.asarray(ne_m, float).reshape(-1, 2)
    ok = truth.covers(t)
    if not np.any(ok):
        return t[:0], t[:0]
    err = ne[ok] - truth.ne(t[ok], origin_lat_e7, origin_lon_e7)
    return t[ok], np.hypot(err[:, 0], err[:, 1])


def yaw_errors_deg(t_s, yaw_rad, truth: Truth) -> np.ndarray:
    t = np.asarray(t_s, float)
    ok = truth.covers(t)
    return np.degrees(wrap_pi(np.asarray(yaw_rad, float)[ok] - truth.yaw_at(t[ok])))


def rms(x) -> float | None:
    x = np.asarray(x, float)
    return None if x.size == 0 else float(np.sqrt(np.mean(x ** 2)))


def in_window(t, window) -> np.ndarray:
    t = np.asarray(t, float)
    if window is None:
        return np.zeros(t.shape, bool)
    return (t >= window[0]) & (t <= window[1])


def quat_yaw(q) -> float:
    """Yaw of a body-to-NED quaternion [w, x, y, z]."""
    w, x, y, z = q
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


FAILSAFE_WORDS = ("failsafe", "ekf variance", "lane switch", "crash", "potential thrust loss")


def failsafes(texts) -> list[str]:
    """STATUSTEXTs that report a failsafe or an EKF failure."""
    return [t for t in texts if any(w in t.lower() for w in FAILSAFE_WORDS)]
