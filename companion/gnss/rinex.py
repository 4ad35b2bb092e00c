"""RINEX 2.x / 3.x readers: navigation files (GPS LNAV, Galileo I/NAV and F/NAV, BeiDou D1/D2,
QZSS LNAV) and observation files (any system).

Own fixed-column parsers (no georinex at run time): a 1-h 30-s file reads in well under a second.

* :func:`read_rinex_nav` -> list of :class:`GpsEphemeris` of G/E/C/J, and on request GLONASS's
  (:class:`~.glonass.GlonassEphemeris`, RINEX 3); SBAS and NavIC skipped.
* :func:`read_rinex_nav_header_iono` -> Klobuchar (alpha[4], beta[4]) from the header, or None.
* :func:`read_rinex_obs` -> (header dict, list of :class:`GnssEpoch`).

Conventions: RINEX nav angles are already radians, the GPS and Galileo weeks in the file are
continuous GPS weeks (no 1024 roll-over); BeiDou records are in BDT (epoch, toe, BDT week), converted
as :class:`GpsEphemeris` describes.  Observation time tags are the receiver's GPS time tags, converted to continuous
GPS seconds.  RINEX 2 observation types are mapped onto RINEX 3 codes (RTKLIB's convention):
C1->C1C, P1->C1W, L1->L1C, D1->D1C, S1->S1C, P2->C2W, L2->L2W (L2C if the file has C2 but no P2),
C2->C2X... see ``_RINEX2_MAP``.  One :class:`SatObservation` is produced per satellite per signal,
named 'L' + band + attribute ('L1C', 'L2W', 'L1W', ...).  LLI bit 0 -> ``loss_of_lock``; in
RINEX 3 LLI bit 1 -> ``half_cycle_ambiguous``.
"""
from __future__ import annotations

import datetime as _dt
import math
import re
import sys
from pathlib import Path

import numpy as np

from .ephemeris_store import MIN_FIT_INTERVAL_H
from .glonass import GlonassEphemeris, gps_minus_utc_s
from .glonass import ephemeris_from_rinex as glonass_ephemeris_from_rinex
from .signals import FREQUENCY_HZ
from ..messages import (SPEED_OF_LIGHT_MPS, SYSTEM_TO_GPS_S, SYSTEM_WEEK_TO_GPS_WEEK, GnssEpoch, GpsEphemeris,
                        SatObservation)

_GPS_EPOCH = _dt.datetime(1980, 1, 6)
_SECONDS_PER_WEEK = 604800.0
_NAV_LINES = {"G": 8, "J": 8, "E": 8, "C": 8, "I": 8, "R": 4, "S": 4}

# RINEX 2 observation type -> RINEX 3 code (type letter, band, attribute)
_RINEX2_MAP = {
    "C1": "C1C", "P1": "C1W", "L1": "L1C", "D1": "D1C", "S1": "S1C",
    "C2": "C2X", "P2": "C2W", "L2": "L2W", "D2": "D2W", "S2": "S2W",
    "C5": "C5X", "L5": "L5X", "D5": "D5X", "S5": "S5X",
}


def _calendar_to_t_gps(year: int, month: int, day: int, hour: int, minute: int, sec: float) -> float:
    if year < 100:
        year += 2000 if year < 80 else 1900
    d = _dt.datetime(year, month, day, hour, minute) - _GPS_EPOCH
    return d.days * 86400.0 + d.seconds + sec


def _f(s: str) -> float:
    s = s.strip()
    if not s:
        return 0.0
    return float(s.replace("D", "E").replace("d", "e"))


#: file names of compressed RINEX: gzip/Unix compress, Hatanaka (.crx, RINEX 2 .YYd), zip, bzip2
_COMPRESSED = re.compile(r"(\.(gz|Z|zip|bz2|crx)|\.\d\dd)$", re.IGNORECASE)


def _open_text(path) -> list[str]:
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


def _header_end(lines: list[str]) -> int:
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
    lines = _open_text(path)
    alpha = beta = None
    qzs: dict[str, list[float]] = {}
    for ln in lines[:_header_end(lines)]:
        label = ln[60:].strip()
        if label == "ION ALPHA":
            alpha = [_f(ln[2 + 12 * k:14 + 12 * k]) for k in range(4)]
        elif label == "ION BETA":
            beta = [_f(ln[2 + 12 * k:14 + 12 * k]) for k in range(4)]
        elif label == "IONOSPHERIC CORR":
            vals = [_f(ln[5 + 12 * k:17 + 12 * k]) for k in range(4)]
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


def read_rinex_nav(path, systems: str = "GECJ") -> list:
    """Keplerian ephemerides of ``systems`` (GPS, Galileo, BeiDou, QZSS) from a RINEX 2.x GPS ('N'),
    3.x or 4.x navigation file, in file order (Galileo F/NAV records with an I/NAV twin dropped),
    then, when ``systems`` has 'R', a RINEX 3 file's GLONASS records
    (:class:`~.glonass.GlonassEphemeris`).  SBAS and NavIC records, RINEX 4's GLONASS and CNAV
    ephemerides and its ION / STO / EOP records are skipped."""
    lines = _open_text(path)
    head = _header_end(lines)
    version = _f(lines[0][:9])
    file_sys = lines[0][40:41].upper() if version >= 3 else "G"
    out: list[GpsEphemeris] = []
    recs: list[tuple[GpsEphemeris, bool]] = []
    glonass: list[GlonassEphemeris] = []
    leap_s = _header_leap_seconds(lines, head)
    i = head
    n = len(lines)
    if version < 3:
        if lines[0][20:21].upper() not in ("N", " "):
            raise ValueError(f"{path}: RINEX 2 file is not a GPS navigation file")
        if "G" not in systems:
            return out
        while i < n:
            ln = lines[i]
            if not ln.strip():
                i += 1
                continue
            prn = int(ln[0:2])
            yy, mo, dd, hh, mi = (int(ln[3 + 3 * k:5 + 3 * k]) for k in range(5))
            ss = _f(ln[17:22])
            vals = [_f(ln[22:41]), _f(ln[41:60]), _f(ln[60:79])]
            for k in range(1, 8):
                row = lines[i + k] if i + k < n else ""
                for c in range(4):
                    vals.append(_f(row[3 + 19 * c:22 + 19 * c]))
            i += 8
            out.append(_eph_from_fields(f"G{prn:02d}", _calendar_to_t_gps(yy, mo, dd, hh, mi, ss), vals))
        return out
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
        recs.append(_v3_nav_record(lines, i, sys_))
        i += 8
    return _prefer_inav(recs) + glonass


def _header_leap_seconds(lines: list[str], head: int) -> int | None:
    """GPS - UTC from a RINEX 3 header's LEAP SECONDS line, None without one."""
    for ln in lines[:head]:
        if ln[60:].strip().startswith("LEAP SECONDS"):
            try:
                return int(ln[:6])
            except ValueError:
                return None
    return None


def _glonass_record(lines: list[str], i: int, j: int, leap_s: int | None) -> GlonassEphemeris | None:
    """The GLONASS record of lines ``i`` to ``j`` (its epoch is UTC; ``leap_s`` from the header,
    or by the date when the header has none); None for a record cut short or with a frequency
    channel outside -7..+13 (its carriers would be wrong)."""
    ln = lines[i]
    yy, mo, dd, hh, mi, ss = (int(ln[4:8]), int(ln[9:11]), int(ln[12:14]), int(ln[15:17]),
                              int(ln[18:20]), _f(ln[21:23]))
    vals = [_f(ln[23:42]), _f(ln[42:61]), _f(ln[61:80])]
    for k in range(i + 1, min(j, i + 4)):
        row = lines[k]
        for c in range(4):
            vals.append(_f(row[4 + 19 * c:23 + 19 * c]))
    if len(vals) < 15 or not -7 <= vals[10] <= 13:
        return None
    t_utc = _calendar_to_t_gps(yy, mo, dd, hh, mi, ss)
    leap = leap_s if leap_s is not None else gps_minus_utc_s(t_utc)
    return glonass_ephemeris_from_rinex(f"R{int(ln[1:3]):02d}", t_utc, leap, vals)


#: RINEX 4's Keplerian ephemeris messages, the ones read (the legacy navigation messages; CNAV,
#: CNV1-3 of the modernised signals are skipped)
_V4_KEPLER_MESSAGES = {("G", "LNAV"), ("J", "LNAV"), ("E", "INAV"), ("E", "FNAV"), ("C", "D1"), ("C", "D2")}


def _v3_nav_record(lines: list[str], i: int, sys_: str) -> tuple[GpsEphemeris, bool]:
    """(ephemeris, is Galileo F/NAV only) of the eight-line RINEX 3 record starting at line ``i``."""
    ln = lines[i]
    n = len(lines)
    prn = int(ln[1:3])
    yy, mo, dd, hh, mi, ss = (int(ln[4:8]), int(ln[9:11]), int(ln[12:14]), int(ln[15:17]),
                              int(ln[18:20]), _f(ln[21:23]))
    vals = [_f(ln[23:42]), _f(ln[42:61]), _f(ln[61:80])]
    for k in range(1, 8):
        row = lines[i + k] if i + k < n else ""
        for c in range(4):
            vals.append(_f(row[4 + 19 * c:23 + 19 * c]))
    sat = f"{sys_}{prn:02d}"
    return _eph_from_fields(sat, _calendar_to_t_gps(yy, mo, dd, hh, mi, ss), vals), _is_fnav(sat, vals)


# ---------------------------------------------------------------------------------------------
# observations
# ---------------------------------------------------------------------------------------------

def _wavelength(sys_: str, band: str) -> float:
    """Carrier wavelength, m, of a band of a system (:data:`FREQUENCY_HZ`); NaN for GLONASS FDMA."""
    hz = FREQUENCY_HZ.get(sys_, {}).get(band)
    return SPEED_OF_LIGHT_MPS / hz if hz else float("nan")


def _build_obs(sat: str, codes: list[str], values: list[float], llis: list[int], ssis: list[int],
               version: float) -> list[SatObservation]:
    """Group one satellite's observation values by signal (band + attribute)."""
    sig: dict[str, dict] = {}
    for code, val, lli in zip(codes, values, llis):
        # blank (NaN here) or 0.0: "missing observations are written as 0.0 or blanks" (RINEX
        # 2.11 and 3.0x); some converters write 0.000 for a signal not tracked at this epoch
        if val != val or val == 0.0:
            continue
        key = code[1:3]
        d = sig.setdefault(key, {})
        t = code[0]
        if t == "C":
            d["P"] = val
        elif t == "L":
            d["L"] = val
            d["lli"] = lli
        elif t == "D":
            d["D"] = val
        elif t == "S":
            d["S"] = val
    out = []
    nan = float("nan")
    sat = sys.intern(sat)          # one string per satellite and signal name for the whole file, not
    for key, d in sig.items():     # per observation: a long file is held in memory whole
        if "P" not in d and "L" not in d and "D" not in d:
            continue
        lli = d.get("lli", 0)
        out.append(SatObservation(
            sat=sat, pseudorange_m=d.get("P", nan), carrier_cycles=d.get("L", nan),
            doppler_hz=d.get("D", nan), cn0_dbhz=d.get("S", nan),
            loss_of_lock=bool(lli & 1), half_cycle_ambiguous=bool(lli & 2) if version >= 3 else False,
            signal=sys.intern("L" + key), wavelength_m=_wavelength(sat[0], key[0])))
    return out


def _parse_obs_fields(text: str, nobs: int) -> tuple[list[float], list[int], list[int]]:
    vals, llis, ssis = [], [], []
    nan = float("nan")
    for k in range(nobs):
        f = text[16 * k:16 * k + 16]
        v = f[:14].strip()
        vals.append(float(v) if v else nan)
        c = f[14:15]
        llis.append(int(c) if c.strip() else 0)
        c = f[15:16]
        ssis.append(int(c) if c.strip() else 0)
    return vals, llis, ssis


def read_rinex_obs(path, systems: str = "G", t_gps_window: tuple[float, float] | None = None
                   ) -> tuple[dict, list[GnssEpoch]]:
    """Read a RINEX 2.x / 3.x observation file.

    Returns ``(header, epochs)``; ``header`` has 'version', 'marker', 'approx_position_e'
    (np.array, m, or None), 'antenna_delta_hen_m', 'receiver', 'antenna', 'interval_s' (NaN if
    absent), 'obs_types' (system -> RINEX 3 codes), 'n_epochs', 'skipped' (counts by reason:
    'other system' observations, 'event' records (flags 2-6), 'repeated epoch' time tags),
    'out_of_order_epochs', 'time_system'.  Epochs come out in time order, one per time tag
    (:func:`_in_time_order`; :func:`reading_notes` says what was done).  Only
    satellites of ``systems`` are kept (default GPS only; 'GECJ' for GPS, Galileo, BeiDou and QZSS,
    wavelengths from :data:`FREQUENCY_HZ`; GLONASS observations get NaN wavelengths).  Time tags
    of a file in BDT (TIME OF FIRST OBS) are moved to GPS time (+14 s).  Epochs with flag > 1 (events) are skipped; flag 1 (power failure) is kept
    and all its observations are marked ``loss_of_lock``.  ``t_gps_window`` (first, last GPS
    time, s): epochs outside it are stepped over unparsed ('epochs_outside_window' counts them;
    a base file of hours read for a rover of minutes); 'file_span_t_gps' is (first, last) epoch
    of the whole file, read or not (None: no epoch).
    """
    lines = _open_text(path)
    head = _header_end(lines)
    version = _f(lines[0][:9])
    hdr: dict = {"version": version, "marker": "", "approx_position_e": None, "antenna_delta_hen_m": None,
                 "receiver": "", "antenna": "", "interval_s": float("nan"), "obs_types": {},
                 "skipped": {"other system": 0, "event": 0}, "time_system": "GPS", "epochs_outside_window": 0}
    t_first, t_last = t_gps_window if t_gps_window is not None else (-math.inf, math.inf)
    span = (math.inf, -math.inf)
    r2_types: list[str] = []
    r3_types: dict[str, list[str]] = {}
    cur_sys = None
    for ln in lines[:head]:
        label = ln[60:].strip()
        if label == "MARKER NAME":
            hdr["marker"] = ln[:60].strip()
        elif label == "APPROX POSITION XYZ":
            xyz = np.array([_f(ln[0:14]), _f(ln[14:28]), _f(ln[28:42])])
            hdr["approx_position_e"] = xyz if np.any(xyz != 0.0) else None
        elif label == "ANTENNA: DELTA H/E/N":
            hdr["antenna_delta_hen_m"] = np.array([_f(ln[0:14]), _f(ln[14:28]), _f(ln[28:42])])
        elif label == "REC # / TYPE / VERS":
            hdr["receiver"] = ln[20:40].strip()
        elif label == "ANT # / TYPE":
            hdr["antenna"] = ln[20:40].strip()
        elif label == "INTERVAL":
            hdr["interval_s"] = _f(ln[:10])
        elif label == "TIME OF FIRST OBS" and ln[48:51].strip():
            hdr["time_system"] = ln[48:51].strip()
        elif label == "# / TYPES OF OBSERV":
            if ln[:6].strip():
                r2_types = []
            r2_types += ln[6:60].split()
        elif label == "SYS / # / OBS TYPES":
            if ln[0] != " ":
                cur_sys = ln[0]
                r3_types[cur_sys] = []
            r3_types[cur_sys] += ln[7:60].split()
    if version < 3:
        has_p2 = "P2" in r2_types
        mapped = []
        for t in r2_types:
            c = _RINEX2_MAP.get(t, t + "X" if len(t) == 2 else t)
            if t == "L2" and not has_p2 and "C2" in r2_types:
                c = "L2X"
            if t == "C2" and not has_p2:
                c = "C2X"
            mapped.append(c)
        # keep pseudorange/phase pairing: L2 goes with whichever L2 code exists
        if "L2W" in mapped and "C2W" not in mapped and "C2X" in mapped:
            mapped[mapped.index("L2W")] = "L2X"
        # GLONASS names its P code 'P' and its L2 C/A 'C' (RINEX 3), where GPS has 'W' and 'X'
        r2_codes = {"G": mapped, "R": [c[:2] + "P" if c[2] == "W" else (c[:2] + "C" if c[1:] == "2X" else c)
                                       for c in mapped]}
        hdr["obs_types"] = {"G": mapped}
        hdr["obs_types_rinex2"] = list(r2_types)
    else:
        if version < 3.03 and "C" in r3_types:
            # BeiDou B1I was band 1 up to RINEX 3.02 and is band 2 from 3.03 on, where band 1 is
            # B1C (1575.42 MHz, not B1I's 1561.098): read as 3.03 codes (RTKLIB does the same)
            r3_types["C"] = [c[0] + "2" + c[2:] if c[0] in "CLDS" and c[1] == "1" else c for c in r3_types["C"]]
        hdr["obs_types"] = r3_types

    epochs: list[GnssEpoch] = []
    dt_tag = SYSTEM_TO_GPS_S["C"] if hdr["time_system"] == "BDT" else 0.0
    i, n = head, len(lines)
    if version < 3:
        nobs = len(hdr["obs_types"]["G"])
        nlines_per_sat = max(1, math.ceil(nobs / 5))
        while i < n:
            ln = lines[i]
            if not ln.strip():
                i += 1
                continue
            flag = int(ln[28:29] or 0)
            nsat = int(ln[29:32])
            if flag > 1:
                hdr["skipped"]["event"] += 1
                # flags 2-5: nsat header lines follow; 6 (cycle slip records): an epoch's layout
                i += 1 + (nsat if flag < 6 else (nsat - 1) // 12 + nsat * nlines_per_sat)
                continue
            sats = []
            row = ln
            while len(sats) < nsat:
                chunk = row[32:68]
                for k in range(0, len(chunk), 3):
                    s = chunk[k:k + 3]
                    if s.strip() and len(sats) < nsat:
                        sats.append(s[0].replace(" ", "G") + s[1:].replace(" ", "0"))
                if len(sats) < nsat:
                    i += 1
                    row = lines[i]
            t = _calendar_to_t_gps(int(ln[1:3]), int(ln[4:6]), int(ln[7:9]), int(ln[10:12]),
                                   int(ln[13:15]), float(ln[15:26]))
            i += 1
            span = (min(span[0], t), max(span[1], t))
            if not t_first <= t <= t_last:
                hdr["epochs_outside_window"] += 1
                i += nsat * nlines_per_sat
                continue
            obs = []
            for s in sats:
                text = "".join(lines[i + k].ljust(80)[:80] for k in range(nlines_per_sat))
                i += nlines_per_sat
                if s[0] not in systems:
                    hdr["skipped"]["other system"] += 1
                    continue
                vals, llis, ssis = _parse_obs_fields(text, nobs)
                if flag == 1:
                    llis = [l | 1 for l in llis]
                codes = r2_codes["R" if s[0] == "R" else "G"]
                obs.extend(_build_obs(s, codes, vals, llis, ssis, version))
            epochs.append(GnssEpoch(t_gps=t, observations=tuple(obs), source="rover"))
    else:
        while i < n:
            ln = lines[i]
            if not ln.startswith(">"):
                i += 1
                continue
            flag = int(ln[31:32] or 0)
            nsat = int(ln[32:35])
            if flag > 1:
                hdr["skipped"]["event"] += 1
                i += 1 + nsat
                continue
            t = _calendar_to_t_gps(int(ln[2:6]), int(ln[7:9]), int(ln[10:12]), int(ln[13:15]),
                                   int(ln[16:18]), float(ln[18:29])) + dt_tag
            i += 1
            span = (min(span[0], t), max(span[1], t))
            if not t_first <= t <= t_last:
                hdr["epochs_outside_window"] += 1
                i += nsat
                continue
            obs = []
            for _ in range(nsat):
                row = lines[i]
                i += 1
                s = row[0:3].replace(" ", "0")
                sys_ = s[0]
                if sys_ not in systems or sys_ not in r3_types:
                    hdr["skipped"]["other system"] += 1
                    continue
                codes = r3_types[sys_]
                vals, llis, ssis = _parse_obs_fields(row[3:].ljust(3 + 16 * len(codes)), len(codes))
                if flag == 1:
                    llis = [l | 1 for l in llis]
                obs.extend(_build_obs(s, codes, vals, llis, ssis, version))
            epochs.append(GnssEpoch(t_gps=t, observations=tuple(obs), source="rover"))
    epochs, hdr["out_of_order_epochs"], hdr["skipped"]["repeated epoch"] = _in_time_order(epochs)
    hdr["file_span_t_gps"] = span if span[0] <= span[1] else None
    hdr["n_epochs"] = len(epochs)
    return hdr, epochs


def _in_time_order(epochs: list[GnssEpoch]) -> tuple[list[GnssEpoch], int, int]:
    """(epochs sorted by time with one per time tag, how many were out of order, how many repeated
    an earlier epoch's tag and were dropped).  Files joined end to end overlap (hourly files, a
    logger restarted), and a filter fed an epoch twice or backwards would take it as a new epoch
    or run backwards in time; the first of a repeated tag is kept, as it came first in the file."""
    out_of_order = sum(1 for a, b in zip(epochs, epochs[1:]) if b.t_gps < a.t_gps)
    ordered = sorted(epochs, key=lambda e: e.t_gps) if out_of_order else epochs   # stable: the first stays first
    kept = [e for k, e in enumerate(ordered) if k == 0 or e.t_gps != ordered[k - 1].t_gps]
    return kept, out_of_order, len(ordered) - len(kept)


def reading_notes(hdr: dict) -> str:
    """What :func:`read_rinex_obs` left out or put in order, for a person ('' when nothing).  Event
    records (flags 2-6: a header block, a new occupation) are part of the format, not news."""
    skipped = hdr.get("skipped") or {}
    notes = []
    if skipped.get("repeated epoch"):
        notes.append(f"{skipped['repeated epoch']} epochs repeating an earlier time tag dropped (the first kept)")
    if hdr.get("out_of_order_epochs"):
        notes.append(f"epochs put in time order ({hdr['out_of_order_epochs']} went back in time)")
    return "; ".join(notes)
