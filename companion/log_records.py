"""The field log's own records: a solution as the pipeline produced it (:func:`encode_solution`,
every float64 bit kept, so a replay compares bit for bit) and the configuration event that makes
a log self-describing (:func:`config_event`).  Older solution record versions still decode."""
from __future__ import annotations

import json
import math
import struct

import numpy as np

from .messages import NavSolution

STATUS_CODES = {"init": 0, "nav": 1, "coasting": 2, "untrusted": 3, "diverged": 4, "converging": 5,
                "suspect": 6}
STATUS_NAMES = {v: k for k, v in STATUS_CODES.items()}
MODE_CODES = {"none": 0, "tight": 1, "loose": 2}
MODE_NAMES = {v: k for k, v in MODE_CODES.items()}

# solution record: version, status, inject, mode, reset_counter, imu_count, t_boot_us, t_gps,
# r_e(3) v_e(3) C_b_e(9) sigma_r(3) sigma_v(3) sigma_att(3), last_gnss_update_t_gps;
# version 2 appends hpl_m (the horizontal protection level, NaN when there is none);
# version 3 appends the RTK fix state (code of FIX_CODES), the number of fixed DD ambiguities
# and the LAMBDA ratio (NaN when not fixed)
_SOL_V1 = struct.Struct("<BBBBIQq d 3d 3d 9d 3d 3d 3d d".replace(" ", ""))
_SOL_V2 = struct.Struct("<BBBBIQq d 3d 3d 9d 3d 3d 3d d d".replace(" ", ""))
_SOL = struct.Struct("<BBBBIQq d 3d 3d 9d 3d 3d 3d d d BH d".replace(" ", ""))
_SOL_BY_VERSION = {1: _SOL_V1, 2: _SOL_V2, 3: _SOL}
SOLUTION_RECORD_VERSION = 3
FIX_CODES = {"none": 0, "float": 1, "fixed": 2}
FIX_NAMES = {v: k for k, v in FIX_CODES.items()}

def encode_solution(sol: NavSolution) -> bytes:
    """Compact binary encoding of a solution for the field log (every float64 bit kept)."""
    x = sol.extras
    return _SOL.pack(SOLUTION_RECORD_VERSION, STATUS_CODES.get(sol.status, 255), int(bool(x.get("inject"))),
                     MODE_CODES.get(x.get("mode", "none"), 0), int(sol.reset_counter) & 0xFFFFFFFF,
                     int(x.get("imu_count", 0)), int(x.get("t_boot_us", -1)), float(sol.t_gps),
                     *np.asarray(sol.r_e, float).tolist(), *np.asarray(sol.v_e, float).tolist(),
                     *np.asarray(sol.C_b_e, float).reshape(9).tolist(),
                     *np.asarray(sol.sigma_r_n_m, float).tolist(), *np.asarray(sol.sigma_v_n_mps, float).tolist(),
                     *np.asarray(sol.sigma_att_rad, float).tolist(), float(sol.last_gnss_update_t_gps),
                     float(x.get("hpl_m", math.nan)), FIX_CODES.get(sol.fix_state, 0),
                     max(0, min(int(sol.n_fixed), 0xFFFF)), float(sol.fix_ratio))


def decode_solution(data: bytes) -> NavSolution:
    """Any record version (1: old field logs without the protection level, 2: without the RTK
    fix state)."""
    rec = _SOL_BY_VERSION.get(data[0], _SOL) if data else _SOL
    v = rec.unpack(data)
    _ver, st, inj, mode, rc, n, tb, t = v[:8]
    f = np.array(v[8:34], float)
    extras = {"inject": bool(inj), "mode": MODE_NAMES.get(mode, "none"), "imu_count": n, "t_boot_us": tb}
    if len(f) > 25:
        extras["hpl_m"] = float(f[25])
    fix = {}
    if len(v) > 34:
        fix = {"fix_state": FIX_NAMES.get(v[34], "none"), "n_fixed": int(v[35]), "fix_ratio": float(v[36])}
    return NavSolution(t, f[0:3], f[3:6], f[6:15].reshape(3, 3), f[15:18], f[18:21], f[21:24],
                       STATUS_NAMES.get(st, "untrusted"), float(f[24]), rc, extras, **fix)


def solution_records_equal(logged: bytes, produced: bytes) -> bool:
    """A logged solution record against one this version produced: an older record (an old
    field log: version 1 or 2) is compared on the fields it has."""
    old = _SOL_BY_VERSION.get(logged[0]) if logged else None
    if (old is not None and old is not _SOL and produced[:1] == bytes([SOLUTION_RECORD_VERSION])
            and len(logged) == old.size):
        return logged[1:] == produced[1:old.size]
    return logged == produced


def config_event(config, event: str = "config") -> bytes:
    """The 'event' record that makes a log self-describing (replay rebuilds the pipeline from it):
    the configuration with its secrets written as ``***`` (replay does not need them; the logs get
    shared) and the antenna calibration file's SHA-256.  ``event``: 'config' (the start of a file)
    or 'config_change' (a ground station set a parameter; replay applies it at that record)."""
    from .nav.rtk_antennas import antennas_digest
    return json.dumps({"event": event, "toml": config.to_toml(comments=False, redact=True),
                       **antennas_digest(config)}).encode()


__all__ = ["encode_solution", "decode_solution", "solution_records_equal", "config_event", "STATUS_CODES",
           "STATUS_NAMES", "MODE_CODES", "MODE_NAMES", "FIX_CODES", "FIX_NAMES", "SOLUTION_RECORD_VERSION"]
