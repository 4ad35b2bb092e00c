"""ArduPilot SITL's truth, followed live, as a smooth function of SITL's boot time.

Source: SIM_STATE (position ``lat_int``/``lon_int`` at 1e-7 deg, ``alt`` float m, NED velocity
``vn ve vd`` float m/s; no time stamp) and ATTITUDE (``time_boot_ms``), both requested at the
same rate on a MAVLink port of their own.  ArduPilot sends the streams that are due in the same
scheduler loop back to back, ATTITUDE first, and SITL's clock does not move inside a loop, so a
SIM_STATE takes the boot time of the ATTITUDE just before it in the byte stream (one that no other
SIM_STATE took; else the sample is dropped and counted).  No host clock is involved: a loaded
machine delays the bytes, not their times.  ``time_boot_ms`` is SITL's clock rounded down to the
millisecond, so half a millisecond is added.

Positions are turned into NED metres about SITL's home with ArduPilot's flat-Earth convention
(:func:`sitl.ardupilot_score.ned_from_latlon_e7`, the inverse of how SITL makes its latitude and
longitude from its NED physics), where SIM_STATE's velocity is their derivative.  :meth:`Truth.fit`
is a weighted least-squares cubic per axis over the samples of a window (positions at their
quantisation, 3 mm; velocities at 5 mm/s), which smooths the 1.1-cm steps of the position;
:meth:`Truth.antenna_e` gives the fitted point back as ECEF (ArduPilot's inverse, then WGS-84).
"""
from __future__ import annotations

from collections import deque

import numpy as np

from .ardupilot_score import ned_from_latlon_e7
from .fly import ned_to_ecef_ardupilot

SIGMA_POS_M = np.array([3.2e-3, 3.2e-3, 1e-4])     # lat/lon 1e-7 deg steps (1.1 cm / sqrt 12); alt float32
SIGMA_VEL_MPS = 5e-3
BOOT_MS_MID_S = 0.5e-3


class Truth:
    """SIM_STATE samples (boot s, NED m, NED m/s) about ``home_e7`` (lat, lon 1e-7 deg, alt m)."""

    def __init__(self, home_lat_e7: int, home_lon_e7: int, home_alt_m: float, keep_s: float = 10.0):
        self.home_lat_e7, self.home_lon_e7, self.home_alt_m = int(home_lat_e7), int(home_lon_e7), float(home_alt_m)
        self.samples: deque = deque()
        self.keep_s = keep_s
        self._att_boot_s: float | None = None
        self.counters = {"sim_state": 0, "attitude": 0, "paired": 0, "unpaired": 0, "non_increasing": 0}

    # -- input ---------------------------------------------------------------------------------
    def on_message(self, msg) -> bool:
        """ATTITUDE / SIM_STATE in byte-stream order; True when a truth sample was added."""
        mt = msg.get_type()
        if mt == "ATTITUDE":
            self.counters["attitude"] += 1
            self._att_boot_s = msg.time_boot_ms * 1e-3 + BOOT_MS_MID_S
            return False
        if mt != "SIM_STATE":
            return False
        self.counters["sim_state"] += 1
        t, self._att_boot_s = self._att_boot_s, None
        if t is None:
            self.counters["unpaired"] += 1
            return False
        if self.samples and t <= self.samples[-1][0]:
            self.counters["non_increasing"] += 1
            return False
        self.counters["paired"] += 1
        ne = ned_from_latlon_e7([msg.lat_int], [msg.lon_int], self.home_lat_e7, self.home_lon_e7)[0]
        self.samples.append((t, np.array([ne[0], ne[1], self.home_alt_m - msg.alt]),
                             np.array([msg.vn, msg.ve, msg.vd], float)))
        while self.samples and self.samples[0][0] < t - self.keep_s:
            self.samples.popleft()
        return True

    @property
    def latest_boot_s(self) -> float | None:
        return self.samples[-1][0] if self.samples else None

    # -- the fit -------------------------------------------------------------------------------
    def fit(self, t_boot_s: float, before_s: float = 0.25, after_s: float = 0.1, min_samples: int = 6):
        """Cubic in (t - t_boot_s) per NED axis over the samples in [t - before, t + after]: a
        (4, 3) coefficient array, or None when the samples do not surround ``t_boot_s``."""
        sel = [s for s in self.samples if t_boot_s - before_s <= s[0] <= t_boot_s + after_s]
        if len(sel) < min_samples or sel[0][0] > t_boot_s or sel[-1][0] < t_boot_s:
            return None
        tau = np.array([s[0] - t_boot_s for s in sel])
        p = np.array([s[1] for s in sel])
        v = np.array([s[2] for s in sel])
        coef = np.empty((4, 3))
        ap = np.vander(tau, 4, increasing=True)                           # 1, tau, tau^2, tau^3
        av = np.column_stack([np.zeros_like(tau), np.ones_like(tau), 2.0 * tau, 3.0 * tau ** 2])
        for ax in range(3):
            a = np.vstack([ap / SIGMA_POS_M[ax], av / SIGMA_VEL_MPS])
            b = np.concatenate([p[:, ax] / SIGMA_POS_M[ax], v[:, ax] / SIGMA_VEL_MPS])
            coef[:, ax] = np.linalg.lstsq(a, b, rcond=None)[0]
        return coef

    @staticmethod
    def ned_at(coef, dt_s: float) -> np.ndarray:
        return coef[0] + dt_s * (coef[1] + dt_s * (coef[2] + dt_s * coef[3]))

    def antenna_e(self, ned_m) -> np.ndarray:
        """ECEF of a NED point about home (ArduPilot's flat Earth back to latitude/longitude)."""
        return ned_to_ecef_ardupilot(ned_m, self.home_lat_e7, self.home_lon_e7,
                                     int(round(self.home_alt_m * 1000.0)))


def home_e7(lat_deg: float, lon_deg: float) -> tuple[int, int]:
    return int(round(lat_deg * 1e7)), int(round(lon_deg * 1e7))


__all__ = ["Truth", "home_e7"]
