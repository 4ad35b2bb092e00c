"""u-blox UBX binary protocol -> typed navigation messages.

:class:`UbxDecoder` is an incremental, stateful decoder: feed it arbitrary byte chunks (from a
serial port, a SERIAL_CONTROL tunnel, a file) and it returns the messages completed by that chunk:

* ``RXM-RAWX``  -> :class:`~companion.messages.GnssEpoch` (rover raw observations)
* ``RXM-SFRBX`` -> :class:`~companion.messages.GpsEphemeris` of GPS and QZSS (L1 C/A LNAV),
  Galileo (E1-B/E5b I/NAV) and BeiDou (B1I/B2I D1 and D2), and
  :class:`~companion.gnss.glonass.GlonassEphemeris` (L1OF/L2OF strings 1-4), once per new
  consistent set per satellite; see :mod:`companion.io.ubx_sfrbx`.  Counted: ``ephemerides`` and
  ``ephemerides_<G|J|E|C|R>``; words of other messages ``sfrbx_not_decoded_<letter>``
* ``NAV-PVT``   -> :class:`~companion.messages.GnssFix` (the receiver's own solution)
* ``NAV-RELPOSNED`` (version 0, M8P; version 1, F9P) -> :class:`~companion.messages.GnssBaseline`
  (moving-baseline vector for dual-antenna heading) when ``gnssFixOK`` and ``relPosValid``;
  otherwise counted (``relposned_invalid``).  ``carrier_fixed`` = carrSoln 2.
* ``NAV-TIMEGPS`` only updates the decoder's notion of the GPS week; ``MON-VER`` sets
  ``receiver_model``.

Robustness contract: ``feed`` never raises on bad input.  Garbage between frames, bad checksums,
impossible lengths and malformed payloads are skipped and counted in ``counters`` (a plain dict,
reason -> count) and reported through :mod:`logging` at most once per ``log_interval_s`` per reason.
After a bad frame the decoder resynchronises on the next ``0xB5 0x62`` after the false sync, so
a valid frame that follows garbage or a truncated frame is still decoded.

Frames are split and checked here (Fletcher-8 over class..payload) and payloads are unpacked with
:mod:`struct` straight from the u-blox interface description (ZED-F9P, protocol 27+); pyubx2 is
used by the tests to build reference frames, which cross-checks this decoder.

Conventions of the produced observations (see :class:`~companion.messages.SatObservation`):

* satellite ids RINEX-style: ``G05 E11 C30 R07 J02 S37 I03`` (SBAS PRN 1xx -> ``Sxx``);
* ``signal`` is the RINEX 3 observation code without the type letter (``L1C``, ``L2L``, ``L5Q``,
  ``L1B``, ``L7Q``, BeiDou B1I ``L2I`` ...), ``wavelength_m`` from the carrier frequency
  (GLONASS FDMA from the frequency slot ``freqId - 7``);
* pseudorange NaN unless ``prValid``, carrier NaN unless ``cpValid``;
  ``half_cycle_ambiguous`` = carrier valid but the half-cycle ambiguity not yet resolved;
* RAWX ``doMes`` is documented by u-blox as "positive sign for approaching satellites", which is
  already the RINEX convention, so it is passed through unchanged (the tests check the sign
  against the pseudorange rate of the real log);
* ``lock_time_s`` from ``locktime`` (ms, saturates at 64.5 s); ``loss_of_lock`` is set when the
  lock time decreased, or when more time passed since the signal was last seen than the lock time
  covers.
"""
from __future__ import annotations

import calendar
import logging
import math
import struct
import time
from typing import Callable, Union

import numpy as np

from ..messages import (SECONDS_PER_WEEK, SPEED_OF_LIGHT_MPS, GnssBaseline, GnssEpoch, GnssFix, GpsEphemeris,
                        SatObservation)
from ..nav.earth import C_n_e, geodetic_to_ecef
from .ubx_sfrbx import SfrbxEphemerides

log = logging.getLogger(__name__)

UbxMessage = Union[GnssEpoch, GpsEphemeris, GnssFix, GnssBaseline]
# A week hint: a full GPS week number, or a callable returning the current GPS time estimate (s).
WeekHint = Union[int, Callable[[], float], None]

SYNC = b"\xb5\x62"
MAX_PAYLOAD = 8192          # RXM-RAWX with 255 measurements is 8176 bytes
GPS_EPOCH_UNIX_S = calendar.timegm((1980, 1, 6, 0, 0, 0))
DEFAULT_LEAP_SECONDS = 18   # GPS - UTC since 2017-01-01
ERA_WEEK = 2560             # reference for a 10-bit week with nothing better: weeks 2048-3071 (2019-2038)

# ---------------------------------------------------------------------------------------------
# Signals: carrier frequencies (Hz) by RINEX system letter and band digit.
_F = {
    "G": {"1": 1575.42e6, "2": 1227.60e6, "5": 1176.45e6},
    "J": {"1": 1575.42e6, "2": 1227.60e6, "5": 1176.45e6, "6": 1278.75e6},
    "S": {"1": 1575.42e6, "5": 1176.45e6},
    "E": {"1": 1575.42e6, "5": 1176.45e6, "7": 1207.14e6, "8": 1191.795e6, "6": 1278.75e6},
    "C": {"2": 1561.098e6, "1": 1575.42e6, "5": 1176.45e6, "7": 1207.14e6, "8": 1191.795e6,
          "6": 1268.52e6},
    "I": {"5": 1176.45e6, "9": 2492.028e6},
    "R": {"3": 1202.025e6, "4": 1600.995e6, "6": 1248.06e6},
}


def carrier_frequency_hz(sat: str, signal: str, glo_channel: int | None = None) -> float:
    """Carrier frequency of ``signal`` ('L1C', ...) on satellite ``sat``; NaN if unknown.

    GLONASS FDMA bands 1 and 2 need the frequency channel number k (-7..+6).
    """
    system, band = sat[0], signal[1:2]
    if system == "R" and band in ("1", "2"):
        if glo_channel is None or not -7 <= glo_channel <= 13:
            return math.nan
        return (1602.0e6 + glo_channel * 0.5625e6) if band == "1" else (1246.0e6 + glo_channel * 0.4375e6)
    return _F.get(system, {}).get(band, math.nan)


def wavelength_m(sat: str, signal: str, glo_channel: int | None = None) -> float:
    return SPEED_OF_LIGHT_MPS / carrier_frequency_hz(sat, signal, glo_channel)


# u-blox gnssId -> RINEX system letter
_GNSS_LETTER = {0: "G", 1: "S", 2: "E", 3: "C", 5: "J", 6: "R", 7: "I"}

# (gnssId, sigId) -> RINEX 3 signal code (u-blox F9 interface description, "Signal identifiers")
UBX_SIGNAL = {
    (0, 0): "L1C", (0, 3): "L2L", (0, 4): "L2S", (0, 6): "L5I", (0, 7): "L5Q",
    (1, 0): "L1C",
    (2, 0): "L1C", (2, 1): "L1B", (2, 3): "L5I", (2, 4): "L5Q", (2, 5): "L7I", (2, 6): "L7Q",
    (2, 8): "L6B", (2, 9): "L6C", (2, 10): "L6A",
    (3, 0): "L2I", (3, 1): "L2I", (3, 2): "L7I", (3, 3): "L7I", (3, 4): "L6I", (3, 10): "L6I",
    (3, 5): "L1P", (3, 6): "L1D", (3, 7): "L5P", (3, 8): "L5D",
    (5, 0): "L1C", (5, 1): "L1Z", (5, 4): "L2S", (5, 5): "L2L", (5, 8): "L5I", (5, 9): "L5Q",
    (6, 0): "L1C", (6, 2): "L2C",
    (7, 0): "L5A",
}


def ubx_sat_id(gnss_id: int, sv_id: int) -> str | None:
    """RINEX satellite id from u-blox gnssId/svId; None for IMES or an unknown GLONASS slot."""
    letter = _GNSS_LETTER.get(gnss_id)
    if letter is None:
        return None
    if letter == "S":
        prn = sv_id - 100 if sv_id >= 120 else None
    elif letter == "R":
        prn = sv_id if 1 <= sv_id <= 32 else None      # 255 = slot unknown
    elif letter == "J":
        prn = sv_id if sv_id < 193 else sv_id - 192
    else:
        prn = sv_id
    if prn is None or prn <= 0 or prn > 99:
        return None
    return f"{letter}{prn:02d}"


# ---------------------------------------------------------------------------------------------
class TimeReference:
    """Resolves a time of week to continuous GPS seconds near a reference time.

    The reference is, in order of preference: the last time this object resolved or was told
    (``update``), else the week hint: an int week (its middle), or a callable returning the
    current GPS time estimate (for a live link, e.g. from the system clock or the autopilot).
    """

    def __init__(self, week_hint: WeekHint = None):
        self.week_hint = week_hint
        self.t_last: float | None = None

    def reference(self) -> float | None:
        if self.t_last is not None:
            return self.t_last
        hint = self.week_hint
        if hint is None:
            return None
        if callable(hint):
            try:
                t = hint()
            except Exception:  # a failing clock callback must not break decoding
                log.exception("week_hint callable failed")
                return None
            return None if t is None else float(t)    # None = no reference yet: counted, no traceback
        return int(hint) * SECONDS_PER_WEEK + SECONDS_PER_WEEK / 2

    def week(self) -> int | None:
        ref = self.reference()
        return None if ref is None else int(ref // SECONDS_PER_WEEK)

    def update(self, t_gps: float) -> None:
        self.t_last = t_gps

    def resolve_tow(self, tow_s: float, period_s: float = SECONDS_PER_WEEK) -> float | None:
        """Continuous time congruent to ``tow_s`` modulo ``period_s`` nearest to the reference."""
        ref = self.reference()
        if ref is None:
            return None
        k = round((ref - tow_s) / period_s)
        return k * period_s + tow_s


def system_clock_gps_time(leap_seconds: int = DEFAULT_LEAP_SECONDS) -> float:
    """Current GPS time from the system clock (UTC + leap seconds); a ``week_hint`` for live use."""
    return time.time() - GPS_EPOCH_UNIX_S + leap_seconds


class RateLimitedLog:
    """One warning per reason per interval, with the running count."""

    def __init__(self, logger: logging.Logger, interval_s: float = 10.0):
        self.logger = logger
        self.interval_s = interval_s
        self._last: dict[str, float] = {}

    def warn(self, reason: str, count: int, detail: str = "") -> None:
        now = time.monotonic()
        last = self._last.get(reason)
        if last is None or now - last >= self.interval_s:
            self._last[reason] = now
            self.logger.warning("%s (%d so far)%s", reason, count, f": {detail}" if detail else "")


def ubx_checksum(body: bytes | bytearray | memoryview) -> tuple[int, int]:
    """8-bit Fletcher checksum over class, id, length and payload."""
    a = np.frombuffer(body, dtype=np.uint8).astype(np.int64)
    n = a.size
    ck_a = int(a.sum()) & 0xFF
    ck_b = int((a * np.arange(n, 0, -1, dtype=np.int64)).sum()) & 0xFF
    return ck_a, ck_b


def ubx_frame(msg_class: int, msg_id: int, payload: bytes) -> bytes:
    """A whole UBX frame: sync, class, id, length, payload, checksum."""
    body = bytes([msg_class, msg_id, len(payload) & 0xFF, len(payload) >> 8]) + bytes(payload)
    return b"\xb5\x62" + body + bytes(ubx_checksum(body))


RAWX_HEAD = struct.Struct("<dHbBBB2x")
RAWX_MEAS = struct.Struct("<ddfBBBBHBBBBBx")
_SFRBX_HEAD = struct.Struct("<BBBBBBBx")
_PVT = struct.Struct("<IHBBBBBBIiBBBBiiiiIIiiiiiIIH")
_TIMEGPS = struct.Struct("<IihbBI")

RXM_RAWX = (0x02, 0x15)
RXM_SFRBX = (0x02, 0x13)
NAV_PVT = (0x01, 0x07)
NAV_TIMEGPS = (0x01, 0x20)
NAV_RELPOSNED = (0x01, 0x3C)
MON_VER = (0x0A, 0x04)
_RELPOS_V1 = struct.Struct("<BBHIiiiii4xbbbbIIIII4xI")     # 64 bytes (F9P)
_RELPOS_V0 = struct.Struct("<BBHIiiibbbxIIII")             # 40 bytes (M8P)


class UbxDecoder:
    """Incremental UBX decoder; see the module docstring.

    Parameters
    ----------
    week_hint:
        GPS week (int) or callable returning the current GPS time estimate, used to resolve the
        10-bit week of SFRBX subframes and NAV-PVT's time of week before the first RXM-RAWX
        (which carries the full week) has been seen.
    check_parity:
        Verify the LNAV and BeiDou word parity of SFRBX subframes (the receiver has checked it
        already; a failure here means the log is corrupt or the layout assumption is wrong).
        Galileo pages are always CRC-checked.
    """

    def __init__(self, week_hint: WeekHint = None, check_parity: bool = True,
                 log_interval_s: float = 10.0):
        self._buf = bytearray()
        self.time_ref = TimeReference(week_hint)
        self.leap_seconds: int | None = None
        self.receiver_model = ""                 # MON-VER's, e.g. 'u-blox ZED-F9P'
        self.sfrbx = SfrbxEphemerides(check_parity=check_parity)
        self.ephemerides = self.sfrbx.gps       # GPS LNAV (its ``klobuchar`` feeds the pipeline)
        self.counters: dict[str, int] = {}
        self._rlog = RateLimitedLog(log, log_interval_s)
        self._lock: dict[tuple[str, str], tuple[float, float]] = {}

    # -- bookkeeping -----------------------------------------------------------------------
    def _count(self, reason: str, n: int = 1) -> None:
        self.counters[reason] = self.counters.get(reason, 0) + n

    def _reject(self, reason: str, detail: str = "", n: int = 1) -> None:
        self._count(reason, n)
        self._rlog.warn(f"UBX {reason}", self.counters[reason], detail)

    def _skip(self, buf: bytearray, start: int, end: int) -> None:
        """Count bytes outside UBX frames: text (NMEA interleaved on the same port) is normal and
        counted as ``text_bytes``; anything else is ``garbage_bytes`` and logged."""
        if end <= start:
            return
        if bytes(buf[start:end]).isascii():
            self._count("text_bytes", end - start)
        else:
            self._reject("garbage_bytes", n=end - start)

    @property
    def pending_bytes(self) -> int:
        """Bytes buffered waiting for the rest of a frame."""
        return len(self._buf)

    # -- framing ---------------------------------------------------------------------------
    def feed(self, data: bytes) -> list[UbxMessage]:
        out: list[UbxMessage] = []
        buf = self._buf
        buf += data
        pos = 0
        n = len(buf)
        while True:
            i = buf.find(SYNC, pos)
            if i < 0:
                # keep a trailing 0xB5 which may be the first half of a sync
                keep = 1 if n > pos and buf[-1] == 0xB5 else 0
                self._skip(buf, pos, n - keep)
                pos = n - keep
                break
            self._skip(buf, pos, i)
            pos = i
            if n - pos < 6:
                break
            length = buf[pos + 4] | (buf[pos + 5] << 8)
            if length > MAX_PAYLOAD:
                self._reject("bad_length", f"{length} bytes")
                pos += 2
                continue
            end = pos + 6 + length + 2
            if end > n:
                break
            body = memoryview(buf)[pos + 2:pos + 6 + length]
            ck_a, ck_b = ubx_checksum(body)
            if ck_a != buf[end - 2] or ck_b != buf[end - 1]:
                body.release()
                self._reject("bad_checksum", f"class 0x{buf[pos + 2]:02x} id 0x{buf[pos + 3]:02x}")
                pos += 2          # resync just after the false/corrupt sync
                continue
            msg_class, msg_id = buf[pos + 2], buf[pos + 3]
            payload = bytes(body[4:])
            body.release()
            pos = end
            self._count("frames")
            try:
                out.extend(self._dispatch(msg_class, msg_id, payload))
            except Exception as exc:  # never let one malformed payload stop the stream
                self._reject("bad_payload", f"class 0x{msg_class:02x} id 0x{msg_id:02x}: {exc!r}")
        del buf[:pos]
        return out

    def _dispatch(self, msg_class: int, msg_id: int, payload: bytes) -> list[UbxMessage]:
        key = (msg_class, msg_id)
        if key == RXM_RAWX:
            m = self._rawx(payload)
            return [m] if m is not None else []
        if key == RXM_SFRBX:
            m = self._sfrbx(payload)
            return [m] if m is not None else []
        if key == NAV_PVT:
            m = self._nav_pvt(payload)
            return [m] if m is not None else []
        if key == NAV_TIMEGPS:
            self._nav_timegps(payload)
            return []
        if key == NAV_RELPOSNED:
            m = self._nav_relposned(payload)
            return [m] if m is not None else []
        if key == MON_VER:
            self._mon_ver(payload)
            return []
        self._count("ignored_frames")
        return []

    # -- RXM-RAWX --------------------------------------------------------------------------
    def _rawx(self, p: bytes) -> GnssEpoch | None:
        if len(p) < 16:
            self._reject("bad_payload", "RXM-RAWX too short")
            return None
        rcv_tow, week, leap_s, num_meas, rec_stat, _version = RAWX_HEAD.unpack_from(p, 0)
        if len(p) != 16 + 32 * num_meas:
            self._reject("bad_payload", f"RXM-RAWX length {len(p)} for {num_meas} measurements")
            return None
        if not (0.0 <= rcv_tow < SECONDS_PER_WEEK) or week == 0:
            self._reject("rawx_bad_time", f"week {week} tow {rcv_tow}")
            return None
        t_gps = week * SECONDS_PER_WEEK + rcv_tow
        if rec_stat & 0x01:
            self.leap_seconds = leap_s
        self.time_ref.update(t_gps)
        self._count("rawx")
        obs: list[SatObservation] = []
        for k in range(num_meas):
            (pr, cp, do, gnss_id, sv_id, sig_id, freq_id, lock_ms, cno, _prs, _cps, _dos,
             trk) = RAWX_MEAS.unpack_from(p, 16 + 32 * k)
            sat = ubx_sat_id(gnss_id, sv_id)
            signal = UBX_SIGNAL.get((gnss_id, sig_id))
            if sat is None or signal is None:
                self._count("rawx_unknown_signal")
                continue
            glo_k = freq_id - 7 if sat[0] == "R" else None
            lam = wavelength_m(sat, signal, glo_k)
            pr_valid = bool(trk & 0x01)
            cp_valid = bool(trk & 0x02) and math.isfinite(lam)
            half_cyc_valid = bool(trk & 0x04)
            lock_s = lock_ms * 1e-3
            slip = False
            if cp_valid:
                prev = self._lock.get((sat, signal))
                if prev is not None:
                    t_prev, lock_prev = prev
                    slip = lock_s < lock_prev or (lock_ms < 64500 and t_gps - t_prev > lock_s + 1e-3)
                self._lock[(sat, signal)] = (t_gps, lock_s)
            obs.append(SatObservation(
                sat=sat,
                pseudorange_m=pr if pr_valid else math.nan,
                carrier_cycles=cp if cp_valid else math.nan,
                doppler_hz=float(do),
                cn0_dbhz=float(cno),
                lock_time_s=lock_s,
                half_cycle_ambiguous=cp_valid and not half_cyc_valid,
                loss_of_lock=slip,
                signal=signal,
                wavelength_m=lam,
            ))
        return GnssEpoch(t_gps=t_gps, observations=tuple(obs), source="rover")

    # -- RXM-SFRBX -------------------------------------------------------------------------
    def _sfrbx(self, p: bytes) -> GpsEphemeris | None:
        if len(p) < 8:
            self._reject("bad_payload", "RXM-SFRBX too short")
            return None
        gnss_id, sv_id, sig_id, freq_id, num_words, _chn, _ver = _SFRBX_HEAD.unpack_from(p, 0)
        if len(p) != 8 + 4 * num_words:
            self._reject("bad_payload", f"RXM-SFRBX length {len(p)} for {num_words} words")
            return None
        self._count("sfrbx")
        sat = ubx_sat_id(gnss_id, sv_id)
        if sat is None:
            self._count("sfrbx_unknown_satellite")
            return None
        words = struct.unpack_from(f"<{num_words}I", p, 8)
        ref_week = self.time_ref.week()
        if ref_week is None:
            ref_week = ERA_WEEK
        eph, reason = self.sfrbx.add(sat[0], sat, sig_id, words, ref_week, freq_id=freq_id,
                                     t_rx_gps=self.time_ref.t_last, leap_seconds=self.leap_seconds)
        if reason == "not_decoded":
            self._count(f"sfrbx_not_decoded_{sat[0]}")
        elif reason == "glonass_no_time":
            self._count("sfrbx_glonass_no_time")          # before the first RXM-RAWX: not the data's fault
        elif reason:
            self._reject(f"sfrbx_{reason}", sat)
        if eph is not None:
            self._count("ephemerides")
            self._count(f"ephemerides_{sat[0]}")
        return eph

    # -- MON-VER ---------------------------------------------------------------------------
    def _mon_ver(self, p: bytes) -> None:
        """The receiver's model: the 'MOD=' extension (F9: 'MOD=ZED-F9P'), else its hardware
        version (the firmware is not part of it: the channel biases are the hardware's)."""
        if len(p) < 40 or (len(p) - 40) % 30:
            self._reject("bad_payload", f"MON-VER length {len(p)}")
            return
        def text(b: bytes) -> str:
            return b.split(b"\0", 1)[0].decode("ascii", "replace").strip()
        ext = [text(p[k:k + 30]) for k in range(40, len(p), 30)]
        mod = next((e[4:] for e in ext if e.startswith("MOD=")), "") or f"hardware {text(p[30:40])}"
        self.receiver_model = f"u-blox {mod}"
        self._count("mon_ver")

    # -- NAV-TIMEGPS / NAV-PVT -------------------------------------------------------------
    def _nav_timegps(self, p: bytes) -> None:
        if len(p) < 16:
            self._reject("bad_payload", "NAV-TIMEGPS too short")
            return
        itow, ftow, week, leap_s, valid, _tacc = _TIMEGPS.unpack_from(p, 0)
        if valid & 0x04:
            self.leap_seconds = leap_s
        if valid & 0x03 == 0x03:
            self.time_ref.update(week * SECONDS_PER_WEEK + itow * 1e-3 + ftow * 1e-9)

    def _nav_relposned(self, p: bytes) -> GnssBaseline | None:
        f = _relposned_fields(p)
        if f is None:
            self._reject("bad_payload", f"NAV-RELPOSNED: {len(p)} bytes, version {p[0] if p else '?'}")
            return None
        flags = f["flags"]
        if not (flags & 0x01 and flags & 0x04):          # gnssFixOK, relPosValid
            self._count("relposned_invalid")
            return None
        t_gps = self.time_ref.resolve_tow(f["tow_s"])
        if t_gps is None:
            self._reject("relposned_unknown_week")
            return None
        self._count("nav_relposned")
        return GnssBaseline(t_gps=t_gps, rel_pos_ned_m=f["ned_m"], sigma_ned_m=f["acc_m"],
                            carrier_fixed=((flags >> 3) & 0x03) == 2, length_sigma_m=f["acc_len_m"])

    def _nav_pvt(self, p: bytes) -> GnssFix | None:
        if len(p) < _PVT.size:
            self._reject("bad_payload", "NAV-PVT too short")
            return None
        (itow, year, month, day, hour, minute, sec, valid, _tacc, nano, fix_type, flags, _flags2,
         num_sv, lon, lat, height, _hmsl, hacc, vacc, vel_n, vel_e, vel_d, _gspeed, _headmot,
         sacc, _headacc, _pdop) = _PVT.unpack_from(p, 0)
        tow = itow * 1e-3
        t_gps = self.time_ref.resolve_tow(tow)
        if t_gps is None and (valid & 0x03) == 0x03 and 1980 <= year < 2100:
            try:
                leap = self.leap_seconds if self.leap_seconds is not None else DEFAULT_LEAP_SECONDS
                t_utc = calendar.timegm((year, month, day, hour, minute, sec)) - GPS_EPOCH_UNIX_S
                approx = t_utc + nano * 1e-9 + leap
                k = round((approx - tow) / SECONDS_PER_WEEK)
                t_gps = k * SECONDS_PER_WEEK + tow
            except (ValueError, OverflowError):
                t_gps = None
        if t_gps is None:
            self._reject("pvt_unknown_week")
            return None
        self.time_ref.update(t_gps)
        self._count("nav_pvt")
        lat_rad = math.radians(lat * 1e-7)
        lon_rad = math.radians(lon * 1e-7)
        r_e = geodetic_to_ecef(lat_rad, lon_rad, height * 1e-3)
        v_e = C_n_e(lat_rad, lon_rad) @ np.array([vel_n, vel_e, vel_d], float) * 1e-3
        gnss_fix_ok = bool(flags & 0x01)
        if not gnss_fix_ok or fix_type in (0, 5):
            ft = 0
        elif fix_type == 2:
            ft = 2
        else:
            ft = 3
            carr = (flags >> 6) & 0x03
            if carr == 2:
                ft = 6
            elif carr == 1:
                ft = 5
            elif flags & 0x02:
                ft = 4
        return GnssFix(t_gps=t_gps, r_e=r_e, v_e=v_e, sigma_h_m=hacc * 1e-3, sigma_v_m=vacc * 1e-3,
                       sigma_vel_mps=sacc * 1e-3, num_sats=num_sv, fix_type=ft)


def _relposned_fields(p: bytes) -> dict | None:
    """NAV-RELPOSNED payload -> N/E/D (m), their accuracies (m), length accuracy (m, NaN in v0),
    iTOW (s), flags; None if too short or of an unknown version."""
    if len(p) >= _RELPOS_V1.size and p[0] == 1:
        (_v, _r, _ref, itow, n, e, d, _length, _heading, hpn, hpe, hpd, _hpl, acc_n, acc_e, acc_d, acc_l,
         _acc_h, flags) = _RELPOS_V1.unpack_from(p, 0)
        acc_len = acc_l * 1e-4
    elif len(p) >= _RELPOS_V0.size and p[0] == 0:
        _v, _r, _ref, itow, n, e, d, hpn, hpe, hpd, acc_n, acc_e, acc_d, flags = _RELPOS_V0.unpack_from(p, 0)
        acc_len = float("nan")
    else:
        return None
    # cm + 0.1 mm high-precision parts; accuracies in 0.1 mm
    ned = np.array([n * 1e-2 + hpn * 1e-4, e * 1e-2 + hpe * 1e-4, d * 1e-2 + hpd * 1e-4])
    return {"tow_s": itow * 1e-3, "ned_m": ned, "acc_m": np.array([acc_n, acc_e, acc_d]) * 1e-4,
            "acc_len_m": acc_len, "flags": flags}


def decode_ubx_file(path: str, week_hint: WeekHint = None, chunk_size: int = 4096) -> tuple[list[UbxMessage], UbxDecoder]:
    """Convenience: decode a whole UBX file (in chunks, like a live stream)."""
    dec = UbxDecoder(week_hint=week_hint)
    out: list[UbxMessage] = []
    with open(path, "rb") as f:
        while chunk := f.read(chunk_size):
            out.extend(dec.feed(chunk))
    return out, dec
