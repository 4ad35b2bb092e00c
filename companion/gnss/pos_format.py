"""RTKLIB's solution file (``.pos``), as rnx2rtkp writes it and rtkplot / pos2kml read it.

One header block of ``%`` lines (program, inputs, options, the column line), then one line per
epoch: time (``yyyy/mm/dd hh:mm:ss.sss`` GPST, or GPS week and seconds of week), position
(latitude/longitude in degrees and ellipsoidal height, or ECEF x/y/z), ``Q`` (1 fix, 2 float,
3 SBAS, 4 DGPS, 5 single, 6 PPP), ``ns`` (satellites), standard deviations with the signed square
roots of the covariances (``sdne = sign(c_ne) sqrt(|c_ne|)``, RTKLIB's convention), age of the
differential corrections (s) and the ambiguity ratio.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

import numpy as np

from ..messages import SECONDS_PER_WEEK
from ..nav.earth import C_n_e, ecef_to_geodetic

GPS_EPOCH = datetime(1980, 1, 6, tzinfo=timezone.utc)
Q_FIX, Q_FLOAT, Q_SBAS, Q_DGPS, Q_SINGLE, Q_PPP = 1, 2, 3, 4, 5, 6


@dataclass
class PosRecord:
    t_gps: float
    r_e: np.ndarray
    cov_e: np.ndarray          # 3x3 ECEF covariance (m^2)
    quality: int
    n_sats: int
    age_s: float = 0.0
    ratio: float = 0.0


def _signed_sqrt(c: float) -> float:
    return math.copysign(math.sqrt(abs(c)), c)


def gpst_calendar(t_gps: float) -> str:
    t = GPS_EPOCH + timedelta(seconds=round(t_gps, 3))
    return t.strftime("%Y/%m/%d %H:%M:%S.") + f"{t.microsecond // 1000:03d}"


def parse_gpst(text: str) -> float:
    """GPS seconds of a GPST calendar time as RTKLIB writes it ('2021/09/22 06:31:00', seconds may
    have decimals) or in ISO form ('2021-09-22T06:31:00'); ValueError otherwise."""
    t = text.strip().replace("T", " ").replace("-", "/")
    date, _, clock = t.partition(" ")
    try:
        y, mo, d = (int(v) for v in date.split("/"))
        h, mi, s = (clock.split(":") + ["0", "0", "0"])[:3] if clock else ("0", "0", "0")
        day = datetime(y, mo, d, int(h), int(mi), tzinfo=timezone.utc)
    except ValueError:
        raise ValueError(f"not a GPST time (YYYY/MM/DD HH:MM:SS): {text!r}") from None
    return (day - GPS_EPOCH).total_seconds() + float(s)


def span_text(t0_gps: float, t1_gps: float) -> str:
    """A span of GPS time for a person: '2005/04/02 00:00:00 to 00:59:30 GPST' (the date once
    when both ends share it)."""
    a, b = gpst_calendar(t0_gps)[:19], gpst_calendar(t1_gps)[:19]
    return f"{a} to {b[11:] if a[:10] == b[:10] else b} GPST"


def _time_field(t_gps: float, time_format: str) -> str:
    if time_format == "week":
        week = int(t_gps // SECONDS_PER_WEEK)
        return f"{week:4d} {t_gps - week * SECONDS_PER_WEEK:10.3f}"
    return gpst_calendar(t_gps)


def format_pos(records, *, program: str, inputs=(), options: dict | None = None, coords: str = "llh",
               time_format: str = "gpst") -> str:
    """The whole file as text; ``coords`` 'llh' or 'xyz', ``time_format`` 'gpst' or 'week'."""
    if coords not in ("llh", "xyz") or time_format not in ("gpst", "week"):
        raise ValueError("coords: llh|xyz, time_format: gpst|week")
    lines = [f"% program   : {program}"]
    lines += [f"% inp file  : {p}" for p in inputs]
    recs = list(records)
    if recs:
        lines.append(f"% obs start : {gpst_calendar(recs[0].t_gps)} GPST")
        lines.append(f"% obs end   : {gpst_calendar(recs[-1].t_gps)} GPST")
    for k, v in (options or {}).items():
        lines.append(f"% {k:<10s}: {v}")
    lines.append("%")
    lines.append("% (" + ("lat/lon/height=WGS84/ellipsoidal" if coords == "llh" else "x/y/z-ecef=WGS84")
                 + ",Q=1:fix,2:float,3:sbas,4:dgps,5:single,6:ppp,ns=# of satellites)")
    tcol = "GPST" if time_format == "gpst" else "GPST week   tow(s)"
    tcol = f"%  {tcol:<21s}" if time_format == "gpst" else f"% {tcol:<16s}"
    if coords == "llh":
        lines.append(tcol + "  latitude(deg) longitude(deg)  height(m)   Q  ns   sdn(m)   sde(m)   sdu(m)"
                            "  sdne(m)  sdeu(m)  sdun(m) age(s)  ratio")
    else:
        lines.append(tcol + "    x-ecef(m)      y-ecef(m)      z-ecef(m)   Q  ns   sdx(m)   sdy(m)   sdz(m)"
                            "  sdxy(m)  sdyz(m)  sdzx(m) age(s)  ratio")
    for r in recs:
        cov = np.asarray(r.cov_e, dtype=float)
        if coords == "llh":
            lat, lon, h = ecef_to_geodetic(np.asarray(r.r_e, dtype=float))
            C = C_n_e(lat, lon)
            enu = C[:, [1, 0]]                          # east, north columns of NED
            E = np.column_stack([enu, -C[:, 2]])       # east, north, up
            q = E.T @ cov @ E
            # RTKLIB: sdn sde sdu sdne sdeu sdun
            sd = (q[1, 1], q[0, 0], q[2, 2], q[1, 0], q[0, 2], q[2, 1])
            pos = f"{math.degrees(lat):14.9f} {math.degrees(lon):14.9f} {h:10.4f}"
        else:
            sd = (cov[0, 0], cov[1, 1], cov[2, 2], cov[0, 1], cov[1, 2], cov[2, 0])
            pos = f"{r.r_e[0]:14.4f} {r.r_e[1]:14.4f} {r.r_e[2]:14.4f}"
        sds = " ".join(f"{math.sqrt(max(v, 0.0)):8.4f}" for v in sd[:3]) + " " + \
            " ".join(f"{_signed_sqrt(v):8.4f}" for v in sd[3:])
        ratio = min(r.ratio if math.isfinite(r.ratio) else 999.9, 999.9)
        lines.append(f"{_time_field(r.t_gps, time_format)} {pos} {r.quality:3d} {r.n_sats:3d} {sds} "
                     f"{r.age_s:6.2f} {ratio:6.1f}")
    return "\n".join(lines) + "\n"


FIX_STATE_Q = {"fixed": Q_FIX, "float": Q_FLOAT}


def pos_records_from_nav_solutions(solutions) -> list[PosRecord]:
    """Fused solutions (:class:`companion.messages.NavSolution`, the IMU's position) as records:
    the covariance from the north/east/down sigmas (the filter's marginals; their correlations
    are not in a solution), Q 1/2 from the carrier-phase fix state, 5 otherwise (an INS solution
    has no RTKLIB class of its own), ns 0 (a solution does not carry it).  'init' solutions and
    non-finite positions are left out."""
    out = []
    for s in solutions:
        r = np.asarray(s.r_e, dtype=float)
        sig = np.asarray(s.sigma_r_n_m, dtype=float)
        if s.status == "init" or not (np.all(np.isfinite(r)) and np.all(np.isfinite(sig))):
            continue
        lat, lon, _ = ecef_to_geodetic(r)
        C = C_n_e(lat, lon)
        out.append(PosRecord(float(s.t_gps), r, C @ np.diag(sig ** 2) @ C.T,
                             FIX_STATE_Q.get(getattr(s, "fix_state", "none"), Q_SINGLE), 0))
    return out


def write_pos(path, records, **kw) -> None:
    with open(path, "w") as fh:
        fh.write(format_pos(records, **kw))


__all__ = ["PosRecord", "format_pos", "write_pos", "gpst_calendar", "pos_records_from_nav_solutions", "Q_FIX",
           "Q_FLOAT", "Q_DGPS", "Q_SINGLE"]
