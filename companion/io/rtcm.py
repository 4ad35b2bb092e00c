"""RTCM 3 -> typed navigation messages, RTCM frame splitting and MAVLink GPS_RTCM_DATA fragments.

* :class:`RtcmFramer` splits a byte stream (NTRIP, serial radio, MQTT payloads, a file) into
  whole RTCM 3 frames (``0xD3``, 6 reserved bits, 10-bit length, payload, CRC-24Q).  Frames whose
  CRC fails are counted and skipped; the framer resynchronises one byte after the false preamble,
  so the good frames that follow are not lost.  The frames it returns are what the service
  forwards to the autopilot.
* :class:`RtcmDecoder` decodes frames (field extraction by pyrtcm) into

  - :class:`~companion.messages.BaseStationPosition` from 1005/1006 (ARP, ECEF; 1006 adds the
    antenna height, informational: DF025-027 already are the ARP);
  - :class:`~companion.messages.GnssEpoch` (``source='base'``) from legacy 1004 (GPS L1/L2) and
    from MSM4-MSM7 of GPS (107x), GLONASS (108x), Galileo (109x), SBAS (110x), QZSS (111x),
    BeiDou (112x) and NavIC (113x), with RINEX 3 signal codes (pyrtcm's tables, RTKLIB's: BeiDou
    B1I 'L2I', Galileo E1 'L1C', E5a 'L5Q', E5b 'L7Q').  All messages of one epoch are merged into
    one GnssEpoch by :class:`~companion.io.rtcm_epoch.EpochAssembler` (lost frames, late flushes,
    whole-second system offsets: see there);
  - :class:`~companion.messages.GpsEphemeris` from 1019 (GPS), 1044 (QZSS), 1042 (BeiDou) and
    1045/1046 (Galileo F/NAV, I/NAV; ``galileo_nav`` chooses), once per new issue per satellite
    (:mod:`companion.io.rtcm_eph`: the field scaling, checked against convbin).
  - 1007 / 1008 / 1033 (the base's antenna and receiver descriptors) are kept as
    ``base_descriptor`` (:mod:`companion.io.rtcm_descriptor`), not emitted;
  - 1020 (GLONASS ephemeris) gives the satellites' FDMA frequency channels, a
    :class:`~companion.gnss.glonass.GlonassEphemeris` once per new issue per satellite (the
    engine fuses GLONASS when ``[filter] systems`` names R), and ``glonass_ephemerides`` /
    ``glonass_history`` (the post-processing RTK takes them from a base capture).

Times: RTCM carries time of week (GPS, Galileo, QZSS, SBAS, NavIC: GPS TOW in ms; BeiDou: BDT =
GPS - 14 s; GLONASS: day of week + Moscow time of day, converted with ``leap_seconds``; once the
decoder tracks time the GLONASS day is the one nearest it, the day-of-week field only places the
first epoch).  The full week is resolved against ``week_hint``: an int GPS week, or a callable
returning the current GPS time estimate (e.g. :func:`companion.io.ubx.system_clock_gps_time` for a
live link, or the nav engine's time).  After the first epoch the decoder tracks its own time, so
week roll-overs during a session are handled.  Without any hint, observation epochs and
ephemerides are dropped and counted (``no_time_reference``): a replay must say what week it is.

Observation conventions are those of :class:`~companion.messages.SatObservation`: pseudorange and
carrier (cycles, RINEX sign) from rough + fine ranges; Doppler (MSM5/7) = -range rate / lambda;
``lock_time_s`` is the *minimum* lock time the indicator guarantees; ``loss_of_lock`` is set when
the lock time indicator decreased (RTKLIB's rule); ``half_cycle_ambiguous`` from DF420.
"""
from __future__ import annotations

import logging
import math
from typing import Union

import numpy as np
from pyrtcm import RTCMReader

from ..messages import SECONDS_PER_WEEK, BaseStationPosition, GnssEpoch, GpsEphemeris, SatObservation
from .crc24q import crc24q
from .rtcm_descriptor import BaseDescriptor, base_descriptor, merged
from .rtcm_epoch import EpochAssembler
from .rtcm_eph import (GALILEO_FNAV, GALILEO_INAV, GlonassEphemeris, beidou_ephemeris, galileo_ephemeris,
                       glonass_ephemeris, gps_ephemeris, qzss_ephemeris)
from .ubx import (DEFAULT_LEAP_SECONDS, RateLimitedLog, TimeReference, WeekHint,
                  wavelength_m)

log = logging.getLogger(__name__)

RtcmMessage = Union[GnssEpoch, GpsEphemeris, BaseStationPosition]

PREAMBLE = 0xD3
#: GLONASS issues held in ``RtcmDecoder.glonass_history`` (24 satellites x 48 issues a day = 1152: a day)
MAX_GLONASS_HISTORY = 1152
MS_TO_M = 299792.458          # light travel in one millisecond, m

# --------------------------------------------------------------------------------------------
# Framing.  The CRC lives in crc24q.py (C speed when anycrc is installed).

# Message numbers a frame may carry: the standard's 1001-1320 (RTCM 10403.3 ends at 1305) and
# the proprietary 4001-4095.  Anything else after a 0xD3 (the experimental 1-100 included: never
# seen from a caster) is a false sync, rejected before any CRC is computed.
_MSG_RANGES = ((1001, 1320), (4001, 4095))
# Messages of fixed payload length (bytes; checked on the recordings in tests/data): a false sync
# claiming one of these numbers with another length is rejected before the CRC too.
_FIXED_LENGTH = {1005: 19, 1006: 21, 1019: 61, 1020: 45, 1041: 61, 1042: 64, 1044: 61, 1045: 62,
                 1046: 63}
MAX_FRAME = 3 + 1023 + 3           # preamble + header, longest payload, CRC


def known_message_number(mtype: int) -> bool:
    for lo, hi in _MSG_RANGES:
        if lo <= mtype <= hi:
            return True
    return False


def frame_message_type(frame: bytes) -> int:
    """Message number (first 12 payload bits) of a whole frame."""
    return (frame[3] << 4) | (frame[4] >> 4) if len(frame) >= 6 else -1


class RtcmFramer:
    """Incremental splitter of a byte stream into CRC-checked RTCM 3 frames.

    ``feed(data)`` returns the complete frames (bytes, preamble to CRC inclusive).  ``counters``
    (stable keys): ``frames``; ``garbage_bytes`` (bytes skipped between frames); the false syncs,
    each one 0xD3 that did not start a frame: ``bad_header`` (reserved bits set), ``bad_length``
    (zero, or not the fixed length of its message number), ``bad_message_number`` (outside
    1001-1320 / 4001-4095), ``bad_crc``.

    Work per byte is bounded: every candidate 0xD3 costs a few byte tests, and only a candidate
    that passes them all costs one CRC (over at most 1026 bytes, at C speed); a candidate is
    examined once, however the stream is chunked (the scan resumes where it stopped, and a
    candidate waiting for the rest of its frame is only re-checked when more bytes arrive).
    ``crc_bytes`` in the counters is the total CRC work, so a test can bound it per input byte.
    """

    def __init__(self, log_interval_s: float = 10.0, name: str = "RTCM"):
        self._buf = bytearray()
        self.counters: dict[str, int] = {}
        self._rlog = RateLimitedLog(log, log_interval_s)
        self.name = name
        self.bytes_in = 0

    def _count(self, reason: str, n: int = 1) -> None:
        self.counters[reason] = self.counters.get(reason, 0) + n

    def _reject(self, reason: str, detail: str = "", n: int = 1) -> None:
        self._count(reason, n)
        self._rlog.warn(f"{self.name} {reason}", self.counters[reason], detail)

    @property
    def pending_bytes(self) -> int:
        return len(self._buf)

    def _precheck(self, buf: bytearray, pos: int, n: int) -> str | None:
        """Why the 0xD3 at ``pos`` cannot start a frame (None: it may; check the CRC).  Needs
        ``n - pos >= 5``: preamble, reserved + length, 12-bit message number."""
        b1 = buf[pos + 1]
        if b1 & 0xFC:
            return "bad_header"
        length = ((b1 & 0x03) << 8) | buf[pos + 2]
        if length < 2:
            return "bad_length"
        mtype = (buf[pos + 3] << 4) | (buf[pos + 4] >> 4)
        if not known_message_number(mtype):
            return "bad_message_number"
        fixed = _FIXED_LENGTH.get(mtype)
        if fixed is not None and fixed != length:
            return "bad_length"
        return None

    def feed(self, data: bytes) -> list[bytes]:
        frames: list[bytes] = []
        buf = self._buf
        buf += data
        self.bytes_in += len(data)
        n = len(buf)
        pos = 0
        false_syncs = garbage = 0
        while True:
            i = buf.find(PREAMBLE, pos)
            if i < 0:
                garbage += n - pos
                pos = n
                break
            garbage += i - pos
            pos = i
            if n - pos < 5:
                break
            why = self._precheck(buf, pos, n)
            if why is None:
                length = ((buf[pos + 1] & 0x03) << 8) | buf[pos + 2]
                end = pos + 3 + length + 3
                if end > n:
                    break                  # wait for the rest; only this candidate is re-checked
                self._count("crc_bytes", end - pos - 3)
                crc = (buf[end - 3] << 16) | (buf[end - 2] << 8) | buf[end - 1]
                if crc24q(memoryview(buf)[pos:end - 3]) == crc:
                    frames.append(bytes(buf[pos:end]))
                    self._count("frames")
                    pos = end
                    continue
                why = "bad_crc"
            # a false sync: count it, skip the 0xD3, resume the scan at the next byte
            self._count(why)
            garbage += 1
            false_syncs += 1
            pos += 1
        if garbage:
            self._count("garbage_bytes", garbage)
        if false_syncs:
            # one rate-limited line per chunk, not per false sync: a flood must not flood the log
            self._rlog.warn(f"{self.name} false syncs", sum(
                self.counters.get(k, 0) for k in ("bad_header", "bad_length", "bad_message_number", "bad_crc")),
                f"{false_syncs} in the last {len(data)} bytes")
        elif garbage:
            self._rlog.warn(f"{self.name} garbage_bytes", self.counters["garbage_bytes"])
        del buf[:pos]
        return frames


# --------------------------------------------------------------------------------------------
# MAVLink GPS_RTCM_DATA fragmentation (common.xml message 233; ArduPilot AP_GPS::handle_gps_rtcm_fragment).
GPS_RTCM_DATA_LEN = 180
GPS_RTCM_MAX_FRAGMENTS = 4


def rtcm_to_gps_rtcm_data_fragments(frame: bytes, seq: int) -> list[tuple[int, bytes]]:
    """Split one RTCM frame into GPS_RTCM_DATA ``(flags, data)`` pairs (data unpadded; its length
    is the message's ``len`` field and the caller pads ``data`` to 180 bytes).

    flags: bit 0 = fragmented, bits 1-2 = fragment id, bits 3-7 = sequence id (``seq & 0x1F``).

    * ``len(frame) <= 180``: one unfragmented message (ArduPilot injects it directly).
    * 181..720 bytes: fragments of 180 bytes, the last shorter.  The autopilot knows it has the
      whole frame when a fragment shorter than 180 bytes arrives, or when all four fragments
      are full; so a frame of exactly 360 or 540 bytes is followed by a zero-length fragment.
    * more than 720 bytes: cannot be sent (two bits of fragment id): returns ``[]``.
    """
    n = len(frame)
    if n == 0 or n > GPS_RTCM_DATA_LEN * GPS_RTCM_MAX_FRAGMENTS:
        return []
    seq_bits = (seq & 0x1F) << 3
    if n <= GPS_RTCM_DATA_LEN:
        return [(seq_bits, bytes(frame))]
    chunks = [bytes(frame[i:i + GPS_RTCM_DATA_LEN]) for i in range(0, n, GPS_RTCM_DATA_LEN)]
    if n % GPS_RTCM_DATA_LEN == 0 and len(chunks) < GPS_RTCM_MAX_FRAGMENTS:
        chunks.append(b"")
    return [(1 | (k << 1) | seq_bits, c) for k, c in enumerate(chunks)]


class GpsRtcmDataFragmenter:
    """Stateful wrapper: advances the 5-bit sequence id per frame and counts dropped frames."""

    def __init__(self):
        self.seq = 0
        self.counters: dict[str, int] = {"frames": 0, "fragments": 0, "dropped_too_long": 0}

    def fragments(self, frame: bytes) -> list[tuple[int, bytes]]:
        out = rtcm_to_gps_rtcm_data_fragments(frame, self.seq)
        if not out:
            self.counters["dropped_too_long"] += 1
            log.warning("RTCM frame of %d bytes is too long for GPS_RTCM_DATA, dropped", len(frame))
            return []
        self.seq = (self.seq + 1) & 0x1F
        self.counters["frames"] += 1
        self.counters["fragments"] += len(out)
        return out


# --------------------------------------------------------------------------------------------
# Lock time indicators -> minimum lock time (s)
def lock_time_df013(i: int) -> float:
    """1004 / 1012 L1/L2 lock time indicator (7 bits) -> minimum lock time, s."""
    if i < 24:
        return float(i)
    if i < 48:
        return 2.0 * i - 24
    if i < 72:
        return 4.0 * i - 120
    if i < 96:
        return 8.0 * i - 408
    if i < 120:
        return 16.0 * i - 1176
    if i < 127:
        return 32.0 * i - 3096
    return 937.0


def lock_time_df402(i: int) -> float:
    """MSM4/5 lock time indicator (4 bits) -> minimum lock time, s."""
    return 0.0 if i == 0 else 2.0 ** (i + 4) * 1e-3


def lock_time_df407(i: int) -> float:
    """MSM6/7 extended lock time indicator (10 bits) -> minimum lock time, s."""
    if i < 64:
        return i * 1e-3
    if i > 704:
        return math.nan
    if i == 704:
        return 67108.864
    n = (i - 64) // 32 + 1
    offset = 0
    for k in range(1, n + 1):
        offset += 2 ** (k - 1) * 32 * (k + 1)
    return (2 ** n * i - offset) * 1e-3


# --------------------------------------------------------------------------------------------
# MSM: message number -> (system letter, msm type)
_MSM_SYSTEMS = {107: "G", 108: "R", 109: "E", 110: "S", 111: "J", 112: "C", 113: "I"}
_MSM_TIME_FIELD = {"G": "DF004", "R": None, "E": "DF248", "S": "DF004", "J": "DF428",
                   "C": "DF427", "I": "DF546"}
_INVALID_FINE_PR_MS = -2.0 ** -10      # DF400 / DF405 "invalid" marker after scaling
_INVALID_FINE_PH_MS = -2.0 ** -8       # DF401 / DF406
_INVALID_FINE_RATE = -1.6384           # DF404


def _msm_sat_id(system: str, prn: int) -> str | None:
    if system == "J" and prn > 192:
        prn -= 192
    elif system == "S":
        prn = prn - 100 if prn >= 100 else prn + 19
    if not 1 <= prn <= 99:
        return None
    return f"{system}{prn:02d}"


class _TimeReference(TimeReference):
    """A ``week_hint`` callable that returns None (the pipeline before its first IMU sample) means
    "no time reference yet": the decoder counts ``no_time_reference`` and drops the message,
    instead of a logged traceback per frame.  A callable that raises is counted and logged at a
    limited rate (``week_hint_errors``)."""

    def __init__(self, week_hint: WeekHint, count, rlog: RateLimitedLog):
        super().__init__(week_hint)
        self._count_cb, self._rlog = count, rlog

    def reference(self) -> float | None:
        if self.t_last is None and callable(self.week_hint):
            try:
                t = self.week_hint()
                return None if t is None else float(t)
            except Exception as exc:
                n = self._count_cb("week_hint_errors")
                self._rlog.warn("RTCM week_hint_errors", n, repr(exc))
                return None
        return super().reference()


class RtcmDecoder:
    """Incremental RTCM 3 decoder; see the module docstring.

    ``feed(data, t_rx_s)`` frames and decodes; ``decode_frame(frame, t_rx_s)`` decodes one already
    framed message (use this when the same frames are also forwarded).  ``t_rx_s`` (optional: any
    monotonic receive clock, s) lets an open epoch whose last frames were lost be closed
    ``rtcm_epoch.TIMEOUT_S`` after its last frame (``poll(t_rx_s)`` does it without data); without
    it, epochs close on their last frame, on the next epoch's first frame, or on a non-observation
    frame (see :mod:`companion.io.rtcm_epoch`).  ``flush()`` returns what is open (end of file).
    ``counters`` merges the framer's and the decoder's.

    ``galileo_nav``: which Galileo navigation message feeds the ephemerides: ``'inav'`` (default:
    1046, what u-blox SFRBX and E1/E5b receivers use; a 1045 is held until the next observation
    message and dropped if that satellite's 1046 came meanwhile or ever before, so an F/NAV-only
    caster still works), ``'fnav'`` (the mirror image) or ``'both'``.  GLONASS 1020 ephemerides are
    decoded into ``glonass_ephemerides`` (latest per satellite) and ``glonass_history`` (every
    issue, the last :data:`MAX_GLONASS_HISTORY`), not emitted: the engine does not model GLONASS.
    """

    def __init__(self, week_hint: WeekHint = None, leap_seconds: int = DEFAULT_LEAP_SECONDS,
                 log_interval_s: float = 10.0, galileo_nav: str = GALILEO_INAV):
        if galileo_nav not in (GALILEO_INAV, GALILEO_FNAV, "both"):
            raise ValueError(f"galileo_nav must be 'inav', 'fnav' or 'both', not {galileo_nav!r}")
        self.framer = RtcmFramer(log_interval_s)
        self.leap_seconds = leap_seconds
        self.galileo_nav = galileo_nav
        self._counters: dict[str, int] = {}
        self._rlog = RateLimitedLog(log, log_interval_s)
        self.time_ref = _TimeReference(week_hint, self._count, self._rlog)
        self.epochs = EpochAssembler(self._count)
        self._lock: dict[tuple[str, str], float] = {}
        self._cp_adj: dict[tuple[str, str], float] = {}
        self._glo_channel: dict[int, int] = {}
        self._eph_last: dict[tuple[str, str], tuple] = {}
        self._gal_seen: dict[str, set[str]] = {GALILEO_INAV: set(), GALILEO_FNAV: set()}
        self._gal_held: dict[str, GpsEphemeris] = {}
        self.glonass_ephemerides: dict[str, GlonassEphemeris] = {}
        # every issue, first copy kept (a post-processed capture needs the earlier ones too)
        self.glonass_history: dict[tuple[str, float], GlonassEphemeris] = {}
        # what the base says it is (1007 / 1008 / 1033), the latest
        self.base_descriptor: BaseDescriptor | None = None
        self._t_rx: float | None = None

    @property
    def counters(self) -> dict[str, int]:
        out = dict(self.framer.counters)
        for k, v in self._counters.items():
            out[k] = out.get(k, 0) + v
        return out

    def _count(self, reason: str, n: int = 1) -> int:
        self._counters[reason] = c = self._counters.get(reason, 0) + n
        return c

    def _reject(self, reason: str, detail: str = "") -> None:
        self._count(reason)
        self._rlog.warn(f"RTCM {reason}", self._counters[reason], detail)

    # -- entry points ------------------------------------------------------------------------
    def feed(self, data: bytes, t_rx_s: float | None = None) -> list[RtcmMessage]:
        out: list[RtcmMessage] = self.poll(t_rx_s) if t_rx_s is not None else []
        for frame in self.framer.feed(data):
            out.extend(self.decode_frame(frame, t_rx_s))
        return out

    def poll(self, t_rx_s: float) -> list[RtcmMessage]:
        """Close an open epoch whose last frame arrived more than the timeout before ``t_rx_s``."""
        return list(self.epochs.poll(t_rx_s))

    def flush(self) -> list[RtcmMessage]:
        return [*self.epochs.flush(), *self._release_held()]

    def decode_frame(self, frame: bytes, t_rx_s: float | None = None) -> list[RtcmMessage]:
        mtype = frame_message_type(frame)
        self._t_rx = t_rx_s
        out: list[RtcmMessage] = []
        if not _is_observation(mtype):
            out += self.epochs.other_frame(t_rx_s)   # the open set ended before this frame
        try:
            return out + self._decode(mtype, frame)
        except Exception as exc:  # malformed content in a CRC-valid frame: never raise
            self._reject("bad_payload", f"type {mtype}: {exc!r}")
            return out

    # -- dispatch ----------------------------------------------------------------------------
    def _decode(self, mtype: int, frame: bytes) -> list[RtcmMessage]:
        family, sub = divmod(mtype, 10)
        if family in _MSM_SYSTEMS and 1 <= sub <= 7:
            msg = RTCMReader.parse(frame, validate=0, labelmsm=1)
            system = _MSM_SYSTEMS[family]
            if sub < 4:
                # no full pseudorange in MSM1-3: only keep the epoch bookkeeping right
                self._count("msm1_3_unsupported")
                t_gps = self._msm_time(msg, system)
                return [] if t_gps is None else self._add_observations(t_gps, [], bool(msg.DF393), system)
            return self._msm(msg, system, sub)
        if mtype in (1005, 1006):
            msg = RTCMReader.parse(frame, validate=0)
            self._count("station")
            return [BaseStationPosition(
                station_id=int(msg.DF003),
                r_e=np.array([msg.DF025, msg.DF026, msg.DF027], float),
                antenna_height_m=float(getattr(msg, "DF028", 0.0)))]
        if mtype in (1007, 1008, 1033):
            self.base_descriptor = merged(self.base_descriptor, base_descriptor(mtype, RTCMReader.parse(frame, validate=0)))
            self._count("descriptor")
            return []
        if mtype in (1002, 1004):
            msg = RTCMReader.parse(frame, validate=0)
            return self._legacy_gps(msg)
        if mtype in (1010, 1012):
            msg = RTCMReader.parse(frame, validate=0)
            return self._legacy_glonass(msg)
        if mtype in (1001, 1003, 1009, 1011):
            # no integer-millisecond ambiguity: no full pseudorange.  Keep epoch bookkeeping.
            msg = RTCMReader.parse(frame, validate=0)
            self._count(f"ignored_{mtype}")
            if mtype < 1009:
                t_gps = self._resolve(msg.DF004 * 1e-3)
                sys_ = "G"
            else:
                t_gps = self._glonass_time(int(msg.DF034) * 1e-3, None)
                sys_ = "R"
            return [] if t_gps is None else self._add_observations(t_gps, [], bool(msg.DF005), sys_)
        if mtype in _EPHEMERIS_TYPES:
            return self._ephemeris(mtype, RTCMReader.parse(frame, validate=0))
        if mtype == 1020:
            msg = RTCMReader.parse(frame, validate=0)
            self._glo_channel[int(msg.DF038)] = int(msg.DF040) - 7
            self._count("glonass_channel")
            ref = self.time_ref.reference()
            if ref is not None:
                eph = glonass_ephemeris(msg, ref, self.leap_seconds)
                self.glonass_ephemerides[eph.sat] = eph
                new = (eph.sat, eph.t_oe_gps) not in self.glonass_history
                self.glonass_history.setdefault((eph.sat, eph.t_oe_gps), eph)
                if len(self.glonass_history) > MAX_GLONASS_HISTORY:
                    self.glonass_history.pop(next(iter(self.glonass_history)))     # the oldest
                if new:
                    return [eph]
            return []
        self._count(f"ignored_{mtype}")
        return []

    # -- epochs ------------------------------------------------------------------------------
    def _add_observations(self, t_gps: float, obs: list[SatObservation], more_follow: bool,
                          system: str) -> list[RtcmMessage]:
        out: list[RtcmMessage] = []
        closed, t_filed = self.epochs.add(t_gps, system, obs, more_follow, self._t_rx)
        out += closed
        if t_filed is not None:
            self.time_ref.update(t_filed)
        out += self._release_held()
        return out

    def _resolve(self, tow_s: float, period_s: float = SECONDS_PER_WEEK) -> float | None:
        t = self.time_ref.resolve_tow(tow_s, period_s)
        if t is None:
            self._reject("no_time_reference", "pass week_hint to RtcmDecoder")
        return t

    def _slip(self, sat: str, signal: str, lock_s: float) -> bool:
        prev = self._lock.get((sat, signal))
        self._lock[(sat, signal)] = lock_s
        return prev is not None and lock_s < prev

    # -- 1004 --------------------------------------------------------------------------------
    def _adjust_cp(self, key: tuple[str, str], cp_cycles: float) -> float:
        """Undo the sender's 1500-cycle roll-overs of the phase-minus-pseudorange difference."""
        prev = self._cp_adj.get(key)
        if prev is not None:
            if cp_cycles < prev - 750.0:
                cp_cycles += 1500.0 * math.ceil((prev - 750.0 - cp_cycles) / 1500.0)
            elif cp_cycles > prev + 750.0:
                cp_cycles -= 1500.0 * math.ceil((cp_cycles - prev - 750.0) / 1500.0)
        self._cp_adj[key] = cp_cycles
        return cp_cycles

    def _legacy_gps(self, msg) -> list[RtcmMessage]:
        t_gps = self._resolve(msg.DF004 * 1e-3)
        if t_gps is None:
            return []
        self._count(f"obs_{msg.identity}")
        obs = self._legacy_obs(msg, "G", int(msg.DF006), MS_TO_M,
                               ("DF009", "DF010", "DF011", "DF012", "DF013", "DF014", "DF015",
                                "DF016", "DF017", "DF018", "DF019", "DF020"),
                               ("L1C", "L1P"), ("L2X", "L2P", "L2D", "L2W"))
        return self._add_observations(t_gps, obs, bool(msg.DF005), "G")

    def _glonass_time(self, tod_msk_s: float, dow: int | None) -> float | None:
        """GPS time from GLONASS time of day (Moscow = UTC + 3 h) and day of week (7 or None: not
        given).  Once the decoder tracks time, the day is the one nearest that time (RTKLIB's
        adjday_glot): a wrong or missing day of week cannot fool it; before, the day of week
        places the first epoch against a week-number hint."""
        tod_gps = tod_msk_s - 3 * 3600.0 + self.leap_seconds
        if dow is not None and dow != 7 and self.time_ref.t_last is None:
            return self._resolve((dow * 86400.0 + tod_gps) % SECONDS_PER_WEEK)
        return self._resolve(tod_gps % 86400.0, 86400.0)

    def _legacy_glonass(self, msg) -> list[RtcmMessage]:
        t_gps = self._glonass_time(int(msg.DF034) * 1e-3, None)
        if t_gps is None:
            return []
        self._count(f"obs_{msg.identity}")
        obs = self._legacy_obs(msg, "R", int(msg.DF035), 2 * MS_TO_M,
                               ("DF038", "DF039", "DF041", "DF042", "DF043", "DF044", "DF045",
                                "DF046", "DF047", "DF048", "DF049", "DF050"),
                               ("L1C", "L1P"), ("L2C", "L2P", "L2P", "L2P"))
        return self._add_observations(t_gps, obs, bool(msg.DF005), "R")

    def _legacy_obs(self, msg, system: str, nsat: int, modulus_m: float, f: tuple,
                    codes1: tuple, codes2: tuple) -> list[SatObservation]:
        """1002/1004 (GPS) and 1010/1012 (GLONASS) satellite blocks."""
        (f_sat, f_code1, f_pr1, f_ppr1, f_lock1, f_amb, f_cnr1,
         f_code2, f_dpr2, f_ppr2, f_lock2, f_cnr2) = f
        obs: list[SatObservation] = []
        for k in range(1, nsat + 1):
            s = f"_{k:02d}"
            prn = int(getattr(msg, f_sat + s))
            glo_k = None
            if system == "G":
                sat = f"S{prn + 80 - 100:02d}" if prn >= 40 else f"G{prn:02d}"
            else:
                sat = f"R{prn:02d}"
                glo_k = int(msg.__dict__.get("DF040" + s, 0)) - 7
                self._glo_channel[prn] = glo_k
            pr1 = float(getattr(msg, f_pr1 + s)) + int(getattr(msg, f_amb + s)) * modulus_m
            sig1 = codes1[int(getattr(msg, f_code1 + s)) & 1]
            lam1 = wavelength_m(sat, sig1, glo_k)
            ppr1 = float(getattr(msg, f_ppr1 + s))
            cp1 = math.nan
            lock1 = lock_time_df013(int(getattr(msg, f_lock1 + s)))
            if abs(ppr1 + 262.144) > 1e-6 and math.isfinite(lam1):
                cp1 = pr1 / lam1 + self._adjust_cp((sat, sig1), ppr1 / lam1)
            cnr1 = float(getattr(msg, f_cnr1 + s))
            obs.append(SatObservation(
                sat=sat, pseudorange_m=pr1, carrier_cycles=cp1,
                cn0_dbhz=cnr1 if cnr1 > 0 else math.nan, lock_time_s=lock1,
                loss_of_lock=math.isfinite(cp1) and self._slip(sat, sig1, lock1),
                signal=sig1, wavelength_m=lam1))
            if not hasattr(msg, f_dpr2 + s):
                continue           # L1-only message (1002 / 1010)
            dpr2 = float(getattr(msg, f_dpr2 + s))
            ppr2 = float(getattr(msg, f_ppr2 + s))
            pr2_valid = abs(dpr2 + 163.84) > 1e-6
            cp2_valid = abs(ppr2 + 262.144) > 1e-6
            cnr2 = float(getattr(msg, f_cnr2 + s))
            if not (pr2_valid or cp2_valid) or (cnr2 == 0 and dpr2 == 0 and ppr2 == 0):
                continue           # no L2 for this satellite
            sig2 = codes2[int(getattr(msg, f_code2 + s)) & 3]
            lam2 = wavelength_m(sat, sig2, glo_k)
            cp2 = math.nan
            lock2 = lock_time_df013(int(getattr(msg, f_lock2 + s)))
            if cp2_valid and math.isfinite(lam2):
                cp2 = pr1 / lam2 + self._adjust_cp((sat, sig2), ppr2 / lam2)
            obs.append(SatObservation(
                sat=sat, pseudorange_m=pr1 + dpr2 if pr2_valid else math.nan, carrier_cycles=cp2,
                cn0_dbhz=cnr2 if cnr2 > 0 else math.nan, lock_time_s=lock2,
                loss_of_lock=math.isfinite(cp2) and self._slip(sat, sig2, lock2),
                signal=sig2, wavelength_m=lam2))
        return obs

    # -- MSM4..7 -----------------------------------------------------------------------------
    def _msm_time(self, msg, system: str) -> float | None:
        if system == "R":
            return self._glonass_time(int(msg.DF034) * 1e-3, int(msg.DF416))
        tow_s = int(getattr(msg, _MSM_TIME_FIELD[system])) * 1e-3
        if system == "C":
            tow_s = (tow_s + 14.0) % SECONDS_PER_WEEK
        return self._resolve(tow_s)

    def _msm(self, msg, system: str, msm: int) -> list[RtcmMessage]:
        t_gps = self._msm_time(msg, system)
        if t_gps is None:
            return []
        self._count(f"msm{msm}")
        nsat, ncell = int(msg.NSat), int(msg.NCell)
        sats = {}
        for i in range(1, nsat + 1):
            s = f"_{i:02d}"
            prn = int(getattr(msg, "PRN" + s))
            rough_ms = int(getattr(msg, "DF397" + s))
            rough = math.nan if rough_ms == 255 else rough_ms + float(getattr(msg, "DF398" + s))
            ext = getattr(msg, "DF419" + s, None)
            if ext is None:
                ext = getattr(msg, "ExtSatInfo" + s, None)
            rate = getattr(msg, "DF399" + s, None)
            rate = math.nan if rate is None or int(rate) == -8192 else float(rate)
            glo_k = None
            if system == "R":
                if ext is not None and int(ext) <= 13:
                    glo_k = int(ext) - 7
                    self._glo_channel[prn] = glo_k
                else:
                    glo_k = self._glo_channel.get(prn)
            sats[prn] = (rough, rate, glo_k)
        if msm in (4, 5):
            f_pr, f_ph, f_lock, f_cnr = "DF400", "DF401", "DF402", "DF403"
            lock_fn = lock_time_df402
        else:
            f_pr, f_ph, f_lock, f_cnr = "DF405", "DF406", "DF407", "DF408"
            lock_fn = lock_time_df407
        obs: list[SatObservation] = []
        for j in range(1, ncell + 1):
            s = f"_{j:02d}"
            prn = int(getattr(msg, "CELLPRN" + s))
            code = str(getattr(msg, "CELLSIG" + s))
            sat = _msm_sat_id(system, prn)
            if sat is None or prn not in sats or len(code) != 2:
                self._count("msm_unknown_signal")
                continue
            signal = "L" + code
            rough, rate, glo_k = sats[prn]
            lam = wavelength_m(sat, signal, glo_k)
            fine_pr = float(getattr(msg, f_pr + s))
            fine_ph = float(getattr(msg, f_ph + s))
            pr = math.nan
            if math.isfinite(rough) and abs(fine_pr - _INVALID_FINE_PR_MS) > 1e-12:
                pr = (rough + fine_pr) * MS_TO_M
            cp = math.nan
            if math.isfinite(rough) and abs(fine_ph - _INVALID_FINE_PH_MS) > 1e-12 and math.isfinite(lam):
                cp = (rough + fine_ph) * MS_TO_M / lam
            elif math.isfinite(rough) and not math.isfinite(lam):
                self._count("glonass_channel_unknown")
            lock_s = lock_fn(int(getattr(msg, f_lock + s)))
            dop = math.nan
            if msm in (5, 7) and math.isfinite(rate) and math.isfinite(lam):
                fine_rate = float(getattr(msg, "DF404" + s))
                if abs(fine_rate - _INVALID_FINE_RATE) > 1e-9:
                    dop = -(rate + fine_rate) / lam
            cnr = float(getattr(msg, f_cnr + s))
            obs.append(SatObservation(
                sat=sat, pseudorange_m=pr, carrier_cycles=cp, doppler_hz=dop,
                cn0_dbhz=cnr if cnr > 0 else math.nan, lock_time_s=lock_s,
                half_cycle_ambiguous=bool(int(getattr(msg, "DF420" + s))) and math.isfinite(cp),
                loss_of_lock=math.isfinite(cp) and self._slip(sat, signal, lock_s),
                signal=signal, wavelength_m=lam))
        return self._add_observations(t_gps, obs, bool(msg.DF393), system)

    # -- ephemerides -------------------------------------------------------------------------
    def _ephemeris(self, mtype: int, msg) -> list[RtcmMessage]:
        ref = self.time_ref.reference()
        if ref is None:
            self._reject("no_time_reference", "pass week_hint to RtcmDecoder")
            return []
        kind = "lnav"
        if mtype == 1019:
            eph = gps_ephemeris(msg, ref)
        elif mtype == 1044:
            eph = qzss_ephemeris(msg, ref)
        elif mtype == 1042:
            eph = beidou_ephemeris(msg, ref)
        else:
            eph, kind = galileo_ephemeris(msg, ref)
        key = (eph.iode, eph.week, eph.toe_s)
        if self._eph_last.get((eph.sat, kind)) == key:
            self._count("ephemeris_repeat")
            return []
        self._eph_last[(eph.sat, kind)] = key
        if kind in self._gal_seen:
            return self._galileo(eph, kind)
        self._count("ephemerides")
        return [eph]

    def _galileo(self, eph: GpsEphemeris, kind: str) -> list[RtcmMessage]:
        """Galileo I/NAV and F/NAV carry the same orbit with different clocks: one of them feeds
        the ephemeris store (``galileo_nav``); the other only where the preferred never came."""
        self._gal_seen[kind].add(eph.sat)
        if self.galileo_nav == "both" or kind == self.galileo_nav:
            held = self._gal_held.pop(eph.sat, None)
            if held is not None and held.iode == eph.iode:
                self._count("ephemeris_galileo_superseded")
            elif held is not None:
                self._count("ephemerides", 2)
                return [held, eph]
            self._count("ephemerides")
            return [eph]
        if eph.sat in self._gal_seen[self.galileo_nav]:
            self._count("ephemeris_galileo_other_nav")
            return []
        self._gal_held[eph.sat] = eph                  # until the next observation message
        return []

    def _release_held(self) -> list[RtcmMessage]:
        if not self._gal_held:
            return []
        out = list(self._gal_held.values())
        self._gal_held.clear()
        self._count("ephemerides", len(out))
        return out


_EPHEMERIS_TYPES = (1019, 1042, 1044, 1045, 1046)


def _is_observation(mtype: int) -> bool:
    family, sub = divmod(mtype, 10)
    return (family in _MSM_SYSTEMS and 1 <= sub <= 7) or 1001 <= mtype <= 1004 or 1009 <= mtype <= 1012


def decode_rtcm_file(path: str, week_hint: WeekHint = None, chunk_size: int = 4096,
                     leap_seconds: int = DEFAULT_LEAP_SECONDS) -> tuple[list[RtcmMessage], RtcmDecoder]:
    """Convenience: decode a whole RTCM 3 file (in chunks, like a live stream)."""
    dec = RtcmDecoder(week_hint=week_hint, leap_seconds=leap_seconds)
    out: list[RtcmMessage] = []
    with open(path, "rb") as f:
        while chunk := f.read(chunk_size):
            out.extend(dec.feed(chunk))
    out.extend(dec.flush())
    return out, dec


__all__ = ["MAX_FRAME", "known_message_number", "RtcmFramer", "RtcmDecoder", "GlonassEphemeris", "GpsRtcmDataFragmenter", "rtcm_to_gps_rtcm_data_fragments",
           "crc24q", "frame_message_type", "decode_rtcm_file", "lock_time_df013", "lock_time_df402",
           "lock_time_df407"]
