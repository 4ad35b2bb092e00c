"""The companion's state on the ground station's screen: NAMED_VALUE_FLOAT at a low rate.

Mission Planner (Status tab, quick view) and QGroundControl (MAVLink inspector, widgets) show
NAMED_VALUE_FLOAT by name, so an operator sees whether the companion is feeding the autopilot and
how good it says it is, without a laptop on the companion.  Names (at most 10 characters):

``CC_STAT`` solution status code (the field log's ``STATUS_CODES``: 0 init, 1 nav, 2 coasting,
3 untrusted, 4 diverged, 5 converging, 6 suspect), ``CC_INJ`` 1 while estimates are injected, ``CC_MODE`` 1 tight / 2 loose / 0 none,
``CC_SIGH`` / ``CC_SIGV`` horizontal / vertical 1-sigma (m), ``CC_HPL`` the horizontal protection
level (m) when the solution carries one, ``CC_RTK`` 0 none / 1 float / 2 fixed (the filter's fix state, or the
extras' ``rtk_fix``).
"""
from __future__ import annotations

import math

import numpy as np

from ..log_records import FIX_CODES, MODE_CODES, STATUS_CODES      # the field log's codes: one table
from ..messages import NavSolution
from .mavlink_codec import ENCODER


def named_values(sol: NavSolution, time_boot_ms: int) -> list:
    """NAMED_VALUE_FLOAT messages describing one solution."""
    sig = np.asarray(sol.sigma_r_n_m, float)
    x = sol.extras
    vals = [("CC_STAT", float(STATUS_CODES.get(sol.status, 255))), ("CC_INJ", 1.0 if x.get("inject") else 0.0),
            ("CC_MODE", float(MODE_CODES.get(x.get("mode", "none"), 0))),
            ("CC_SIGH", float(math.hypot(sig[0], sig[1]))), ("CC_SIGV", float(sig[2]))]
    for key, name in (("hpl_m", "CC_HPL"), ("protection_level_h_m", "CC_HPL")):
        if key in x and math.isfinite(float(x[key])):
            vals.append((name, float(x[key])))
            break
    fix = sol.fix_state if sol.fix_state != "none" else x.get("rtk_fix", "none")   # the filter's RTK state
    vals.append(("CC_RTK", float(FIX_CODES.get(fix, 0))))
    t = int(time_boot_ms) & 0xFFFFFFFF
    return [ENCODER.named_value_float_encode(t, name.encode("ascii"), v if math.isfinite(v) else -1.0)
            for name, v in vals]


__all__ = ["named_values"]
