"""Autopilot boot time to GPS time (pure: no clock, no socket).

:class:`BootToGpsTime` maps ``time_boot_ms``/``time_usec`` of the autopilot's messages to GPS time.
Fed by SYSTEM_TIME (``time_unix_usec`` is UTC; GPS = UTC + leap seconds, 18 s since 2017-01-01,
:data:`DEFAULT_LEAP_SECONDS`), smoothed, with jump and reboot detection; refinable by receiver time
tags (:meth:`BootToGpsTime.refine`)."""
from __future__ import annotations

import calendar
import logging
from collections import deque

log = logging.getLogger(__name__)

GPS_EPOCH_UNIX_S = calendar.timegm((1980, 1, 6, 0, 0, 0))
DEFAULT_LEAP_SECONDS = 18          # GPS - UTC since 2017-01-01 (IERS bulletin C); none announced since


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


__all__ = ["BootToGpsTime", "unix_to_gps_s", "gps_to_unix_s", "GPS_EPOCH_UNIX_S", "DEFAULT_LEAP_SECONDS"]
