"""RINEX 2.x / 3.x observation files (any system) -> (header dict, list of :class:`GnssEpoch`).

Time tags are the receiver's GPS time tags as continuous GPS seconds (a BDT file's moved by 14 s).
RINEX 2 observation types are mapped onto RINEX 3 codes (RTKLIB's convention): C1->C1C, P1->C1W,
L1->L1C, D1->D1C, S1->S1C, P2->C2W, L2->L2W (L2C if the file has C2 but no P2), C2->C2X... see
``_RINEX2_MAP``; a GLONASS satellite's P codes are 'P' and its L2 C/A 'C'.  RINEX 3.02's BeiDou
band 1 (B1I) is 3.03's band 2.  One :class:`SatObservation` per satellite per signal, named 'L' +
band + attribute ('L1C', 'L2W', ...).  LLI bit 0 -> ``loss_of_lock``; in RINEX 3 LLI bit 1 ->
``half_cycle_ambiguous``.

Files as users have them: 0.0 is a missing value (the standard's rule); epochs come out in time
order, one per time tag (joined files); an epoch that cannot be read (a file cut mid-epoch, a
corrupt line) is counted and the reader resumes at the next epoch line; a file that is not an
observation file (a navigation file given as one) is a clear error.
"""
from __future__ import annotations

import math
import re
import sys
from dataclasses import dataclass

import numpy as np

from .glonass import gps_minus_utc_s
from .rinex import calendar_to_t_gps, header_end, header_float, header_leap_seconds, open_text
from .signals import FREQUENCY_HZ
from ..messages import SPEED_OF_LIGHT_MPS, SYSTEM_TO_GPS_S, GnssEpoch, SatObservation

# RINEX 2 observation type -> RINEX 3 code (type letter, band, attribute)
_RINEX2_MAP = {
    "C1": "C1C", "P1": "C1W", "L1": "L1C", "D1": "D1C", "S1": "S1C",
    "C2": "C2X", "P2": "C2W", "L2": "L2W", "D2": "D2W", "S2": "S2W",
    "C5": "C5X", "L5": "L5X", "D5": "D5X", "S5": "S5X",
}


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
    'other system' observations, 'event' records (flags 2-6), 'repeated epoch' time tags,
    'unreadable epoch', 'unreadable satellite line' (RINEX 3)), 'out_of_order_epochs',
    'time_system'.  Epochs come out in time order, one per time tag (:func:`_in_time_order`;
    :func:`reading_notes` says what was done).  Only satellites of ``systems`` are kept (default
    GPS only; 'GECJ' for GPS, Galileo, BeiDou and QZSS, wavelengths from :data:`FREQUENCY_HZ`;
    GLONASS observations get NaN wavelengths).  Time tags of a file in BDT (TIME OF FIRST OBS, or
    a BeiDou-only file's default) are moved to GPS time (+14 s), in GLO or UTC by the leap seconds
    ('time_tag_to_gps_s').  Epochs with flag > 1 (events) are skipped; flag 1 (power failure)
    is kept and all its observations are marked ``loss_of_lock``.  ``t_gps_window`` (first, last
    GPS time, s): epochs outside it are stepped over unparsed ('epochs_outside_window' counts them;
    a base file of hours read for a rover of minutes); 'file_span_t_gps' is (first, last) epoch
    of the whole file, read or not (None: no epoch).
    """
    lines = open_text(path)
    head = header_end(lines)
    hdr, codes = _read_header(lines, head, path)
    version = hdr["version"]
    ctx = _Context(hdr, codes, systems, *(t_gps_window or (-math.inf, math.inf)),
                   dt_tag=_tag_to_gps_s(hdr, lines, head))
    hdr["time_tag_to_gps_s"] = ctx.dt_tag
    read_epoch = _rinex2_epoch if version < 3 else _rinex3_epoch
    epochs: list[GnssEpoch] = []
    i, n = head, len(lines)
    while i < n:
        if not lines[i].strip():
            i += 1
            continue
        try:
            epoch, i_next = read_epoch(lines, i, ctx)
        except (ValueError, IndexError):
            # a file cut mid-epoch or a corrupt line: this epoch is lost, the next one is read
            hdr["skipped"]["unreadable epoch"] += 1
            i = _next_epoch_line(lines, i + 1, version)
            continue
        i = i_next
        if epoch is not None:
            epochs.append(epoch)
    epochs, hdr["out_of_order_epochs"], hdr["skipped"]["repeated epoch"] = _in_time_order(epochs)
    hdr["file_span_t_gps"] = ctx.span if ctx.span[0] <= ctx.span[1] else None
    hdr["n_epochs"] = len(epochs)
    return hdr, epochs


#: files of one station: their header positions agree within this (m)
SAME_STATION_M = 1.0


def read_rinex_obs_files(paths, systems: str = "G", t_gps_window: tuple[float, float] | None = None,
                         *, moving: bool = False) -> tuple[dict, list[GnssEpoch]]:
    """Several observation files of one receiver (a CORS's hourly or 15-min files, a rover's logger
    restarted) read as one: the first file's header, with 'files', the counts summed and
    'file_span_t_gps' over all; the epochs of all in time order, one per time tag.  Refused: files
    of two stations (header positions more than :data:`SAME_STATION_M` apart; ``moving``, a
    rover's, whose header positions are wherever it was: two marker names, receiver
    numbers or types or antenna types instead), and files
    whose antenna heights differ (one antenna offset is applied to all)."""
    paths = list(paths)
    hdr, epochs = read_rinex_obs(paths[0], systems, t_gps_window)
    if len(paths) == 1:
        return hdr, epochs
    hdr = dict(hdr, files=[str(p) for p in paths], skipped=dict(hdr["skipped"]))
    for path in paths[1:]:
        h, more = read_rinex_obs(path, systems, t_gps_window)
        _check_same_receiver(hdr, h, paths[0], path, moving)
        for k, n in h["skipped"].items():
            hdr["skipped"][k] = hdr["skipped"].get(k, 0) + n
        for k in ("out_of_order_epochs", "epochs_outside_window"):
            hdr[k] += h[k]
        spans = [sp for sp in (hdr["file_span_t_gps"], h["file_span_t_gps"]) if sp]
        hdr["file_span_t_gps"] = (min(sp[0] for sp in spans), max(sp[1] for sp in spans)) if spans else None
        epochs += more
    # the files in any order; a time tag two files share (an overlap) read once
    epochs, _, repeated = _in_time_order(epochs)
    hdr["skipped"]["repeated epoch"] += repeated
    hdr["n_epochs"] = len(epochs)
    return hdr, epochs


def _check_same_receiver(first: dict, other: dict, first_path, path, moving: bool) -> None:
    """ValueError when ``path``'s header says another receiver or antenna offset than the first file's."""
    if moving:
        for key, what in (("marker", "marker"), ("receiver_number", "receiver number"), ("receiver", "receiver"),
                          ("antenna", "antenna")):
            a, b = first.get(key), other.get(key)
            if a and b and a != b:
                raise ValueError(f"{path} is not of the receiver of {first_path}: {what} {b!r}, not {a!r}")
    else:
        a, b = first["approx_position_e"], other["approx_position_e"]
        if a is not None and b is not None and float(np.linalg.norm(a - b)) > SAME_STATION_M:
            raise ValueError(f"{path} is not of the station of {first_path}: their header positions are "
                             f"{np.linalg.norm(a - b):.1f} m apart")
    a, b = first["antenna_delta_hen_m"], other["antenna_delta_hen_m"]
    if not np.allclose(a if a is not None else np.zeros(3), b if b is not None else np.zeros(3), atol=1e-3):
        raise ValueError(f"{path} has another antenna offset (ANTENNA: DELTA H/E/N) than {first_path}: "
                         "process them apart")


#: RINEX 2.11 and 3: TIME OF FIRST OBS may leave the time system blank in a single-system file,
#: which is then in that system's time ('GLO' is UTC(SU), the time GLONASS broadcasts in)
_DEFAULT_TIME_SYSTEM = {"G": "GPS", "R": "GLO", "E": "GAL", "C": "BDT", "J": "QZS", "M": "GPS"}


def _tag_to_gps_s(hdr: dict, lines: list[str], head: int) -> float:
    """What to add to the file's time tags for GPS time: +14 s in BDT; in 'GLO' (GLONASS's UTC, as
    RINEX names it) or 'UTC', the leap seconds (the header's LEAP SECONDS, else the table's at the
    first epoch), as RTKLIB does; GAL and QZS are steered to GPS time."""
    system = hdr["time_system"]
    if system == "BDT":
        return SYSTEM_TO_GPS_S["C"]
    if system in ("GLO", "UTC"):
        leap = header_leap_seconds(lines, head)
        if leap is None:
            leap = gps_minus_utc_s(hdr.get("first_obs_calendar_t", 0.0))
        return float(leap)
    return 0.0


def _read_header(lines: list[str], head: int, path) -> tuple[dict, dict[str, list[str]]]:
    """(the header dict, system -> the RINEX 3 codes of its observation fields)."""
    version = header_float(lines[0][:9])
    file_type = lines[0][20:21]
    if file_type.upper() != "O":
        raise ValueError(f"{path}: not a RINEX observation file (RINEX VERSION / TYPE says "
                         f"{lines[0][20:40].strip()!r}: a navigation file given as observations?)")
    hdr: dict = {"version": version, "marker": "", "approx_position_e": None, "antenna_delta_hen_m": None,
                 "receiver": "", "receiver_number": "", "antenna": "", "interval_s": float("nan"), "obs_types": {},
                 "skipped": {"other system": 0, "event": 0, "unreadable epoch": 0, "unreadable satellite line": 0},
                 "time_system": _DEFAULT_TIME_SYSTEM.get(lines[0][40:41].upper(), "GPS"),
                 "epochs_outside_window": 0}
    r2_types: list[str] = []
    r3_types: dict[str, list[str]] = {}
    cur_sys = None
    for ln in lines[:head]:
        label = ln[60:].strip()
        if label == "MARKER NAME":
            hdr["marker"] = ln[:60].strip()
        elif label == "APPROX POSITION XYZ":
            xyz = np.array([header_float(ln[0:14]), header_float(ln[14:28]), header_float(ln[28:42])])
            hdr["approx_position_e"] = xyz if np.any(xyz != 0.0) else None
        elif label == "ANTENNA: DELTA H/E/N":
            hdr["antenna_delta_hen_m"] = np.array([header_float(ln[0:14]), header_float(ln[14:28]),
                                                   header_float(ln[28:42])])
        elif label == "REC # / TYPE / VERS":
            hdr["receiver_number"] = ln[:20].strip()
            hdr["receiver"] = ln[20:40].strip()
        elif label == "ANT # / TYPE":
            hdr["antenna"] = ln[20:40].strip()
        elif label == "INTERVAL":
            hdr["interval_s"] = header_float(ln[:10])
        elif label == "TIME OF FIRST OBS":
            hdr["time_system"] = ln[48:51].strip() or hdr["time_system"]
            try:
                hdr["first_obs_calendar_t"] = calendar_to_t_gps(*(int(ln[6 * k:6 * k + 6]) for k in range(5)),
                                                                header_float(ln[30:43]))
            except ValueError:
                pass
        elif label == "# / TYPES OF OBSERV":
            if ln[:6].strip():
                r2_types = []
            r2_types += ln[6:60].split()
        elif label == "SYS / # / OBS TYPES":
            if ln[0] != " ":
                cur_sys = ln[0]
                r3_types[cur_sys] = []
            r3_types[cur_sys] += ln[7:60].split()
    if version >= 3:
        if version < 3.03 and "C" in r3_types:
            # BeiDou B1I was band 1 up to RINEX 3.02 and is band 2 from 3.03 on, where band 1 is
            # B1C (1575.42 MHz, not B1I's 1561.098): read as 3.03 codes (RTKLIB does the same)
            r3_types["C"] = [c[0] + "2" + c[2:] if c[0] in "CLDS" and c[1] == "1" else c for c in r3_types["C"]]
        hdr["obs_types"] = r3_types
        return hdr, r3_types
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
    hdr["obs_types"] = {"G": mapped}
    hdr["obs_types_rinex2"] = list(r2_types)
    # one list of types for every system; GLONASS names its P code 'P' and its L2 C/A 'C' (RINEX
    # 3), where GPS has 'W' and 'X'
    return hdr, {"G": mapped, "R": [c[:2] + "P" if c[2] == "W" else (c[:2] + "C" if c[1:] == "2X" else c)
                                    for c in mapped]}


@dataclass
class _Context:
    """What every epoch of a file is read with, and what the reading counts."""
    hdr: dict
    codes: dict[str, list[str]]            # system -> RINEX 3 codes of the fields
    systems: str
    t_first: float                         # the window asked for, GPS s
    t_last: float
    dt_tag: float = 0.0                    # time tag -> GPS time (BDT, GLO and UTC files)
    span: tuple[float, float] = (math.inf, -math.inf)     # the file's epochs, read or not

    def seen(self, t: float) -> bool:
        """Note an epoch's time; whether it is inside the window."""
        self.span = (min(self.span[0], t), max(self.span[1], t))
        if self.t_first <= t <= self.t_last:
            return True
        self.hdr["epochs_outside_window"] += 1
        return False


#: a RINEX 3 satellite: system letter and two digits
_SATELLITE = re.compile(r"^[GRECJSI]\d\d$")

#: a RINEX 2 epoch line: yy mm dd hh mm ss.sssssss, flag, count
_RINEX2_EPOCH = re.compile(r"^ [ \d]\d( [ \d]\d){4} [ \d]\d\.\d{7}  \d[ \d]{2}\d")


def _next_epoch_line(lines: list[str], i: int, version: float) -> int:
    """The index of the first epoch line from ``i`` on (len(lines) when none)."""
    for k in range(i, len(lines)):
        if (lines[k].startswith(">") if version >= 3 else _RINEX2_EPOCH.match(lines[k])):
            return k
    return len(lines)


def _rinex2_epoch(lines: list[str], i: int, ctx: _Context) -> tuple[GnssEpoch | None, int]:
    """The epoch whose epoch line is ``lines[i]`` (None: an event or outside the window), and the
    index after it."""
    ln = lines[i]
    nobs = len(ctx.codes["G"])
    nlines_per_sat = max(1, math.ceil(nobs / 5))
    flag = int(ln[28:29] or 0)
    nsat = int(ln[29:32])
    if flag > 1:
        ctx.hdr["skipped"]["event"] += 1
        # flags 2-5: nsat header lines follow; 6 (cycle slip records): an epoch's layout
        return None, i + 1 + (nsat if flag < 6 else (nsat - 1) // 12 + nsat * nlines_per_sat)
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
    t = calendar_to_t_gps(int(ln[1:3]), int(ln[4:6]), int(ln[7:9]), int(ln[10:12]), int(ln[13:15]),
                          float(ln[15:26])) + ctx.dt_tag
    i += 1
    if not ctx.seen(t):
        return None, i + nsat * nlines_per_sat
    if i + nsat * nlines_per_sat > len(lines):
        raise IndexError("the file ends inside the epoch")
    obs = []
    for s in sats:
        text = "".join(lines[i + k].ljust(80)[:80] for k in range(nlines_per_sat))
        i += nlines_per_sat
        if s[0] not in ctx.systems:
            ctx.hdr["skipped"]["other system"] += 1
            continue
        vals, llis, ssis = _parse_obs_fields(text, nobs)
        if flag == 1:
            llis = [l | 1 for l in llis]
        obs.extend(_build_obs(s, ctx.codes["R" if s[0] == "R" else "G"], vals, llis, ssis, 2.0))
    return GnssEpoch(t_gps=t, observations=tuple(obs), source="rover"), i


def _rinex3_epoch(lines: list[str], i: int, ctx: _Context) -> tuple[GnssEpoch | None, int]:
    """As :func:`_rinex2_epoch` for RINEX 3 (its epoch lines start with '>')."""
    ln = lines[i]
    if not ln.startswith(">"):
        return None, i + 1
    flag = int(ln[31:32] or 0)
    nsat = int(ln[32:35])
    if flag > 1:
        ctx.hdr["skipped"]["event"] += 1
        return None, i + 1 + nsat
    t = calendar_to_t_gps(int(ln[2:6]), int(ln[7:9]), int(ln[10:12]), int(ln[13:15]), int(ln[16:18]),
                          float(ln[18:29])) + ctx.dt_tag
    i += 1
    if not ctx.seen(t):
        return None, i + nsat
    if i + nsat > len(lines) or any(lines[k].startswith(">") for k in range(i, i + nsat)):
        raise IndexError("fewer satellite lines than the epoch line counts (a file cut mid-epoch)")
    obs = []
    for row in lines[i:i + nsat]:
        s = row[0:3].replace(" ", "0")
        sys_ = s[0]
        if not _SATELLITE.match(s):
            ctx.hdr["skipped"]["unreadable satellite line"] += 1          # a corrupt line, not a system
            continue
        if sys_ not in ctx.systems or sys_ not in ctx.codes:
            ctx.hdr["skipped"]["other system"] += 1
            continue
        codes = ctx.codes[sys_]
        vals, llis, ssis = _parse_obs_fields(row[3:].ljust(3 + 16 * len(codes)), len(codes))
        if flag == 1:
            llis = [l | 1 for l in llis]
        obs.extend(_build_obs(s, codes, vals, llis, ssis, ctx.hdr["version"]))
    return GnssEpoch(t_gps=t, observations=tuple(obs), source="rover"), i + nsat


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

    def epochs(n: int) -> str:
        return f"{n} epoch" + ("" if n == 1 else "s")
    notes = []
    if skipped.get("repeated epoch"):
        notes.append(f"{epochs(skipped['repeated epoch'])} repeating an earlier time tag dropped (the first kept)")
    if skipped.get("unreadable epoch"):
        notes.append(f"{epochs(skipped['unreadable epoch'])} unreadable (a file cut mid-epoch or a corrupt line) "
                     f"skipped")
    if skipped.get("unreadable satellite line"):
        n = skipped["unreadable satellite line"]
        notes.append(f"{n} satellite line{'' if n == 1 else 's'} unreadable (a corrupt line) skipped")
    if hdr.get("out_of_order_epochs"):
        notes.append(f"epochs put in time order ({hdr['out_of_order_epochs']} went back in time)")
    if hdr.get("time_tag_to_gps_s") and hdr.get("time_system") in ("GLO", "UTC"):
        notes.append(f"time tags in {hdr['time_system']} (UTC) moved to GPS time (+{hdr['time_tag_to_gps_s']:.0f} s)")
    return "; ".join(notes)
