"""MAVLink edge of the shell: decode autopilot inputs, encode fused outputs, run the link.

Three layers, from pure to I/O:

(a) **Pure decoders** (no clock, no socket):

* :class:`BootToGpsTime` maps autopilot boot time (``time_boot_ms``/``time_usec`` of its messages)
  to GPS time.  Fed by SYSTEM_TIME (``time_unix_usec`` is UTC; GPS = UTC + leap seconds, 18 s since
  2017-01-01, :data:`DEFAULT_LEAP_SECONDS`), smoothed, with jump and reboot detection; refinable by
  receiver time tags (:meth:`BootToGpsTime.refine`).
* :class:`ImuDecoder` / :func:`imu_from_mavlink`: HIGHRES_IMU (SI: m/s^2, rad/s, ``time_usec`` =
  boot time), RAW_IMU and SCALED_IMU2/3 (ArduPilot: acceleration in mG = 1e-3 * 9.80665 m/s^2,
  rates in mrad/s; checked in ArduPilot ``GCS_MAVLINK::send_raw_imu``: ``accel * 1000 /
  GRAVITY_MSS``, ``gyro * 1000``, time ``AP_HAL::micros64()``), body axes FRD.  The interval
  ``dt`` is the difference of consecutive sample times; non-monotonic samples are rejected and
  gaps counted.  Increments are rate x dt (the sample is the rate at the end of the interval).
  Caveat: MAVLink IMU messages are *instantaneous samples* decimated to the stream rate, not
  integrated increments; vibration above half the stream rate aliases.  RAW_IMU/SCALED_IMU carry
  int16 mG / mrad/s (quantisation 9.8 mm/s^2 and 0.057 deg/s): use HIGHRES_IMU where available.
* :func:`gps_fix_from_gps_raw_int`: GPS_RAW_INT -> :class:`~companion.messages.GnssFix`.

(b) **Pure encoders** returning pymavlink message objects (``msg.pack(mav)`` gives bytes; the
link does that): :func:`vision_position_estimate`, :func:`odometry`, :func:`gps_input`,
:func:`set_gps_global_origin`, :func:`statustext`, :func:`gps_rtcm_data_messages`,
:func:`command_set_message_interval`, :func:`heartbeat`, :func:`serial_control_request`.

(c) **I/O**: :class:`MavlinkLink` (asyncio) and :class:`SerialControlTunnel`.

Design of the link (asyncio, no reader thread): pymavlink opens every supported transport
non-blocking (UDP/TCP sockets ``setblocking(False)``, serial ``timeout=0``), so the link registers
the connection's file descriptor with ``loop.add_reader`` and drains ``recv_msg()`` until it returns
``None`` whenever the fd is readable (a transport without an fd is polled every 10 ms).  The
periodic work (heartbeat, TIMESYNC, link timeout, interval retries) is one loop timer armed for
its next deadline, at least every 0.25 s -- no task waking every 10 ms.  All state lives on the event loop thread: no locks, sends are ordinary calls.  A reader
thread would only add a queue hop and locking around pymavlink's shared parser state.  On UDP
without signing the link reads datagrams itself and decodes their high-rate frames with
:mod:`companion.io.mavlink_fast` (same messages as pymavlink's, which parses everything else);
:meth:`MavlinkLink.deliver_to` hands messages to a synchronous consumer instead of the queue.

Frames: positions sent to the autopilot are NED relative to the EKF origin **as ArduPilot computes
them** (``Location::get_distance_NED``: spherical scaling ``LOCATION_SCALING_FACTOR`` =
0.011131884502145034 m per 1e-7 deg and ``cos(mean latitude)`` for east), so the global position
the autopilot reports from the fused NED state matches ours (a WGS-84 tangent plane differs by
~0.2 % of the distance from the origin).
"""
from __future__ import annotations

import asyncio
import calendar
import logging
import math
import os
import socket
import time
from collections import deque
from dataclasses import dataclass
from typing import AsyncIterator, Callable

import numpy as np

os.environ.setdefault("MAVLINK20", "1")        # ODOMETRY (331) and GPS_INPUT need MAVLink 2
from pymavlink import mavutil  # noqa: E402
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from ..messages import SECONDS_PER_WEEK, GnssFix, ImuSample, NavSolution, gps_week_tow  # noqa: E402
from ..nav.earth import C_n_e, dcm_to_euler, ecef_to_geodetic, geodetic_to_ecef  # noqa: E402
from .imu_streams import IMU_CLUSTER_STREAMS, IMU_MESSAGES  # noqa: E402  (names shared with the config)
from .rtcm import GPS_RTCM_DATA_LEN, GpsRtcmDataFragmenter  # noqa: E402

log = logging.getLogger(__name__)

GPS_EPOCH_UNIX_S = calendar.timegm((1980, 1, 6, 0, 0, 0))
DEFAULT_LEAP_SECONDS = 18          # GPS - UTC since 2017-01-01 (IERS bulletin C); none announced since
STANDARD_GRAVITY_MPS2 = 9.80665    # ArduPilot GRAVITY_MSS, the mG scaling of RAW_IMU / SCALED_IMU
LOCATION_SCALING_FACTOR_M = 0.011131884502145034   # ArduPilot: metres per 1e-7 degree of latitude
UNIX_TIME_THRESHOLD_US = 1_000_000_000_000_000    # time_usec above this (2001-09) is UNIX time, not boot time

m = mavlink2
MAV_COMP_ID_ONBOARD_COMPUTER = m.MAV_COMP_ID_ONBOARD_COMPUTER      # 191
SERIAL_CONTROL_DEV_GPS1 = m.SERIAL_CONTROL_DEV_GPS1
SERIAL_CONTROL_DEV_GPS2 = m.SERIAL_CONTROL_DEV_GPS2
SERIAL_CONTROL_DATA_LEN = 70

# 'auto' requests HIGHRES_IMU alone (SI floats) and RAW_IMU (int16 mG, mrad/s) only if the autopilot
# refuses HIGHRES_IMU or it does not arrive: one IMU stream on the link, never two at 200 Hz
IMU_AUTO_FALLBACK = {"HIGHRES_IMU": "RAW_IMU"}
STREAM_FALLBACK_AFTER_S = 3.0
TIMER_SAFETY_NET_S = 0.25      # the link's periodic work runs at least this often (see _arm)
POLL_NO_FD_S = 0.01            # a transport without a file descriptor is polled this often
MIN_RX_PAUSE_S = 0.002         # a shorter sleep saves no wake-up (rx_pause)
# a read that brought more than this many messages (or bad frames) is not followed by a sleep: a 40-ms one
# brings ~10 at 200 Hz; a burst (a parameter download) or a flood would overflow the socket's
# buffer (~200 small datagrams in Linux's default 208 KB) or a serial port's (4 KB) meanwhile
RX_BUSY_MESSAGES = 48
UDP_RX_BUFFER_BYTES = 1 << 20  # asked for the UDP socket (Linux's default 208 KB: ~200 small datagrams)
HOOK_EARLY_S = 0.002           # a hook due as the paused reader wakes runs this much before (_arm_paused_hooks)
HOOK_WINDOW_S = 0.008          # ... when due within this after the wake (the wait for the slot's sample)
TIMESYNC_REPLY_WAIT_S = 0.1    # the reader does not pause this long after our TIMESYNC request (rx_pause)
DEADLINE_SLACK_S = 0.002       # a timeout checked just after it expires, not just before


def parse_imu_stream(name: str) -> tuple[str, int | None]:
    """'SCALED_IMU2' -> ('SCALED_IMU2', None); 'HIGHRES_IMU:1' -> ('HIGHRES_IMU', 1) (its ``id`` field)."""
    if name not in IMU_CLUSTER_STREAMS:
        raise ValueError(f"unknown IMU stream {name!r} (one of {', '.join(IMU_CLUSTER_STREAMS)})")
    msg, _, unit = name.partition(":")
    return msg, (int(unit) if unit else None)


def _encoder(src_system: int = 1, src_component: int = MAV_COMP_ID_ONBOARD_COMPUTER):
    return mavlink2.MAVLink(None, srcSystem=src_system, srcComponent=src_component)


_ENC = _encoder()


def pack(msg, src_system: int = 1, src_component: int = MAV_COMP_ID_ONBOARD_COMPUTER, seq: int = 0) -> bytes:
    """Serialise a message object to MAVLink 2 bytes (deterministic: explicit ids and sequence)."""
    mav = _encoder(src_system, src_component)
    mav.seq = seq & 0xFF
    return bytes(msg.pack(mav))


def parse_bytes(data: bytes) -> list:
    """Parse MAVLink bytes back into message objects (bad data is returned as BAD_DATA messages)."""
    mav = mavlink2.MAVLink(None)
    mav.robust_parsing = True
    return mav.parse_buffer(bytes(data)) or []


# =============================================================================================
# (a) time mapping
def unix_to_gps_s(t_unix_s: float, leap_seconds: int = DEFAULT_LEAP_SECONDS) -> float:
    return t_unix_s - GPS_EPOCH_UNIX_S + leap_seconds


def gps_to_unix_s(t_gps: float, leap_seconds: int = DEFAULT_LEAP_SECONDS) -> float:
    return t_gps + GPS_EPOCH_UNIX_S - leap_seconds


class BootToGpsTime:
    """Maps autopilot boot time (s) to GPS time (s): ``t_gps = t_boot + offset``.

    * :meth:`update_system_time` (SYSTEM_TIME): each message gives an offset sample
      ``UTC + leap - boot``, quantised to 1 ms by ``time_boot_ms``.  Samples are averaged
      (exponential, ``smoothing`` weight per new sample).  A sample more than ``jump_threshold_s``
      away from the current offset is a *jump* candidate (the autopilot's RTC was set or stepped);
      it is accepted -- re-seeding the offset -- when the next sample confirms it, and counted.
      ``time_unix_usec == 0`` (autopilot without UTC yet) is counted and ignored.
    * A boot time that goes backwards (by more than ``reboot_tolerance_s``) means the autopilot
      rebooted: the mapping is reset, ``reboots`` counted and ``boot_epoch`` incremented (users
      such as :class:`ImuDecoder` reset their own state when it changes).
    * :meth:`refine` takes a receiver time tag (GPS time of an event whose boot time is known):
      it has priority over SYSTEM_TIME for ``refine_hold_s``, during which SYSTEM_TIME only checks
      for jumps.  The pipeline has no such pair and does not call it: GPS_RAW_INT ``time_usec`` is
      when the autopilot *received* the fix (no GPS time in the message), SERIAL_CONTROL bytes carry
      no boot time, and a raw epoch matched to either is late by the receiver's output latency --
      the very lag that makes SYSTEM_TIME late.  An honest pair needs an event the autopilot stamps
      and the receiver times (e.g. a trigger pin into UBX TIM-TM2).  What SYSTEM_TIME leaves is
      estimated by the filter instead (``dt_imu``, :mod:`companion.nav.filter`).
    * The offset may drift: :attr:`rate` (s/s) is the least-squares slope of the last
      ``rate_window`` SYSTEM_TIME offsets and the offset is extrapolated with it.  A real
      autopilot's clock is off by some ppm; PX4 SITL's lockstep boot clock runs ~1 % slower than
      UTC, which an offset average alone follows 0.1 s behind, i.e. with a 'jump' every few seconds.
    """

    def __init__(self, leap_seconds: int = DEFAULT_LEAP_SECONDS, smoothing: float = 0.1,
                 jump_threshold_s: float = 0.05, reboot_tolerance_s: float = 1.0,
                 refine_hold_s: float = 10.0, rate_window: int = 30, max_rate: float = 0.05):
        self.leap_seconds = int(leap_seconds)
        self.max_rate = float(max_rate)
        self._rate_window: deque = deque(maxlen=rate_window)    # (t_boot, offset - base) of SYSTEM_TIME
        self._rate_base = 0.0
        self.rate = 0.0                     # d(offset)/d(boot time)
        self._ref_boot_s = 0.0              # boot time at which offset_s holds
        self.smoothing = float(smoothing)
        self.jump_threshold_s = float(jump_threshold_s)
        self.reboot_tolerance_s = float(reboot_tolerance_s)
        self.refine_hold_s = float(refine_hold_s)
        self.offset_s: float | None = None
        self.boot_epoch = 0
        self.last_boot_s: float | None = None
        self._candidate: float | None = None
        self._candidate_boot_s = 0.0
        self._refined_at_boot_s: float | None = None
        self.counters: dict[str, int] = {"system_time": 0, "no_utc": 0, "jumps": 0, "reboots": 0,
                                         "jump_candidates": 0, "refines": 0}

    @property
    def synced(self) -> bool:
        return self.offset_s is not None

    @property
    def reboots(self) -> int:
        return self.counters["reboots"]

    @property
    def jumps(self) -> int:
        return self.counters["jumps"]

    def observe_boot_time(self, t_boot_s: float) -> bool:
        """Note any boot time seen on the link; returns True when it reveals a reboot."""
        last = self.last_boot_s
        if last is not None and t_boot_s < last - self.reboot_tolerance_s:
            self.counters["reboots"] += 1
            self.boot_epoch += 1
            log.warning("autopilot reboot detected (boot time %.3f s after %.3f s)", t_boot_s, last)
            self.offset_s = None
            self.rate = 0.0
            self._candidate = None
            self._refined_at_boot_s = None
            self.last_boot_s = t_boot_s
            return True
        if last is None or t_boot_s > last:
            self.last_boot_s = t_boot_s
        return False

    def update_system_time(self, time_unix_usec: int, time_boot_ms: int) -> None:
        t_boot = time_boot_ms * 1e-3
        self.observe_boot_time(t_boot)
        if time_unix_usec == 0:
            self.counters["no_utc"] += 1
            return
        self.counters["system_time"] += 1
        sample = unix_to_gps_s(time_unix_usec * 1e-6, self.leap_seconds) - t_boot
        self._offset_sample(sample, t_boot, weight=self.smoothing, from_refine=False)

    def update_from_message(self, msg) -> None:
        """Convenience: feed SYSTEM_TIME messages; other messages with time_boot_ms update the
        reboot detector."""
        if msg.get_type() == "SYSTEM_TIME":
            self.update_system_time(int(msg.time_unix_usec), int(msg.time_boot_ms))
        elif hasattr(msg, "time_boot_ms"):
            self.observe_boot_time(int(msg.time_boot_ms) * 1e-3)

    def refine(self, t_boot_s: float, t_gps: float, weight: float = 0.5) -> None:
        """A receiver time tag: the event at boot time ``t_boot_s`` happened at GPS time ``t_gps``."""
        self.observe_boot_time(t_boot_s)
        self.counters["refines"] += 1
        self._offset_sample(t_gps - t_boot_s, t_boot_s, weight=weight, from_refine=True)
        self._refined_at_boot_s = t_boot_s

    def _offset_at(self, t_boot_s: float) -> float:
        return self.offset_s + self.rate * (t_boot_s - self._ref_boot_s)

    def _offset_sample(self, sample: float, t_boot: float, weight: float, from_refine: bool) -> None:
        if self.offset_s is None:
            self.offset_s, self._ref_boot_s = sample, t_boot
            self._candidate = None
            self._rate_window.clear()
            self._rate_base = sample        # the window holds small numbers: no cancellation
            return
        predicted = self._offset_at(t_boot)
        d = sample - predicted
        if abs(d) > self.jump_threshold_s:
            c = self._candidate
            if c is not None and abs(sample - (c + self.rate * (t_boot - self._candidate_boot_s))) \
                    <= self.jump_threshold_s:
                self.counters["jumps"] += 1
                log.warning("autopilot time mapping jumped by %+.3f s", d)
                self.offset_s, self._ref_boot_s = sample, t_boot
                self._candidate = None
                self._rate_window.clear()
                self._rate_base = sample
            else:
                self.counters["jump_candidates"] += 1
                self._candidate, self._candidate_boot_s = sample, t_boot
            return
        self._candidate = None
        held = (not from_refine and self._refined_at_boot_s is not None
                and t_boot - self._refined_at_boot_s < self.refine_hold_s)
        if held:
            return
        if not from_refine:
            self._rate_from(t_boot, sample)
            predicted = self._offset_at(t_boot)
            d = sample - predicted
        self.offset_s, self._ref_boot_s = predicted + weight * d, t_boot

    def _rate_from(self, t_boot: float, sample: float) -> None:
        """Least-squares slope of the last SYSTEM_TIME offsets (>= 3 over >= 2 s; soon enough that
        a 1 % drift does not reach the jump threshold first)."""
        w = self._rate_window
        w.append((t_boot, sample - self._rate_base))
        if len(w) < 3 or w[-1][0] - w[0][0] < 2.0:
            return
        n = len(w)
        mt = sum(t for t, _ in w) / n
        mo = sum(o for _, o in w) / n
        stt = sum((t - mt) ** 2 for t, _ in w)
        slope = sum((t - mt) * (o - mo) for t, o in w) / stt
        self.rate = min(max(slope, -self.max_rate), self.max_rate)

    def to_gps(self, t_boot_s: float) -> float | None:
        return None if self.offset_s is None else t_boot_s + self._offset_at(t_boot_s)

    def to_boot(self, t_gps: float) -> float | None:
        if self.offset_s is None:
            return None
        # t_gps = t_boot (1 + rate) + offset_s - rate * ref
        return (t_gps - self.offset_s + self.rate * self._ref_boot_s) / (1.0 + self.rate)


# =============================================================================================
# (a) IMU decoding
def imu_rates_from_mavlink(msg) -> tuple[int, np.ndarray, np.ndarray, int] | None:
    """Pure: ``(time_us, gyro_radps (3,), accel_mps2 (3,), imu_id)`` from an IMU message, else None.

    ``time_us`` is boot time in microseconds, or UNIX time if the sender used it (> 2001 in us).
    """
    t = msg.get_type()
    if t == "HIGHRES_IMU":
        upd = int(getattr(msg, "fields_updated", 0))
        if upd and (upd & 0x3F) != 0x3F:
            return None                     # accel or gyro not updated in this sample
        gyro = np.array([msg.xgyro, msg.ygyro, msg.zgyro], float)
        acc = np.array([msg.xacc, msg.yacc, msg.zacc], float)
        return int(msg.time_usec), gyro, acc, int(getattr(msg, "id", 0))
    if t == "RAW_IMU":
        gyro = np.array([msg.xgyro, msg.ygyro, msg.zgyro], float) * 1e-3
        acc = np.array([msg.xacc, msg.yacc, msg.zacc], float) * (1e-3 * STANDARD_GRAVITY_MPS2)
        return int(msg.time_usec), gyro, acc, int(getattr(msg, "id", 0))
    if t in ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"):
        gyro = np.array([msg.xgyro, msg.ygyro, msg.zgyro], float) * 1e-3
        acc = np.array([msg.xacc, msg.yacc, msg.zacc], float) * (1e-3 * STANDARD_GRAVITY_MPS2)
        imu_id = {"SCALED_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}[t]
        return int(msg.time_boot_ms) * 1000, gyro, acc, imu_id
    return None


class ImuDecoder:
    """Stateful IMU decoder: consecutive samples of one IMU stream -> :class:`ImuSample`.

    ``message``: 'auto' locks onto the first IMU message type seen (HIGHRES_IMU, RAW_IMU,
    SCALED_IMU2, SCALED_IMU3); others are then ignored (counted ``other_imu``).  ``dt`` comes from
    consecutive time stamps: a sample not later than the previous one is rejected
    (``non_monotonic``); an interval longer than ``gap_factor`` nominal periods is counted as a
    ``gap`` and, if longer than ``max_dt_s``, the sample only restarts the chain (``gap_reset``)
    because a rate times a long interval is not an increment.  The nominal period starts at
    ``1 / rate_hz`` and follows the intervals actually delivered (exponential average).
    """

    def __init__(self, message: str = "auto", rate_hz: float = 200.0, gap_factor: float = 2.5,
                 max_dt_s: float = 0.1, leap_seconds: int = DEFAULT_LEAP_SECONDS, imu_id: int | None = None):
        if message != "auto" and message not in IMU_MESSAGES + ("SCALED_IMU",):
            raise ValueError(f"unknown IMU message {message!r}")
        self.auto = message == "auto"
        self.message = None if self.auto else message
        self.imu_id = imu_id                # HIGHRES_IMU/RAW_IMU 'id' to accept (None = any)
        self.nominal_dt_s = 1.0 / rate_hz
        self.gap_factor = gap_factor
        self.max_dt_s = max_dt_s
        self.leap_seconds = leap_seconds
        self._last_us: int | None = None
        self._epoch = None
        self.counters: dict[str, int] = {"samples": 0, "non_monotonic": 0, "gaps": 0, "gap_reset": 0,
                                         "no_time": 0, "other_imu": 0, "first": 0, "reboot_reset": 0}

    def decode(self, msg, time_map: BootToGpsTime) -> ImuSample | None:
        t = msg.get_type()
        if t not in IMU_MESSAGES and t != self.message:
            return None
        if self.imu_id is not None and int(getattr(msg, "id", 0)) != self.imu_id:
            self.counters["other_imu"] += 1
            return None
        if self.message is None or (self.auto and t == "HIGHRES_IMU" and self.message != t):
            if self.message is not None:
                self.counters["switched_to_highres"] = self.counters.get("switched_to_highres", 0) + 1
                self._last_us = None
            self.message = t
            log.info("IMU source: %s", t)
        elif t != self.message:
            self.counters["other_imu"] += 1
            return None
        r = imu_rates_from_mavlink(msg)
        if r is None:
            return None
        t_us, gyro, acc, imu_id = r
        unix = t_us >= UNIX_TIME_THRESHOLD_US
        if not unix:
            time_map.observe_boot_time(t_us * 1e-6)
        if self._epoch != time_map.boot_epoch:
            if self._epoch is not None:
                self.counters["reboot_reset"] += 1
            self._epoch = time_map.boot_epoch
            self._last_us = None
        last, self._last_us = self._last_us, t_us
        if last is None:
            self.counters["first"] += 1
            return None
        if t_us <= last:
            self.counters["non_monotonic"] += 1
            self._last_us = last
            return None
        dt = (t_us - last) * 1e-6
        if dt > self.gap_factor * self.nominal_dt_s:
            self.counters["gaps"] += 1
            if dt > self.max_dt_s:
                self.counters["gap_reset"] += 1
                return None
        # the interval actually delivered (the autopilot may stream slower than requested): a slow
        # average, so a stream at a quarter of the requested rate is not one long series of 'gaps'
        self.nominal_dt_s += 0.05 * (dt - self.nominal_dt_s)
        if unix:
            t_gps = unix_to_gps_s(t_us * 1e-6, self.leap_seconds)
        else:
            t_gps = time_map.to_gps(t_us * 1e-6)
            if t_gps is None:
                self.counters["no_time"] += 1
                return None
        self.counters["samples"] += 1
        return ImuSample(t_gps=t_gps, dt_s=dt, dtheta_b=gyro * dt, dv_b=acc * dt, imu_id=imu_id)


def imu_from_mavlink(msg, time_map: BootToGpsTime, decoder: ImuDecoder) -> ImuSample | None:
    """Decode one IMU message with ``decoder`` (which holds the previous time stamp)."""
    return decoder.decode(msg, time_map)


# =============================================================================================
# (a) GPS_RAW_INT
def gps_fix_from_gps_raw_int(msg, time_map: BootToGpsTime, *, uere_m: float = 3.0,
                             default_sigma_vel_mps: float = 0.5,
                             latency_s: float = 0.0, epoch_period_s: float = 0.0,
                             leap_seconds: int = DEFAULT_LEAP_SECONDS) -> GnssFix | None:
    """GPS_RAW_INT -> :class:`GnssFix` (antenna position, ECEF).  None without fix or time.

    * ``time_usec``: ArduPilot sends ``last_fix_time_ms * 1000`` (boot time at which its driver
      got the fix, i.e. the epoch plus the receiver's output latency); UNIX time is also accepted.
      ``latency_s`` is subtracted and, with ``epoch_period_s`` > 0, the result is snapped to the
      nearest multiple of the receiver's epoch period (receivers measure on whole GPS seconds).
    * Height: ``alt_ellipsoid`` (mm) when non-zero, else ``alt`` (MSL) is used as if it were
      ellipsoidal.  **Caveat**: that is wrong by the geoid undulation (-107..+85 m worldwide); in
      loose coupling the filter then sits at the wrong height, consistently.
    * Accuracy: ``h_acc``/``v_acc`` (mm) when non-zero; else ``eph``/``epv`` (DOP x 100) times
      ``uere_m``; ``vel_acc`` (mm/s) for the velocity.
    * Velocity: horizontal from ``vel`` (cm/s) and ``cog`` (cdeg); vertical unknown (0 with the
      horizontal sigma doubled... not used: ``v_e`` is None when vel or cog is unknown).
    """
    fix_type = int(msg.fix_type)
    if fix_type < 2:
        return None
    t_us = int(msg.time_usec)
    if t_us >= UNIX_TIME_THRESHOLD_US:
        t_gps = unix_to_gps_s(t_us * 1e-6, leap_seconds)
    else:
        t_gps = time_map.to_gps(t_us * 1e-6)
        if t_gps is None:
            return None
    t_gps -= latency_s
    if epoch_period_s > 0:
        t_gps = round(t_gps / epoch_period_s) * epoch_period_s
    lat = math.radians(msg.lat * 1e-7)
    lon = math.radians(msg.lon * 1e-7)
    alt_ell = int(getattr(msg, "alt_ellipsoid", 0) or 0)
    h = alt_ell * 1e-3 if alt_ell != 0 else msg.alt * 1e-3
    r_e = geodetic_to_ecef(lat, lon, h)
    h_acc = int(getattr(msg, "h_acc", 0) or 0)
    v_acc = int(getattr(msg, "v_acc", 0) or 0)
    sigma_h = h_acc * 1e-3 if h_acc > 0 else (msg.eph * 1e-2 * uere_m if msg.eph not in (0, 65535) else 10.0 * uere_m)
    sigma_v = v_acc * 1e-3 if v_acc > 0 else (msg.epv * 1e-2 * uere_m if msg.epv not in (0, 65535) else 2 * sigma_h)
    vel_acc = int(getattr(msg, "vel_acc", 0) or 0)
    sigma_vel = vel_acc * 1e-3 if vel_acc > 0 else default_sigma_vel_mps
    v_e = None
    if msg.vel != 65535 and msg.cog != 65535:
        speed = msg.vel * 1e-2
        cog = math.radians(msg.cog * 1e-2)
        v_n = np.array([speed * math.cos(cog), speed * math.sin(cog), 0.0])
        v_e = C_n_e(lat, lon) @ v_n
    nsat = int(msg.satellites_visible)
    return GnssFix(t_gps=t_gps, r_e=r_e, v_e=v_e, sigma_h_m=sigma_h, sigma_v_m=sigma_v,
                   sigma_vel_mps=sigma_vel, num_sats=0 if nsat == 255 else nsat, fix_type=fix_type,
                   autopilot_clock=True)


# =============================================================================================
# (b) encoders: geometry helpers
@dataclass(frozen=True, slots=True)
class Origin:
    """The EKF origin: geodetic (rad, rad, m) in the height reference sent to the autopilot."""
    lat_rad: float
    lon_rad: float
    alt_m: float

    @classmethod
    def from_ecef(cls, r_e, geoid_undulation_m: float = 0.0) -> "Origin":
        lat, lon, h = ecef_to_geodetic(r_e)
        return cls(lat, lon, h - geoid_undulation_m)

    def lat_e7(self) -> int:
        return int(round(math.degrees(self.lat_rad) * 1e7))

    def lon_e7(self) -> int:
        return int(round(math.degrees(self.lon_rad) * 1e7))


def ardupilot_ned_from_origin(lat_rad: float, lon_rad: float, alt_m: float, origin: Origin) -> np.ndarray:
    """NED offset of a point from ``origin`` exactly as ArduPilot's ``Location::get_distance_NED``
    computes it (spherical scaling, east scaled by cos of the mean latitude)."""
    dlat_e7 = (math.degrees(lat_rad) - math.degrees(origin.lat_rad)) * 1e7
    dlon_deg = math.degrees(lon_rad) - math.degrees(origin.lon_rad)
    dlon_deg = (dlon_deg + 180.0) % 360.0 - 180.0
    scale = max(math.cos(0.5 * (lat_rad + origin.lat_rad)), 0.01)
    return np.array([dlat_e7 * LOCATION_SCALING_FACTOR_M,
                     dlon_deg * 1e7 * LOCATION_SCALING_FACTOR_M * scale,
                     -(alt_m - origin.alt_m)])


def _solution_geodetic(sol: NavSolution, geoid_undulation_m: float) -> tuple[float, float, float, np.ndarray]:
    lat, lon, h = ecef_to_geodetic(sol.r_e)
    return lat, lon, h - geoid_undulation_m, C_n_e(lat, lon)


def _C_b_n(sol: NavSolution, Cne: np.ndarray) -> np.ndarray:
    return Cne.T @ np.asarray(sol.C_b_e, float)


def _att_var_rpy(sol: NavSolution, Cne: np.ndarray) -> tuple[float, float, float]:
    """Roll/pitch/yaw variances from the ECEF-axis attitude sigmas: rotated to NED, tilt about
    N and E shared by roll and pitch, rotation about D = yaw (small-angle approximation)."""
    s = np.asarray(sol.sigma_att_rad, float)
    P_n = Cne.T @ np.diag(s ** 2) @ Cne
    tilt = 0.5 * (P_n[0, 0] + P_n[1, 1])
    return tilt, tilt, P_n[2, 2]


def upper_triangle_covariance(diag: list[float] | np.ndarray) -> list[float]:
    """21-float row-major upper triangle of a 6x6 diagonal covariance (MAVLink convention)."""
    d = list(map(float, diag))
    out = []
    for i in range(6):
        for j in range(i, 6):
            out.append(d[i] if i == j else 0.0)
    return out


def quality_from_sigma(sigma_h_m: float, max_sigma_h_m: float) -> int:
    """ODOMETRY quality 1..100 (0 = unknown is reserved, -1 = failed) from the horizontal sigma."""
    if not math.isfinite(sigma_h_m) or sigma_h_m > max_sigma_h_m:
        return -1
    return max(1, min(100, int(round(100.0 * (1.0 - sigma_h_m / max_sigma_h_m)))))


def _rot_to_quat(C: np.ndarray) -> list[float]:
    """Rotation matrix -> quaternion [w, x, y, z] (Shepperd)."""
    tr = C[0, 0] + C[1, 1] + C[2, 2]
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        w, x, y, z = 0.25 * s, (C[2, 1] - C[1, 2]) / s, (C[0, 2] - C[2, 0]) / s, (C[1, 0] - C[0, 1]) / s
    elif C[0, 0] > C[1, 1] and C[0, 0] > C[2, 2]:
        s = math.sqrt(1.0 + C[0, 0] - C[1, 1] - C[2, 2]) * 2
        w, x, y, z = (C[2, 1] - C[1, 2]) / s, 0.25 * s, (C[0, 1] + C[1, 0]) / s, (C[0, 2] + C[2, 0]) / s
    elif C[1, 1] > C[2, 2]:
        s = math.sqrt(1.0 + C[1, 1] - C[0, 0] - C[2, 2]) * 2
        w, x, y, z = (C[0, 2] - C[2, 0]) / s, (C[0, 1] + C[1, 0]) / s, 0.25 * s, (C[1, 2] + C[2, 1]) / s
    else:
        s = math.sqrt(1.0 + C[2, 2] - C[0, 0] - C[1, 1]) * 2
        w, x, y, z = (C[1, 0] - C[0, 1]) / s, (C[0, 2] + C[2, 0]) / s, (C[1, 2] + C[2, 1]) / s, 0.25 * s
    q = np.array([w, x, y, z])
    q /= np.linalg.norm(q)
    if q[0] < 0:
        q = -q
    return q.tolist()


# (b) encoders: outputs
def vision_position_estimate(sol: NavSolution, origin: Origin, reset_counter: int, t_boot_us: int,
                             geoid_undulation_m: float = 0.0):
    """VISION_POSITION_ESTIMATE: NED position of the IMU relative to the EKF origin (ArduPilot's
    spherical convention, :func:`ardupilot_ned_from_origin`), roll/pitch/yaw of ``C_b_n``, and the
    21-float covariance (x, y, z, roll, pitch, yaw variances on the diagonal).  ArduPilot reduces
    the covariance to ``posErr``/``angErr`` from the diagonal entries 0, 6, 11 and 15, 18, 20.
    ``t_boot_us`` is the time stamp (ArduPilot corrects any offboard time base for jitter)."""
    lat, lon, alt, Cne = _solution_geodetic(sol, geoid_undulation_m)
    ned = ardupilot_ned_from_origin(lat, lon, alt, origin)
    roll, pitch, yaw = dcm_to_euler(_C_b_n(sol, Cne))
    vr, vp, vy = _att_var_rpy(sol, Cne)
    s = np.asarray(sol.sigma_r_n_m, float) ** 2
    cov = upper_triangle_covariance([s[0], s[1], s[2], vr, vp, vy])
    return _ENC.vision_position_estimate_encode(int(t_boot_us), float(ned[0]), float(ned[1]), float(ned[2]),
                                                roll, pitch, yaw, cov, int(reset_counter) & 0xFF)


def odometry(sol: NavSolution, origin: Origin, reset_counter: int, t_boot_us: int, *,
             quality: int = 0, geoid_undulation_m: float = 0.0):
    """ODOMETRY for ArduPilot's ``GCS_MAVLINK::handle_odometry``, which ignores anything but
    ``frame_id = MAV_FRAME_LOCAL_FRD`` (20) and ``child_frame_id = MAV_FRAME_BODY_FRD`` (12);
    velocity in the *body* frame (ArduPilot rotates it to NED with ``q``), ``q`` = body-to-NED
    [w, x, y, z], angular rates NaN (unknown), ``estimator_type = MAV_ESTIMATOR_TYPE_VISION``,
    ``quality`` 0..100 (``VISO_QUAL_MIN`` drops low ones; see :func:`quality_from_sigma`)."""
    lat, lon, alt, Cne = _solution_geodetic(sol, geoid_undulation_m)
    ned = ardupilot_ned_from_origin(lat, lon, alt, origin)
    Cbn = _C_b_n(sol, Cne)
    v_n = Cne.T @ np.asarray(sol.v_e, float)
    v_b = Cbn.T @ v_n
    vr, vp, vy = _att_var_rpy(sol, Cne)
    s = np.asarray(sol.sigma_r_n_m, float) ** 2
    sv = np.asarray(sol.sigma_v_n_mps, float) ** 2
    pose_cov = upper_triangle_covariance([s[0], s[1], s[2], vr, vp, vy])
    # body-frame velocity variance: isotropic bound (the NED sigmas rotated would need the full matrix)
    vmax = float(np.max(sv))
    vel_cov = upper_triangle_covariance([vmax, vmax, vmax, math.nan, math.nan, math.nan])
    nan = math.nan
    return _ENC.odometry_encode(int(t_boot_us), m.MAV_FRAME_LOCAL_FRD, m.MAV_FRAME_BODY_FRD,
                                float(ned[0]), float(ned[1]), float(ned[2]), _rot_to_quat(Cbn),
                                float(v_b[0]), float(v_b[1]), float(v_b[2]), nan, nan, nan,
                                pose_cov, vel_cov, int(reset_counter) & 0xFF,
                                m.MAV_ESTIMATOR_TYPE_VISION, int(max(-1, min(100, quality))))


#: GPS_INPUT fix_type (MAVLink GPS_FIX_TYPE, ArduPilot's AP_GPS::GPS_Status takes it as is)
GPS_FIX_NO_FIX, GPS_FIX_3D, GPS_FIX_DGPS, GPS_FIX_RTK_FLOAT, GPS_FIX_RTK_FIXED = 1, 3, 4, 5, 6


def gps_fix_type(sol: NavSolution) -> int:
    """GPS_INPUT fix type of a solution: no fix unless navigating (status 'nav' or 'coasting');
    then RTK fixed (6) / float (5) from the carrier-phase fix state, else DGPS (4) when
    ``sol.extras['dgps']``, else 3-D (3).  ArduPilot's EKF uses the fix type for its GPS checks
    and reports it (GPS_RAW_INT, the GCS's "RTK Fixed"); the position accuracy it fuses with is
    the sigma sent beside it, which for a fixed solution is the filter's own covariance."""
    if sol.status not in ("nav", "coasting"):
        return GPS_FIX_NO_FIX
    if sol.fix_state == "fixed":
        return GPS_FIX_RTK_FIXED
    if sol.fix_state == "float":
        return GPS_FIX_RTK_FLOAT
    return GPS_FIX_DGPS if sol.extras.get("dgps") else GPS_FIX_3D


def gps_input(sol: NavSolution, t_gps: float | None = None, *, t_boot_us: int = 0, gps_id: int = 0,
              fix_type: int | None = None, satellites_visible: int = 10, geoid_undulation_m: float = 0.0,
              uere_m: float = 1.0, min_dop: float = 0.6):
    """GPS_INPUT (ArduPilot ``GPS1_TYPE = 14``, ``AP_GPS_MAV``): all fields provided (no ignore
    flags), yaw 0 = not provided.  ``alt`` is MSL: ellipsoidal height minus
    ``geoid_undulation_m``.  ArduPilot needs ``fix_type >= 3`` and ``time_week > 0`` to use the
    time stamp; hdop/vdop are synthetic (sigma / ``uere_m``, at least ``min_dop``) because
    ArduPilot's GPS checks look at hdop.  Set the autopilot's ``GPS1_POS`` to 0: this is the IMU
    position.  ``fix_type`` default: :func:`gps_fix_type` (6/5 for an RTK fixed/float solution)."""
    t = sol.t_gps if t_gps is None else t_gps
    week, tow = gps_week_tow(t)
    lat, lon, h = ecef_to_geodetic(sol.r_e)
    v_n = C_n_e(lat, lon).T @ np.asarray(sol.v_e, float)
    sr = np.asarray(sol.sigma_r_n_m, float)
    sv = np.asarray(sol.sigma_v_n_mps, float)
    sig_h = float(math.hypot(sr[0], sr[1]))
    if fix_type is None:
        fix_type = gps_fix_type(sol)
    return _ENC.gps_input_encode(
        int(t_boot_us), int(gps_id), 0, int(round(tow * 1000.0)) % int(SECONDS_PER_WEEK * 1000), int(week),
        int(fix_type), int(round(math.degrees(lat) * 1e7)), int(round(math.degrees(lon) * 1e7)),
        float(h - geoid_undulation_m), max(min_dop, sig_h / uere_m), max(min_dop, float(sr[2]) / uere_m),
        float(v_n[0]), float(v_n[1]), float(v_n[2]), float(math.sqrt(float(np.sum(sv ** 2)))),
        sig_h, float(sr[2]), int(satellites_visible), 0)


def set_gps_global_origin(lat_deg: float, lon_deg: float, alt_m: float, target_system: int = 1,
                          time_usec: int = 0):
    """SET_GPS_GLOBAL_ORIGIN (lat/lon 1e7 deg, altitude mm; ArduPilot treats it as AMSL and only
    accepts it while no origin is set)."""
    return _ENC.set_gps_global_origin_encode(int(target_system), int(round(lat_deg * 1e7)),
                                             int(round(lon_deg * 1e7)), int(round(alt_m * 1000.0)),
                                             int(time_usec))


def set_gps_global_origin_from(origin: Origin, target_system: int = 1):
    return set_gps_global_origin(math.degrees(origin.lat_rad), math.degrees(origin.lon_rad), origin.alt_m,
                                 target_system)


def statustext_chunks(severity: int, text: str, msg_id: int = 0) -> list:
    """STATUSTEXT, split into 50-byte chunks (MAVLink 2 ``id``/``chunk_seq``) when longer."""
    raw = text.encode("utf-8", "replace")
    if len(raw) <= 50:
        return [_ENC.statustext_encode(int(severity), raw, 0, 0)]
    parts = [raw[i:i + 50] for i in range(0, len(raw), 50)]
    return [_ENC.statustext_encode(int(severity), p, (msg_id or 1) & 0xFFFF, k) for k, p in enumerate(parts)]


def statustext(severity: int, text: str):
    """One STATUSTEXT (text truncated to 50 bytes)."""
    return _ENC.statustext_encode(int(severity), text.encode("utf-8", "replace")[:50], 0, 0)


def gps_rtcm_data_messages(frame: bytes, fragmenter: GpsRtcmDataFragmenter) -> list:
    """GPS_RTCM_DATA messages for one RTCM frame (fragmentation from :mod:`companion.io.rtcm`)."""
    out = []
    for flags, data in fragmenter.fragments(frame):
        padded = list(data) + [0] * (GPS_RTCM_DATA_LEN - len(data))
        out.append(_ENC.gps_rtcm_data_encode(flags, len(data), padded))
    return out


def heartbeat():
    return _ENC.heartbeat_encode(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_ACTIVE)


def command_set_message_interval(message_id: int, rate_hz: float, target_system: int = 1,
                                 target_component: int = 1, confirmation: int = 0):
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL: param1 message id, param2 interval in us
    (-1 = disable; 0 = default rate)."""
    interval_us = -1.0 if rate_hz <= 0 else 1e6 / rate_hz
    return _ENC.command_long_encode(int(target_system), int(target_component),
                                    m.MAV_CMD_SET_MESSAGE_INTERVAL, confirmation,
                                    float(message_id), float(interval_us), 0, 0, 0, 0, 0)


def serial_control_request(device: int, data: bytes = b"", *, flags: int | None = None, timeout_ms: int = 0,
                           baudrate: int = 0, target_system: int = 1, target_component: int = 1):
    """SERIAL_CONTROL request: up to 70 bytes to write, flags RESPOND|EXCLUSIVE|MULTI by default.

    ArduPilot (``GCS_MAVLINK::handle_serial_control``): EXCLUSIVE locks the port away from its own
    GPS driver (``AP_GPS::lock_port``) so the two do not split the byte stream -- the autopilot
    then has no GPS of its own from that port; a request without EXCLUSIVE gives it back.  Data
    is only returned in answer to a request with RESPOND, at most 70 bytes per reply; MULTI makes
    it keep replying while bytes are available.  ``timeout_ms`` > 0 makes the autopilot *sleep*
    in its MAVLink thread waiting for data: keep it 0 and poll instead."""
    if len(data) > SERIAL_CONTROL_DATA_LEN:
        raise ValueError("SERIAL_CONTROL carries at most 70 bytes")
    if flags is None:
        flags = (m.SERIAL_CONTROL_FLAG_RESPOND | m.SERIAL_CONTROL_FLAG_EXCLUSIVE
                 | m.SERIAL_CONTROL_FLAG_MULTI)
    payload = list(data) + [0] * (SERIAL_CONTROL_DATA_LEN - len(data))
    msg = _ENC.serial_control_encode(int(device), int(flags), int(timeout_ms), int(baudrate), len(data), payload)
    if hasattr(msg, "target_system"):
        msg.target_system = int(target_system)
        msg.target_component = int(target_component)
    return msg


# =============================================================================================
# (c) the link
@dataclass(frozen=True, slots=True)
class LinkMessage:
    t_mono_ns: int        # receive time, CLOCK_MONOTONIC
    raw: bytes            # the message's bytes as received (for the field log)
    msg: object           # the pymavlink message


@dataclass
class _PendingInterval:
    msg_id: int
    rate_hz: float
    acked: bool = False
    sent: int = 0
    last_sent_mono: float = -1e9
    result: int | None = None


def _offset_rate(samples, max_rate: float = 0.05) -> float:
    """Least-squares slope of the TIMESYNC offsets against our time (>= 3 samples over >= 2 s),
    clamped to +-``max_rate``; 0 otherwise."""
    if len(samples) < 3 or samples[-1][2] - samples[0][2] < 2_000_000_000:
        return 0.0
    n = len(samples)
    mt = sum(s[2] for s in samples) / n
    mo = sum(s[1] for s in samples) / n
    stt = sum((s[2] - mt) ** 2 for s in samples)
    slope = sum((s[2] - mt) * (s[1] - mo) for s in samples) / stt
    return min(max(slope, -max_rate), max_rate)


class MavlinkLink:
    """Asyncio MAVLink link to one autopilot.

    Usage::

        link = MavlinkLink("udpin:127.0.0.1:14550", message_rates_hz={"HIGHRES_IMU": 200, ...})
        await link.start()
        async for lm in link:          # LinkMessage(t_mono_ns, raw, msg), every message received
            ...
        link.send(msg)                 # a pymavlink message object, packed with our ids
        await link.close()

    Behaviour:

    * HEARTBEAT every ``heartbeat_interval_s`` as MAV_TYPE_ONBOARD_CONTROLLER / MAV_AUTOPILOT_INVALID.
    * On the autopilot's first HEARTBEAT, after a link loss and after a reboot (boot time going
      backwards in SYSTEM_TIME/ATTITUDE/IMU), sends MAV_CMD_SET_MESSAGE_INTERVAL for every entry of
      ``message_rates_hz`` and re-sends each every ``interval_retry_s`` until a COMMAND_ACK
      (result ACCEPTED) names it -- acks cannot name the message id, so commands are sent one at a
      time and the ack is matched to the oldest outstanding one.
    * Sends TIMESYNC requests every ``timesync_interval_s`` and keeps the round trip time and the
      autopilot-boot minus our monotonic clock offset (:attr:`timesync_offset_ns`, from the
      lowest-RTT exchange of the last 16; forgotten when the autopilot reboots).
    * Answers TIMESYNC requests (``tc1 == 0``) with ``tc1`` = our clock *in autopilot boot time*
      (our monotonic ns + that offset; plain monotonic ns until the first reply).  Our estimates are
      stamped in autopilot boot time (the IMU samples' own stamps), and PX4 converts every incoming
      timestamp by the offset it learns from our answers (``Timesync::sync_stamp``): answering in
      the same time base makes that offset ~0 instead of the boot-to-monotonic difference.
      ArduPilot learns its own offset (jitter correction) and is indifferent.
    * Link loss: no HEARTBEAT from ``target_system`` for ``link_timeout_s`` -> ``connected`` False,
      counted; a HEARTBEAT brings it back (counted) and re-requests the streams.
    * Bad CRC / unknown ids / truncated frames: counted by reason (``bad_data``), never yielded.
    * ``fallback_streams`` {primary: alternative}: when the autopilot refuses the primary's interval
      or none of it arrives within ``fallback_after_s`` of the link coming up, the alternative is
      requested at the primary's rate instead (counted ``stream_fallbacks``; 'auto' IMU).
    * ``subscribe(type, callback)``: callback(msg, t_mono_ns) on the event loop for every message of
      that type (e.g. the SERIAL_CONTROL tunnel) in addition to the iterator.
    * The receive queue is bounded (``queue_size``); when full the newest message is dropped and
      counted (``rx_queue_overflow``) -- the consumer is too slow, the link keeps running.
    * ``signing`` (a :class:`~companion.io.mavlink_signing.LinkSigning`): MAVLink 2 signing of what
      we send and checks of what we receive; a refused frame goes nowhere and is counted there
      (``signing: ...`` keys in :meth:`health`), not as ``bad_data``.
    """

    def __init__(self, connection: str, *, source_system: int = 1,
                 source_component: int = MAV_COMP_ID_ONBOARD_COMPUTER, target_system: int = 1,
                 target_component: int = 1, message_rates_hz: dict[str, float] | None = None,
                 heartbeat_interval_s: float = 1.0, link_timeout_s: float = 3.0,
                 timesync_interval_s: float = 1.0, interval_retry_s: float = 1.0,
                 interval_max_retries: int = 10, queue_size: int = 20000,
                 time_map: BootToGpsTime | None = None, fallback_streams: dict[str, str] | None = None,
                 fallback_after_s: float = STREAM_FALLBACK_AFTER_S, signing=None):
        self.connection = connection
        self.signing = signing             # LinkSigning (companion.io.mavlink_signing) or None
        self.source_system = source_system
        self.source_component = source_component
        self.target_system = target_system
        self.target_component = target_component
        self.message_rates_hz = dict(message_rates_hz or {})
        self.heartbeat_interval_s = heartbeat_interval_s
        self.link_timeout_s = link_timeout_s
        self.timesync_interval_s = timesync_interval_s
        self.interval_retry_s = interval_retry_s
        self.interval_max_retries = interval_max_retries
        self.time_map = time_map if time_map is not None else BootToGpsTime()
        self.conn = None
        self.counters: dict[str, int] = {
            "rx_messages": 0, "rx_bytes": 0, "tx_messages": 0, "tx_errors": 0, "bad_data": 0,
            "rx_queue_overflow": 0, "heartbeats_rx": 0, "link_losses": 0, "link_recoveries": 0,
            "interval_requests": 0, "interval_acks": 0, "interval_nacks": 0, "interval_gave_up": 0,
            "timesync_answered": 0, "timesync_sent": 0, "timesync_replies": 0, "autopilot_reboots": 0,
            "stream_fallbacks": 0, "rx_pauses": 0, "rx_busy_reads": 0}
        self.bad_data_reasons: dict[str, int] = {}
        self.connected = False
        self.last_heartbeat_mono: float | None = None
        self.autopilot_type: int | None = None
        self.autopilot_autopilot: int | None = None
        self.timesync_rtt_ns: int | None = None
        self.timesync_offset_ns: int | None = None
        self._ts_samples: deque = deque(maxlen=16)     # (rtt, offset, our mid-point time), ns
        self._ts_rate = 0.0                             # d(offset)/d(our time)
        self._ts_best = (0, 0, 0)
        self._ts_sent: dict[int, int] = {}
        self._ts_reply_by = 0.0                         # monotonic s: a TIMESYNC reply may come until then
        self._queue: asyncio.Queue | None = None
        self._queue_size = queue_size
        self._tasks: list[asyncio.Task] = []
        self._loop: asyncio.AbstractEventLoop | None = None
        self._fd: int | None = None
        self._subs: dict[str, list[Callable]] = {}
        self._intervals: deque[_PendingInterval] = deque()
        self._closed = False
        self._seen_reboot_epoch = 0
        self._last_boot_ms: int | None = None
        # primaries still waiting for their first message -> their alternative
        self._fallback = {k: v for k, v in (fallback_streams or {}).items() if k in self.message_rates_hz}
        self._fallback_after_s = fallback_after_s
        self._link_up_mono: float | None = None
        self.peer_lock = None              # UdpPeerLock on a udpin connection
        self._fast = None                  # DatagramParser on a UDP link without signing
        self._sink: Callable | None = None  # deliver_to's consumer, called instead of queueing
        self._sink_done: asyncio.Future | None = None
        # called after each receive callback: periodic work that rides on a wake-up the process
        # has anyway (the SERIAL_CONTROL poll, serial_control.run_every); a hook's ``next_due()``
        # (monotonic s or None), when it has one, is kept while the reader sleeps (rx_pause)
        self.rx_hooks: list[Callable[[], None]] = []
        # after each read of the descriptor: how long the reader may sleep (seconds; 0 = read on
        # arrival).  What arrives meanwhile waits in the socket and is read in one go: fewer
        # wake-ups (companion.io.rx_pacing).  Never while our TIMESYNC request is out.
        self.rx_pause: Callable[[], float] | None = None
        self._rx_resume: asyncio.TimerHandle | None = None
        self._hooks_timer: asyncio.TimerHandle | None = None
        self._timer: asyncio.TimerHandle | None = None    # the periodic work (_arm)
        self._timer_when = 0.0
        self._next_hb = self._next_ts = 0.0

    # -- lifecycle ---------------------------------------------------------------------------
    async def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._queue = asyncio.Queue(maxsize=self._queue_size)
        self.conn = mavutil.mavlink_connection(self.connection, source_system=self.source_system,
                                               source_component=self.source_component,
                                               dialect="ardupilotmega", autoreconnect=True)
        self.conn.mav.robust_parsing = True
        if self.signing is not None:
            self.signing.attach(self.conn)
        if isinstance(self.conn, mavutil.mavudp):
            try:      # room for what arrives while the reader sleeps (rx_pause) or the loop is busy
                self.conn.port.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, UDP_RX_BUFFER_BYTES)
            except OSError:
                pass                     # the kernel's default (Linux caps it at net.core.rmem_max)
        if isinstance(self.conn, mavutil.mavudp) and self.conn.udp_server:
            from .udp_peer import UdpPeerLock
            self.peer_lock = UdpPeerLock(self.conn, relock_after_s=max(5.0, 2 * self.link_timeout_s))
        if self.signing is None and isinstance(self.conn, mavutil.mavudp) and os.environ.get(
                "COMPANION_MAVLINK_FAST", "1") != "0":
            # one datagram at a time: its leading high-rate frames without pymavlink's per-byte
            # machinery (companion.io.mavlink_fast); signing needs every frame through pymavlink
            from .mavlink_fast import DatagramParser
            self._fast = DatagramParser(self.conn.mav, post=self.conn.post_message,
                                        on_error=lambda exc: self._bad("exception: " + type(exc).__name__))
        fd = getattr(self.conn, "fd", None)
        if fd is None:
            port = getattr(self.conn, "port", None)
            fd = port.fileno() if port is not None and hasattr(port, "fileno") else None
        if fd is not None and fd >= 0:
            try:
                self._loop.add_reader(fd, self._drain)
                self._fd = fd
            except (ValueError, OSError, NotImplementedError):
                self._fd = None
        self.send(heartbeat())
        self._start_timer()

    async def close(self) -> None:
        self._closed = True
        for h in (self._rx_resume, self._hooks_timer):
            if h is not None:
                h.cancel()
        self._rx_resume = self._hooks_timer = None
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        for t in self._tasks:
            t.cancel()
        for t in self._tasks:
            try:
                await t
            except (asyncio.CancelledError, Exception):
                pass
        self._tasks = []
        if self._fd is not None and self._loop is not None:
            self._loop.remove_reader(self._fd)
            self._fd = None
        if self.conn is not None:
            try:
                self.conn.close()
            except Exception:
                pass
        if self._sink_done is not None and not self._sink_done.done():
            self._sink_done.set_result(None)
        if self._queue is not None:
            try:
                self._queue.put_nowait(None)
            except asyncio.QueueFull:
                pass

    async def __aenter__(self):
        await self.start()
        return self

    async def __aexit__(self, *exc):
        await self.close()

    def __aiter__(self) -> AsyncIterator[LinkMessage]:
        return self._iter()

    async def _iter(self):
        while True:
            item = await self._queue.get()
            if item is None:
                return
            yield item

    async def deliver_to(self, sink: Callable[[LinkMessage], None]) -> None:
        """Hand every received message to ``sink`` synchronously, from the receive callback, instead
        of the queue (no task wake-up and no extra event-loop pass per message); returns when the link
        closes, raises what ``sink`` raised (the sink is then detached: the caller restarts)."""
        fut = self._loop.create_future()
        self._sink, self._sink_done = sink, fut
        try:
            await fut
        finally:
            if self._sink_done is fut:
                self._sink = self._sink_done = None

    async def recv(self, timeout: float | None = None) -> LinkMessage | None:
        """The next received message (None on timeout or close)."""
        try:
            return await asyncio.wait_for(self._queue.get(), timeout)
        except asyncio.TimeoutError:
            return None

    def subscribe(self, msg_type: str, callback: Callable) -> None:
        self._subs.setdefault(msg_type, []).append(callback)

    # -- sending -----------------------------------------------------------------------------
    def send(self, msg) -> bool:
        """Pack with our system/component ids and send.  Never raises on I/O errors (counted)."""
        if self.conn is None:
            return False
        try:
            self.conn.mav.send(msg)
            self.counters["tx_messages"] += 1
            return True
        except Exception as exc:  # socket errors, closed serial port
            self.counters["tx_errors"] += 1
            log.debug("MAVLink send failed: %r", exc)
            return False

    def send_fixed(self, msg, cache: dict) -> bool:
        """Send ``msg``, whose fields never change (the SERIAL_CONTROL poll, 50 a second), from
        ``cache``: its frame packed once per sequence number, ids and protocol version -- byte for
        byte what :meth:`send` would send, without pymavlink's pack each time.  Signed links pack
        every frame (the signature changes)."""
        conn = self.conn
        if conn is None:
            return False
        mav = conn.mav
        if getattr(mav.signing, "sign_outgoing", False) or mav.send_callback is not None:
            return self.send(msg)
        key = (mav.seq, mav.srcSystem, mav.srcComponent, type(mav))     # type: a v1 switch replaces it
        try:
            buf = cache.get(key)
            if buf is None:
                buf = cache[key] = bytes(msg.pack(mav))
            conn.write(buf)
            mav.seq = (mav.seq + 1) % 256
            mav.total_packets_sent += 1
            mav.total_bytes_sent += len(buf)
            self.counters["tx_messages"] += 1
            return True
        except Exception as exc:  # socket errors, closed serial port
            self.counters["tx_errors"] += 1
            log.debug("MAVLink send failed: %r", exc)
            return False

    # -- receiving ---------------------------------------------------------------------------
    def _drain(self) -> None:
        c = self.counters
        n0 = c["rx_messages"] + c["bad_data"]
        if self._fast is not None:
            self._drain_datagrams()
        else:
            self._drain_messages()
        for hook in self.rx_hooks:
            hook()
        if self.rx_pause is not None and self._fd is not None:
            if c["rx_messages"] + c["bad_data"] - n0 > RX_BUSY_MESSAGES:
                c["rx_busy_reads"] += 1                   # a burst or a flood: keep reading
            else:
                self._maybe_pause()

    # -- paced reading (rx_pause) ------------------------------------------------------------
    def _maybe_pause(self) -> None:
        """Stop reading for ``rx_pause()`` seconds; not while our TIMESYNC request waits for its
        reply (its round trip would count the sleep)."""
        now = time.monotonic()
        if now < self._ts_reply_by:
            return
        pause = self.rx_pause()
        if pause < MIN_RX_PAUSE_S:
            return
        self._loop.remove_reader(self._fd)
        self._rx_resume = self._loop.call_later(pause, self._resume_reading)
        self.counters["rx_pauses"] += 1
        self._arm_paused_hooks(now)

    def _arm_paused_hooks(self, now: float) -> None:
        """While the reader sleeps, the hooks due before it wakes (the SERIAL_CONTROL poll keeps its
        grid: the autopilot's GPS port buffers ~22 ms) run from a timer of their own, without a
        read: a read then would cost a wake-up's worth of datagrams.  A hook due just after the
        reader wakes, while it waits for the next output slot's sample, runs ``HOOK_EARLY_S``
        before instead (``run_early``, when it has one): its reply then comes with the batch
        rather than as a wake-up of its own."""
        if self._rx_resume is None:
            return
        resume = now + (self._rx_resume.when() - self._loop.time())
        when = None
        for hook in self.rx_hooks:
            plan = self._hook_time(hook, resume)
            if plan is not None and (when is None or plan[0] < when):
                when = plan[0]
        if when is not None:
            self._hooks_timer = self._loop.call_later(max(0.0, when - now), self._paused_hooks)

    @staticmethod
    def _hook_time(hook, resume: float) -> tuple[float, bool] | None:
        """When the paused reader's timer runs ``hook`` (monotonic s) and whether early, or None
        (at the next read)."""
        next_due = getattr(hook, "next_due", None)
        due = next_due() if next_due is not None else None
        if due is None:
            return None
        if due + DEADLINE_SLACK_S < resume - HOOK_EARLY_S:
            return due + DEADLINE_SLACK_S, False    # just after: the hook finds itself due
        if due < resume + HOOK_WINDOW_S and getattr(hook, "run_early", None) is not None:
            return resume - HOOK_EARLY_S, True
        return None

    def _paused_hooks(self) -> None:
        self._hooks_timer = None
        if self._rx_resume is None:
            return                       # reading again: the hooks ride on the reads
        now = time.monotonic()
        resume = now + (self._rx_resume.when() - self._loop.time())
        for hook in self.rx_hooks:
            plan = self._hook_time(hook, resume)
            if plan is not None and plan[1] and now >= plan[0]:
                hook.run_early()
            else:
                hook()                   # runs only when due
        self._arm_paused_hooks(time.monotonic())

    def _resume_reading(self) -> None:
        self._rx_resume = None
        if self._hooks_timer is not None:
            self._hooks_timer.cancel()
            self._hooks_timer = None
        if self._closed or self._fd is None:
            return
        self._loop.add_reader(self._fd, self._drain)
        self._drain()                    # what arrived meanwhile, at once

    def _drain_messages(self) -> None:
        conn = self.conn
        for _ in range(10000):
            try:
                msg = conn.recv_msg()
            except Exception as exc:  # pymavlink raises on some malformed input
                self._bad("exception: " + type(exc).__name__)
                continue
            if msg is None:
                break
            self._handle(msg, time.monotonic_ns())
        if self.signing is not None:
            # at once, not at the next timer: a protocol auto-switch in recv_msg replaced the
            # MAVLink object, and what we send next must be signed again
            self.signing.tick()

    def _drain_datagrams(self) -> None:
        """The UDP receive path: each datagram through :class:`~companion.io.mavlink_fast.DatagramParser`
        (the lean decoder for its leading high-rate frames, pymavlink for the rest) -- the messages
        ``recv_msg`` would have given, in the same order."""
        conn = self.conn
        feed = self._fast.feed
        for _ in range(10000):
            try:
                data = conn.recv()
            except Exception as exc:
                self._bad("exception: " + type(exc).__name__)
                return
            if not data:
                return
            t_ns = time.monotonic_ns()
            if conn.first_byte:                 # pymavlink's MAVLink 1/2 detection, as recv_msg does
                conn.auto_mavlink_version(data)
            for msg in feed(data):
                self._handle(msg, t_ns)

    def _bad(self, reason: str) -> None:
        self.counters["bad_data"] += 1
        key = reason.split(",")[0][:60]
        self.bad_data_reasons[key] = self.bad_data_reasons.get(key, 0) + 1

    def _handle(self, msg, t_ns: int) -> None:
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            if self.signing is not None and self.signing.rejected(msg):
                return                           # refused by signing: counted there, not bad data
            self._bad(str(getattr(msg, "reason", "bad data")))
            return
        if mtype.startswith("UNKNOWN_"):
            # an id outside the dialect: its CRC cannot be checked; after a truncated frame this
            # is usually garbage, so it is counted and not passed on
            self._bad("unknown message id")
            return
        raw = bytes(msg.get_msgbuf())
        self.counters["rx_messages"] += 1
        self.counters["rx_bytes"] += len(raw)
        from_ap = msg.get_srcSystem() == self.target_system
        if self._fallback and mtype in self._fallback:
            del self._fallback[mtype]            # the primary arrives: no fallback needed
        if mtype == "HEARTBEAT" and from_ap and msg.type != m.MAV_TYPE_GCS \
                and msg.get_srcComponent() == self.target_component:
            self._on_heartbeat(msg)
        elif mtype == "TIMESYNC":
            self._on_timesync(msg, t_ns)
        elif mtype == "COMMAND_ACK" and from_ap:
            self._on_command_ack(msg)
        if from_ap and mtype in ("SYSTEM_TIME", "ATTITUDE"):
            boot_ms = int(msg.time_boot_ms)
            if mtype == "SYSTEM_TIME":
                self.time_map.update_system_time(int(msg.time_unix_usec), boot_ms)
            else:
                self.time_map.observe_boot_time(boot_ms * 1e-3)
        if self.time_map.boot_epoch != self._seen_reboot_epoch:
            self._seen_reboot_epoch = self.time_map.boot_epoch
            self.counters["autopilot_reboots"] += 1
            self._ts_samples.clear()             # its boot clock restarted: the old offset is void
            self.timesync_offset_ns = None
            self._request_streams("autopilot reboot")
        for cb in self._subs.get(mtype, ()):
            try:
                cb(msg, t_ns)
            except Exception:
                log.exception("MAVLink subscriber for %s failed", mtype)
        sink = self._sink
        if sink is not None:
            try:
                sink(LinkMessage(t_ns, raw, msg))
            except Exception as exc:
                self._sink = None                # later messages queue until the caller is back
                if not self._sink_done.done():
                    self._sink_done.set_exception(exc)
            return
        try:
            self._queue.put_nowait(LinkMessage(t_ns, raw, msg))
        except asyncio.QueueFull:
            self.counters["rx_queue_overflow"] += 1

    def _on_heartbeat(self, msg) -> None:
        if self.peer_lock is not None:
            self.peer_lock.lock()          # the datagram just parsed came from the autopilot
        self.counters["heartbeats_rx"] += 1
        self.last_heartbeat_mono = time.monotonic()
        self.autopilot_type = msg.type
        self.autopilot_autopilot = msg.autopilot
        if not self.connected:
            if self.counters["heartbeats_rx"] > 1 or self.counters["link_losses"]:
                self.counters["link_recoveries"] += 1
                log.info("autopilot link recovered")
            self.connected = True
            self._link_up_mono = self.last_heartbeat_mono
            self._request_streams("link up")
            self._wake_now()               # TIMESYNC and the timeout/fallback deadlines start now

    def _on_timesync(self, msg, t_ns: int) -> None:
        if msg.tc1 == 0:
            ours_ns = t_ns if self.timesync_offset_ns is None else t_ns + self._timesync_offset_at(t_ns)
            reply = _ENC.timesync_encode(ours_ns, msg.ts1)
            if hasattr(reply, "target_system"):
                reply.target_system = msg.get_srcSystem()
                reply.target_component = msg.get_srcComponent()
            self.send(reply)
            self.counters["timesync_answered"] += 1
            return
        sent = self._ts_sent.pop(int(msg.ts1), None)
        if sent is None:
            return
        self._ts_reply_by = 0.0
        rtt = t_ns - sent
        self.counters["timesync_replies"] += 1
        # autopilot time tc1 (ns since its boot) corresponds to our mid-point
        offset = int(msg.tc1) - (sent + rtt // 2)
        self._ts_samples.append((rtt, offset, sent + rtt // 2))
        self._ts_rate = _offset_rate(self._ts_samples)
        self._ts_best = min(self._ts_samples)
        self.timesync_rtt_ns = rtt
        self.timesync_offset_ns = self._timesync_offset_at(t_ns)

    def _timesync_offset_at(self, t_ns: int) -> int:
        """The lowest-RTT offset of the window, carried to ``t_ns`` at the offset's drift rate: PX4
        SITL's lockstep boot clock runs ~1.3 % slow, so a 16-s-old best sample is 0.2 s off, and
        PX4 resets its time synchroniser after 5 answers more than 0.1 s from its estimate ("time
        jump detected"), converting our estimates' stamps wrongly meanwhile (EKF2 lost our vision)."""
        _, off, t_ref = self._ts_best
        return int(off + self._ts_rate * (t_ns - t_ref))

    def mono_to_boot_us(self, t_mono_ns: int) -> int | None:
        """Our monotonic time -> autopilot boot time (us), from TIMESYNC; None before a reply."""
        if self.timesync_offset_ns is None:
            return None
        return (t_mono_ns + self._timesync_offset_at(t_mono_ns)) // 1000

    def _on_command_ack(self, msg) -> None:
        if msg.command != m.MAV_CMD_SET_MESSAGE_INTERVAL:
            return
        pend = next((p for p in self._intervals if not p.acked and p.sent > 0), None)
        if pend is None:
            return
        pend.result = int(msg.result)
        if msg.result == m.MAV_RESULT_ACCEPTED:
            pend.acked = True
            self.counters["interval_acks"] += 1
        else:
            pend.acked = True          # a refusal will not change by repeating it
            self.counters["interval_nacks"] += 1
            log.warning("autopilot refused SET_MESSAGE_INTERVAL for message %d (result %d)",
                        pend.msg_id, msg.result)
            primary = next((k for k in self._fallback if getattr(m, f"MAVLINK_MSG_ID_{k}", None) == pend.msg_id),
                           None)
            if primary is not None:
                self._fall_back(primary, "refused")
        self._send_next_interval()

    def _fall_back(self, primary: str, why: str) -> None:
        alt = self._fallback.pop(primary)
        rate = self.message_rates_hz[primary]
        self.message_rates_hz[alt] = rate
        self._intervals.append(_PendingInterval(getattr(m, f"MAVLINK_MSG_ID_{alt}"), float(rate)))
        self.counters["stream_fallbacks"] += 1
        log.warning("%s %s by the autopilot: requesting %s at %g Hz instead", primary, why, alt, rate)

    # -- stream rates ------------------------------------------------------------------------
    def _request_streams(self, why: str) -> None:
        if not self.message_rates_hz:
            return
        log.info("requesting message intervals (%s)", why)
        self._intervals.clear()
        for name, rate in self.message_rates_hz.items():
            msg_id = getattr(m, f"MAVLINK_MSG_ID_{name}", None)
            if msg_id is None:
                log.error("unknown MAVLink message %s in message_rates_hz", name)
                continue
            self._intervals.append(_PendingInterval(msg_id, float(rate)))
        self._send_next_interval()

    def _send_next_interval(self) -> None:
        now = time.monotonic()
        for p in self._intervals:
            if p.acked:
                continue
            if p.sent and now - p.last_sent_mono < self.interval_retry_s:
                return                  # one outstanding at a time
            if p.sent >= self.interval_max_retries:
                p.acked = True
                self.counters["interval_gave_up"] += 1
                log.warning("no COMMAND_ACK for SET_MESSAGE_INTERVAL of message %d", p.msg_id)
                continue
            self.send(command_set_message_interval(p.msg_id, p.rate_hz, self.target_system,
                                                   self.target_component, confirmation=min(p.sent, 255)))
            p.sent += 1
            p.last_sent_mono = now
            self.counters["interval_requests"] += 1
            return

    @property
    def intervals_acknowledged(self) -> bool:
        return bool(self._intervals) and all(p.acked and p.result == m.MAV_RESULT_ACCEPTED
                                             for p in self._intervals)

    # -- periodic work -----------------------------------------------------------------------
    # No polling task: one loop timer (``call_at``) armed for the earliest deadline -- heartbeat,
    # TIMESYNC, link timeout, stream fallback, interval retry -- at most TIMER_SAFETY_NET_S ahead,
    # so anything not computed here is late by at most that; a transport without a file
    # descriptor (nothing to wake the loop) is still drained every POLL_NO_FD_S.
    def _start_timer(self) -> None:
        now = time.monotonic()
        self._next_hb = self._next_ts = now
        self._arm(now)

    def _arm(self, when: float) -> None:
        """(Re-)arm the timer for ``when`` (monotonic s) unless it already fires earlier."""
        if self._closed or self._loop is None:
            return
        h = self._timer
        if h is not None:
            if not h.cancelled() and self._timer_when <= when:
                return
            h.cancel()
        # loop.time() is time.monotonic() for the default loops; converted anyway
        self._timer_when = when
        self._timer = self._loop.call_at(self._loop.time() + (when - time.monotonic()), self._on_timer)

    def _wake_now(self) -> None:
        """A state change (link up) brings deadlines forward: run the periodic work next pass."""
        self._arm(time.monotonic())

    def _on_timer(self) -> None:
        self._timer = None
        now = time.monotonic()
        try:
            self._tick(now)
        except Exception:      # a bug here must not end the heartbeats and the timeout checks
            self.counters["timer_errors"] = self.counters.get("timer_errors", 0) + 1
            log.exception("MAVLink link periodic work failed")
        finally:
            self._arm(self._next_deadline(time.monotonic()))

    def _tick(self, now: float) -> None:
        if self._fd is None:
            self._drain()
        if self.signing is not None:
            self.signing.tick()
        if now >= self._next_hb:
            self.send(heartbeat())
            self._next_hb = now + self.heartbeat_interval_s
        if self.timesync_interval_s > 0 and now >= self._next_ts and self.connected:
            ts1 = time.monotonic_ns()
            self._ts_sent[ts1] = ts1
            self._ts_reply_by = now + TIMESYNC_REPLY_WAIT_S     # read it on arrival: its RTT counts
            if len(self._ts_sent) > 32:
                self._ts_sent.pop(next(iter(self._ts_sent)))
            req = _ENC.timesync_encode(0, ts1)
            if hasattr(req, "target_system"):
                req.target_system = self.target_system
                req.target_component = self.target_component
            self.send(req)
            self.counters["timesync_sent"] += 1
            self._next_ts = now + self.timesync_interval_s
        if self.connected and self.last_heartbeat_mono is not None \
                and now - self.last_heartbeat_mono > self.link_timeout_s:
            self.connected = False
            self.counters["link_losses"] += 1
            log.warning("autopilot link lost (no HEARTBEAT for %.1f s)", now - self.last_heartbeat_mono)
        if self._fallback and self.connected and self._link_up_mono is not None \
                and now - self._link_up_mono > self._fallback_after_s:
            for primary in list(self._fallback):
                self._fall_back(primary, f"not sent within {self._fallback_after_s:g} s")
        self._send_next_interval()

    def _next_deadline(self, now: float) -> float:
        t = min(now + TIMER_SAFETY_NET_S, self._next_hb)
        if self._fd is None:
            t = min(t, now + POLL_NO_FD_S)
        if self.connected:
            if self.timesync_interval_s > 0:
                t = min(t, self._next_ts)
            if self.last_heartbeat_mono is not None:
                t = min(t, self.last_heartbeat_mono + self.link_timeout_s + DEADLINE_SLACK_S)
            if self._fallback and self._link_up_mono is not None:
                t = min(t, self._link_up_mono + self._fallback_after_s + DEADLINE_SLACK_S)
        for p in self._intervals:
            if not p.acked:            # one outstanding at a time: the first not acknowledged
                t = min(t, p.last_sent_mono + self.interval_retry_s if p.sent else now)
                break
        return max(t, now + 0.001)

    def health(self) -> dict:
        return {"connected": self.connected, **self.counters, "bad_data_reasons": dict(self.bad_data_reasons),
                **({} if self.signing is None else {**self.signing.counters, "signing": self.signing.health()}),
                "udp_peer": None if self.peer_lock is None else {
                    "peer": self.peer_lock.peer and "%s:%d" % self.peer_lock.peer, **self.peer_lock.counters},
                "time_map": dict(self.time_map.counters), "timesync_rtt_ms":
                    None if self.timesync_rtt_ns is None else self.timesync_rtt_ns * 1e-6}


def message_rates_from_config(cfg) -> dict[str, float]:
    """The stream rates to request for a :class:`companion.config.MavlinkConfig`."""
    rates: dict[str, float] = {}
    if cfg.imu_cluster:
        for name in cfg.imu_cluster:
            rates[parse_imu_stream(name)[0]] = cfg.imu_rate_hz
    else:   # one stream: 'auto' asks for HIGHRES_IMU, RAW_IMU only as its fallback (link_from_config)
        rates[cfg.imu_message if cfg.imu_message != "auto" else "HIGHRES_IMU"] = cfg.imu_rate_hz
    rates["SYSTEM_TIME"] = cfg.system_time_rate_hz
    if cfg.gps_raw_rate_hz > 0:
        rates["GPS_RAW_INT"] = cfg.gps_raw_rate_hz
    if cfg.attitude_rate_hz > 0:
        rates["ATTITUDE"] = cfg.attitude_rate_hz
    if cfg.extended_sys_state_rate_hz > 0:
        rates["EXTENDED_SYS_STATE"] = cfg.extended_sys_state_rate_hz
    return rates


def link_from_config(cfg, time_map: BootToGpsTime | None = None) -> MavlinkLink:
    """A :class:`MavlinkLink` for a :class:`companion.config.MavlinkConfig` (raises
    :class:`~companion.io.mavlink_signing.SigningKeyError` for an unusable signing key file)."""
    from .mavlink_signing import signing_from_config
    return MavlinkLink(cfg.connection, source_system=cfg.source_system, source_component=cfg.source_component,
                       target_system=cfg.target_system, target_component=cfg.target_component,
                       message_rates_hz=message_rates_from_config(cfg),
                       heartbeat_interval_s=cfg.heartbeat_interval_s, link_timeout_s=cfg.link_timeout_s,
                       timesync_interval_s=cfg.timesync_interval_s, interval_retry_s=cfg.interval_retry_s,
                       time_map=time_map,
                       fallback_streams=IMU_AUTO_FALLBACK if cfg.imu_message == "auto" and not cfg.imu_cluster
                       else None, signing=signing_from_config(cfg))


__all__ = ["BootToGpsTime", "ImuDecoder", "IMU_CLUSTER_STREAMS", "parse_imu_stream", "imu_from_mavlink",
           "imu_rates_from_mavlink", "gps_fix_from_gps_raw_int", "Origin", "ardupilot_ned_from_origin", "vision_position_estimate",
           "odometry", "gps_input", "set_gps_global_origin", "set_gps_global_origin_from", "statustext",
           "statustext_chunks", "gps_rtcm_data_messages", "heartbeat", "command_set_message_interval",
           "serial_control_request", "quality_from_sigma", "upper_triangle_covariance", "pack", "gps_fix_type",
           "parse_bytes", "LinkMessage", "MavlinkLink", "SerialControlTunnel", "message_rates_from_config",
           "link_from_config", "unix_to_gps_s", "gps_to_unix_s", "DEFAULT_LEAP_SECONDS",
           "SERIAL_CONTROL_DEV_GPS1", "SERIAL_CONTROL_DEV_GPS2", "MAV_COMP_ID_ONBOARD_COMPUTER",
           "IMU_AUTO_FALLBACK"]

from .serial_control import SerialControlTunnel  # noqa: E402,F401  (moved; re-exported)
