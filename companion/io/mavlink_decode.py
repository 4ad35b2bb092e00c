"""Autopilot inputs decoded from MAVLink (pure: no clock, no socket).

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

Times go through :class:`~companion.io.mavlink_time.BootToGpsTime`."""
from __future__ import annotations

import logging
import math

import numpy as np

from ..messages import GnssFix, ImuSample
from ..nav.earth import C_n_e, geodetic_to_ecef
from .imu_streams import IMU_CLUSTER_STREAMS, IMU_MESSAGES  # names shared with the config
from .mavlink_time import DEFAULT_LEAP_SECONDS, BootToGpsTime, unix_to_gps_s

log = logging.getLogger(__name__)

STANDARD_GRAVITY_MPS2 = 9.80665    # ArduPilot GRAVITY_MSS, the mG scaling of RAW_IMU / SCALED_IMU
UNIX_TIME_THRESHOLD_US = 1_000_000_000_000_000    # time_usec above this (2001-09) is UNIX time, not boot time


def parse_imu_stream(name: str) -> tuple[str, int | None]:
    """'SCALED_IMU2' -> ('SCALED_IMU2', None); 'HIGHRES_IMU:1' -> ('HIGHRES_IMU', 1) (its ``id`` field)."""
    if name not in IMU_CLUSTER_STREAMS:
        raise ValueError(f"unknown IMU stream {name!r} (one of {', '.join(IMU_CLUSTER_STREAMS)})")
    msg, _, unit = name.partition(":")
    return msg, (int(unit) if unit else None)


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


__all__ = ["parse_imu_stream", "imu_rates_from_mavlink", "ImuDecoder", "imu_from_mavlink", "gps_fix_from_gps_raw_int",
           "UNIX_TIME_THRESHOLD_US"]
