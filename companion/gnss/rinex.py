"""RINEX 2.x / 3.x / 4 navigation files (GPS LNAV, Galileo I/NAV and F/NAV, BeiDou D1/D2, QZSS
LNAV, GLONASS) and the fixed-column helpers the observation reader (:mod:`.rinex_obs`) shares.

Own fixed-column parsers (no georinex at run time): a 1-h 30-s file reads in well under a second.

* :func:`read_rinex_nav` -> list of :class:`GpsEphemeris` of G/E/C/J, and on request GLONASS's
  (:class:`~.glonass.GlonassEphemeris`, RINEX 3); SBAS and NavIC skipped.
* :func:`read_rinex_nav_header_iono` -> Klobuchar (alpha[4], beta[4]) from the header, or None.

Conventions: RINEX nav angles are already radians, the GPS and Galileo weeks in the file are
continuous GPS weeks (no 1024 roll-over); BeiDou records are in BDT (epoch, toe, BDT week), converted
as :class:`GpsEphemeris` describes.
"""
from __future__ import annotations

import datetime as _dt
import re
from pathlib import Path

import numpy as np

from .ephemeris_store import MIN_FIT_INTERVAL_H
from .glonass import GlonassEphemeris, gps_minus_utc_s
from .glonass import ephemeris_from_rinex as glonass_ephemeris_from_rinex
from ..messages import SYSTEM_WEEK_TO_GPS_WEEK, GpsEphemeris

_GPS_EPOCH = _dt.datetime(1980, 1, 6)
_SECONDS_PER_WEEK = 604800.0
_NAV_LINES = {"G": 8, "J": 8, "E": 8, "C": 8, "I": 8, "R": 4, "S": 4}

def calendar_to_t_gps(year: int, month: int, day: int, hour: int, minute: int, sec: float) -> float:
    if year < 100:
        year += 2000 if year < 80 else 1900
    d = _dt.datetime(year, month, day, hour, minute) - _GPS_EPOCH
    return d.days * 86400.0 + d.seconds + sec


def header_float(s: str) -> float:
    """A header or navigation field: blank is 0, Fortran D exponents allowed."""
    s = s.strip()
    if not s:
        return 0.0
    return float(s.replace("D", "E").replace("d", "e"))


#: file names of compressed RINEX: gzip/Unix compress, Hatanaka (.crx, RINEX 2 .YYd), zip, bzip2
_COMPRESSED = re.compile(r"(\.(gz|Z|zip|bz2|crx)|\.\d\dd)$", re.IGNORECASE)


def open_text(path) -> list[str]:
    """Lines of a RINEX file, plain or compressed: gzip, .Z, Hatanaka (.crx, .YYd) and their
    gzipped forms are decompressed by the ``hatanaka`` package (RNXCMP's own C code), not here."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"RINEX file not found: {p}")
    if _COMPRESSED.search(p.name):
        from ..extras import require
        hatanaka = require("hatanaka", "rinex", f"reading the compressed RINEX file {p.name}")
        try:
            return hatanaka.decompress(p).decode("ascii", errors="replace").splitlines()
        except hatanaka.HatanakaException as exc:
            raise ValueError(f"{p}: cannot decompress: {exc}") from None
    return p.read_text(errors="replace").splitlines()


def header_end(lines: list[str]) -> int:
    for i, ln in enumerate(lines):
        if ln[60:].strip().startswith("END OF HEADER"):
            return i + 1
    raise ValueError("RINEX: no END OF HEADER")


# ---------------------------------------------------------------------------------------------
# navigation
# ---------------------------------------------------------------------------------------------

def read_rinex_nav_header_iono(path) -> tuple[np.ndarray, np.ndarray] | None:
    """Klobuchar (alpha[4] s, s/semicircle...; beta[4]) from a RINEX 2 (ION ALPHA/BETA) or RINEX 3
    (IONOSPHERIC CORR GPSA/GPSB) navigation header, or None when absent.  Units as broadcast
    (IS-GPS-200 20.3.3.5.1.7: alpha_n in s/semicircle^n, beta_n in s/semicircle^n).  Without GPS
    coefficients, QZSS's (QZSA/QZSB: the same model and units, IS-QZSS-PNT 5.2.2, fitted over the
    QZSS service area) are returned: a short u-blox log often has QZSS's and not yet GPS's."""
    lines = open_text(path)
    alpha = beta = None
    qzs: dict[str, list[float]] = {}
    for ln in lines[:header_end(lines)]:
        label = ln[60:].strip()
        if label == "ION ALPHA":
            alpha = [header_float(ln[2 + 12 * k:14 + 12 * k]) for k in range(4)]
        elif label == "ION BETA":
            beta = [header_float(ln[2 + 12 * k:14 + 12 * k]) for k in range(4)]
        elif label == "IONOSPHERIC CORR":
            vals = [header_float(ln[5 + 12 * k:17 + 12 * k]) for k in range(4)]
            if ln[:4] == "GPSA":
                alpha = vals
            elif ln[:4] == "GPSB":
                beta = vals
            elif ln[:4] in ("QZSA", "QZSB"):
                qzs[ln[:4]] = vals
    if (alpha is None or beta is None) and len(qzs) == 2:
        alpha, beta = qzs["QZSA"], qzs["QZSB"]
    if alpha is None or beta is None:
        return None
    return np.array(alpha, float), np.array(beta, float)


#: validity of a broadcast ephemeris, hours either side of toe x 2 (RTKLIB MAXDTOE_*: GPS and QZSS
#: 2 h, Galileo 4 h, BeiDou 6 h); the store accepts |t - toe| <= fit_interval_h / 2
FIT_INTERVAL_H = {"G": 4.0, "J": 4.0, **MIN_FIT_INTERVAL_H}
#: Galileo data-source bits (RINEX 3 field 'Data sources'): I/NAV E1-B (0), E5b-I (2), clock for E5b,E1
#: (9); F/NAV E5a-I (1), clock for E5a,E1 (8)
GAL_INAV_BITS = (1 << 0) | (1 << 2) | (1 << 9)
GAL_FNAV_BITS = (1 << 1) | (1 << 8)
#: SISA 'no accuracy prediction available' (RINEX -1): RTKLIB's STD_GAL_NAPA, m
GAL_NAPA_SIGMA_M = 500.0


def _fit_interval_h(value: float) -> float:
    """RINEX stores hours; 0 (unknown) or the raw ICD flag (0/1) mean the standard 4 h."""
    return value if value >= 4.0 else 4.0


def _eph_from_fields(sat: str, t_oc_gps: float, v: list[float]) -> GpsEphemeris:
    """``v`` = 29+ broadcast orbit fields in RINEX order, starting with af0.

    GPS/QZSS: IODE, TGD, SV accuracy, health, fit interval as broadcast.  Galileo: IODnav as iode,
    SISA as ura_m (NAPA -> ``GAL_NAPA_SIGMA_M``), SV health word, BGD(E1,E5b) for an I/NAV record or
    BGD(E1,E5a) for an F/NAV one as tgd_s; the Galileo week of RINEX 3 is already a GPS week.
    BeiDou: the epoch is BDT and toe is BDT seconds, the BDT week gets +1356, AODE as iode, SatH1
    as health, TGD1 as tgd_s and TGD2 as tgd2_s.  ``t_oc_gps`` is the epoch read *as if* GPS time
    (the calendar of the record), which for BeiDou is the BDT calendar.
    """
    sys_ = sat[0]
    week = int(round(v[21])) + SYSTEM_WEEK_TO_GPS_WEEK["C"] * (sys_ == "C")
    toe = v[11]
    # toc as seconds of the toe week in the system's own time (may fall outside [0, 604800) at a
    # week boundary; the ephemeris code folds time differences into +-half a week)
    toc = t_oc_gps - week * _SECONDS_PER_WEEK
    tgd, tgd2, ura, iodc = v[25], 0.0, v[23], int(round(v[26]))
    fit = FIT_INTERVAL_H.get(sys_, 4.0)
    if sys_ == "G":
        fit = _fit_interval_h(v[29] if len(v) > 29 else 0.0)
    elif sys_ == "E":
        src = int(round(v[20]))
        inav = bool(src & GAL_INAV_BITS) or not (src & GAL_FNAV_BITS)
        tgd, tgd2 = (v[26], 0.0) if inav else (v[25], v[26])
        ura = ura if ura >= 0.0 else GAL_NAPA_SIGMA_M
        iodc = 0                         # Galileo has no IODC
    elif sys_ == "C":
        tgd2 = v[26]
        iodc = int(round(v[28])) if len(v) > 28 else 0     # AODC
    return GpsEphemeris(
        sat=sat, week=week, toe_s=toe, toc_s=toc,
        sqrt_a=v[10], e=v[8], i0_rad=v[15], omega0_rad=v[13], omega_rad=v[17], m0_rad=v[6],
        delta_n_radps=v[5], idot_radps=v[19], omega_dot_radps=v[18],
        cuc_rad=v[7], cus_rad=v[9], crc_m=v[16], crs_m=v[4], cic_rad=v[12], cis_rad=v[14],
        af0_s=v[0], af1_sps=v[1], af2_sps2=v[2], tgd_s=tgd, tgd2_s=tgd2,
        iode=int(round(v[3])), iodc=iodc, health=int(round(v[24])),
        ura_m=ura, fit_interval_h=fit)


def _is_fnav(sat: str, v: list[float]) -> bool:
    """A Galileo record whose data-source field says F/NAV only."""
    src = int(round(v[20]))
    return sat[0] == "E" and bool(src & GAL_FNAV_BITS) and not src & GAL_INAV_BITS


def _prefer_inav(recs: list[tuple[GpsEphemeris, bool]]) -> list[GpsEphemeris]:
    """Drop Galileo F/NAV records that have an I/NAV twin (same satellite, IODnav, toe): the I/NAV
    clock refers to E1/E5b, the one an E1 user with BGD(E1,E5b) needs (RTKLIB's default selection).
    ``recs``: (ephemeris, is F/NAV)."""
    inav = {(e.sat, e.iode, e.toe_s) for e, fnav in recs if e.sat[0] == "E" and not fnav}
    return [e for e, fnav in recs if not (fnav and (e.sat, e.iode, e.toe_s) in inav)]


def read_rinex_nav(path, systems: str = "GECJ", counts: dict | None = None) -> list:
    """Keplerian ephemerides of ``systems`` (GPS, Galileo, BeiDou, QZSS) from a RINEX 2.x GPS ('N'),
    3.x or 4.x navigation file, in file order (Galileo F/NAV records with an I/NAV twin dropped),
    then, when ``systems`` has 'R', a RINEX 3 file's GLONASS records or a RINEX 2 GLONASS ('G')
    file's (:class:`~.glonass.GlonassEphemeris`).  SBAS and NavIC records, RINEX 4's GLONASS and CNAV
    ephemerides and its ION / STO / EOP records are skipped.  A record that cannot be read (a file
    cut mid-record, a corrupt line) is left out and counted in ``counts['unreadable records']``;
    reading resumes at the next record's first line."""
    counts = {} if counts is None else counts
    counts.setdefault("unreadable records", 0)
    lines = open_text(path)
    head = header_end(lines)
    version = header_float(lines[0][:9])
    file_sys = lines[0][40:41].upper() if version >= 3 else "G"
    out: list[GpsEphemeris] = []
    recs: list[tuple[GpsEphemeris, bool]] = []
    glonass: list[GlonassEphemeris] = []
    leap_s = header_leap_seconds(lines, head)
    i = head
    n = len(lines)
    if version < 3:
        kind = lines[0][20:21].upper()
        if kind == "G":                          # 'G: GLONASS NAV DATA' (a .g file beside the .n)
            if "R" not in systems:
                return []
            return _rinex2_records(lines, head, 4, counts,
                                   lambda prn, t, vals: _glonass_from_fields(prn, t, vals, leap_s))
        if kind not in ("N", " "):
            raise ValueError(f"{path}: a RINEX 2 navigation file of another kind ({lines[0][20:40].strip()!r}); "
                             "GPS ('N') and GLONASS ('G') ones are read")
        if "G" not in systems:
            return out
        return _rinex2_records(lines, head, 8, counts,
                               lambda prn, t, vals: _eph_from_fields(f"G{prn:02d}", t, vals))
    while i < n:
        ln = lines[i]
        if not ln.strip():
            i += 1
            continue
        if ln.startswith(">"):
            # RINEX 4: each record under a '> EPH G01 LNAV' line (also ION, STO, EOP records and
            # CNAV / CNV2 ephemerides, of other lengths), running to the next '>' line; the
            # Keplerian messages read here keep RINEX 3's eight lines
            j = i + 1
            while j < n and not lines[j].startswith(">"):
                j += 1
            f = ln[1:].split()
            sys_ = f[1][:1] if len(f) >= 3 else ""
            if f[:1] == ["EPH"] and (sys_, f[2]) in _V4_KEPLER_MESSAGES and sys_ in systems and j - i > 8:
                recs.append(_v3_nav_record(lines, i + 1, sys_))
            i = j
            continue
        sys_ = ln[0] if ln[0] != " " else file_sys
        if sys_ not in FIT_INTERVAL_H:
            # GLONASS, SBAS, NavIC: a record that starts with its satellite's letter runs to the next
            # one's line (GLONASS has 4 lines, 5 in RINEX 3.05)
            j = i + _NAV_LINES.get(sys_, 8)
            if ln[0] != " ":
                j = i + 1
                while j < n and lines[j][:1] == " ":
                    j += 1
            if sys_ == "R" and "R" in systems:
                eph = _glonass_record(lines, i, j, leap_s)
                if eph is not None:
                    glonass.append(eph)
            i = j
            continue
        if sys_ not in systems:
            i += 8
            continue
        try:
            if i + 8 > n or any(_V3_RECORD.match(lines[k]) for k in range(i + 1, i + 8)):
                raise IndexError("fewer than 8 lines before the next record or the end of the file")
            recs.append(_v3_nav_record(lines, i, sys_))
        except (ValueError, IndexError):
            counts["unreadable records"] += 1
            i = _next_record(lines, i + 1, _V3_RECORD)
            continue
        i += 8
    return _prefer_inav(recs) + glonass


#: the first line of a navigation record: RINEX 2 'PP YY MM DD HH MM SS.S', RINEX 3 'G01 YYYY MM DD'
_V2_RECORD = re.compile(r"^[ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d [ \d]\d\.\d")
_V3_RECORD = re.compile(r"^[A-Z][ \d]\d \d{4} \d\d \d\d \d\d \d\d \d\d")


def nav_reading_notes(counts: dict) -> str:
    """What :func:`read_rinex_nav` left out, for a person ('' when nothing)."""
    n = counts.get("unreadable records", 0)
    if not n:
        return ""
    return f"{n} record{'' if n == 1 else 's'} unreadable (a file cut mid-record or a corrupt line) skipped"


def _next_record(lines: list[str], i: int, first_line: re.Pattern) -> int:
    """The index of the next record's first line from ``i`` on (len(lines) when none)."""
    while i < len(lines) and not first_line.match(lines[i]):
        i += 1
    return i


def header_leap_seconds(lines: list[str], head: int) -> int | None:
    """GPS - UTC from a RINEX 3 header's LEAP SECONDS line (navigation or observation file), None
    without one."""
    for ln in lines[:head]:
        if ln[60:].strip().startswith("LEAP SECONDS"):
            try:
                return int(ln[:6])
            except ValueError:
                return None
    return None


def _rinex2_records(lines: list[str], head: int, n_lines: int, counts: dict, make) -> list:
    """The records of a RINEX 2 navigation file ('N': GPS, 8 lines; 'G': GLONASS, 4), each
    ``make(prn, epoch, fields)`` (None: left out): the first line 'PP YY MM DD HH MM SS.S' and three
    fields, then four fields a line after 3 blanks (RINEX 3's layout, one column to the left and a
    two-digit year).  A record that cannot be read (a file cut mid-record, a corrupt line) is
    counted in ``counts['unreadable records']``; reading resumes at the next record's first line."""
    out = []
    i, n = head, len(lines)
    while i < n:
        ln = lines[i]
        if not ln.strip():
            i += 1
            continue
        try:
            if i + n_lines > n:
                raise IndexError("the file ends inside the record")
            yy, mo, dd, hh, mi = (int(ln[3 + 3 * k:5 + 3 * k]) for k in range(5))
            vals = [header_float(ln[22:41]), header_float(ln[41:60]), header_float(ln[60:79])]
            for k in range(1, n_lines):
                for c in range(4):
                    vals.append(header_float(lines[i + k][3 + 19 * c:22 + 19 * c]))
            eph = make(int(ln[0:2]), calendar_to_t_gps(yy, mo, dd, hh, mi, header_float(ln[17:22])), vals)
        except (ValueError, IndexError):
            counts["unreadable records"] += 1
            i = _next_record(lines, i + 1, _V2_RECORD)
            continue
        i += n_lines
        if eph is not None:
            out.append(eph)
    return out


def _glonass_from_fields(prn: int, t_utc: float, vals: list[float], leap_s: int | None) -> GlonassEphemeris | None:
    """A GLONASS ephemeris from its record's 15 fields (epoch in UTC; ``leap_s`` from the header,
    or by the date when the header has none); None for a record cut short or with a frequency
    channel outside -7..+13 (its carriers would be wrong)."""
    if len(vals) < 15 or not -7 <= vals[10] <= 13:
        return None
    leap = leap_s if leap_s is not None else gps_minus_utc_s(t_utc)
    return glonass_ephemeris_from_rinex(f"R{prn:02d}", t_utc, leap, vals)


def _glonass_record(lines: list[str], i: int, j: int, leap_s: int | None) -> GlonassEphemeris | None:
    """The GLONASS record of RINEX 3 lines ``i`` to ``j`` (:func:`_glonass_from_fields`)."""
    ln = lines[i]
    yy, mo, dd, hh, mi, ss = (int(ln[4:8]), int(ln[9:11]), int(ln[12:14]), int(ln[15:17]),
                              int(ln[18:20]), header_float(ln[21:23]))
    vals = [header_float(ln[23:42]), header_float(ln[42:61]), header_float(ln[61:80])]
    for k in range(i + 1, min(j, i + 4)):
        row = lines[k]
        for c in range(4):
            vals.append(header_float(row[4 + 19 * c:23 + 19 * c]))
    return _glonass_from_fields(int(ln[1:3]), calendar_to_t_gps(yy, mo, dd, hh, mi, ss), vals, leap_s)


#: RINEX 4's Keplerian ephemeris messages, the ones read (the legacy navigation messages; CNAV,
#: CNV1-3 of the modernised signals are skipped)
_V4_KEPLER_MESSAGES = {("G", "LNAV"), ("J", "LNAV"), ("E", "INAV"), ("E", "FNAV"), ("C", "D1"), ("C", "D2")}


def _v3_nav_record(lines: list[str], i: int, sys_: str) -> tuple[GpsEphemeris, bool]:
    """(ephemeris, is Galileo F/NAV only) of the eight-line RINEX 3 record starting at line ``i``."""
    ln = lines[i]
    n = len(lines)
    prn = int(ln[1:3])
    yy, mo, dd, hh, mi, ss = (int(ln[4:8]), int(ln[9:11]), int(ln[12:14]), int(ln[15:17]),
                              int(ln[18:20]), header_float(ln[21:23]))
    vals = [header_float(ln[23:42]), header_float(ln[42:61]), header_float(ln[61:80])]
    for k in range(1, 8):
        row = lines[i + k] if i + k < n else ""
        for c in range(4):
            vals.append(header_float(row[4 + 19 * c:23 + 19 * c]))
    sat = f"{sys_}{prn:02d}"
    return _eph_from_fields(sat, calendar_to_t_gps(yy, mo, dd, hh, mi, ss), vals), _is_fnav(sat, vals)


# ---------------------------------------------------------------------------------------------
# observations
# ---------------------------------------------------------------------------------------------
