"""IMU screening before integration: clipped, out-of-range and physically implausible samples.

One bad 5-ms sample integrated as truth is enough to send a strapdown INS kilometres off (a 1e5
m/s^2 sample is a 500 m/s velocity step) and, worse, to make the filter reject the correct GNSS
afterwards.  Every sample is therefore tested, per sensor triad, before the engine integrates it:

* **clip / range**: an axis at or beyond ``clip_fraction`` of the sensor's full scale is clipped
  (the true value is somewhere beyond it) or physically impossible for the sensor;
* **plausibility**: an axis further than ``accel_jump_mps2`` / ``gyro_jump_radps`` from the median
  of the last ``window`` samples is more than a vehicle can do in one IMU interval (rates are the
  autopilot's low-pass filtered ones at 50-400 Hz, so vibration shows as a few m/s^2, not tens).
  The window holds every sample, accepted or not, so a real, lasting step is adopted after
  ``window // 2 + 1`` samples instead of being rejected for ever.

A rejected triad is *bridged*: the last good rate of that triad times this interval is integrated
instead, and the covariance grows by what the sample could have hidden, per body axis
``sigma = min(|measured - held|, jump limit) * tau`` (the jump limit bounds what the vehicle can
physically have done, the difference what the sensor claims it did).

Hot path: plain floats and preallocated lists; the median is only computed when the quick test
against the previous sample fails.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass

log = logging.getLogger(__name__)

STANDARD_GRAVITY_MPS2 = 9.80665


@dataclass(frozen=True)
class ImuFullScale:
    """Full-scale range of an IMU stream (symmetric, per axis)."""

    accel_mps2: float
    gyro_radps: float


# Per MAVLink message: the sensor's range as the autopilots configure it, and the message field's own
# range where it is smaller.  PX4 (HIGHRES_IMU, float fields) runs its IMUs at +-16 g and
# +-2000 deg/s; ArduPilot (RAW_IMU, SCALED_IMU*: int16 mG and mrad/s) sets its accelerometers to
# +-16 g, and the mrad/s field saturates at 32.767 rad/s (1877 deg/s) before a 2000-deg/s gyro does.
_G16 = 16.0 * STANDARD_GRAVITY_MPS2
_INT16_MRADPS = 32.767
FULL_SCALE_BY_MESSAGE: dict[str, ImuFullScale] = {
    "HIGHRES_IMU": ImuFullScale(_G16, math.radians(2000.0)),
    "RAW_IMU": ImuFullScale(_G16, _INT16_MRADPS),
    "SCALED_IMU": ImuFullScale(_G16, _INT16_MRADPS),
    "SCALED_IMU2": ImuFullScale(_G16, _INT16_MRADPS),
    "SCALED_IMU3": ImuFullScale(_G16, _INT16_MRADPS),
}
DEFAULT_FULL_SCALE = FULL_SCALE_BY_MESSAGE["HIGHRES_IMU"]


class ImuScreenCounter:
    """Stable counter keys (health report, field log, tests)."""

    ACCEL_CLIPPED = "imu_screen.accel_clipped"          # an axis at >= clip_fraction of full scale
    GYRO_CLIPPED = "imu_screen.gyro_clipped"
    ACCEL_IMPLAUSIBLE = "imu_screen.accel_implausible"  # jump from the running median
    GYRO_IMPLAUSIBLE = "imu_screen.gyro_implausible"
    BRIDGED = "imu_screen.samples_bridged"              # samples integrated with a held triad
    DROPPED_NO_GOOD_SAMPLE = "imu_screen.dropped_before_good_sample"


class ImuScreen:
    """Per-sample screen of one IMU stream.  :meth:`check` says whether a sample may be integrated
    as it is; when not, :attr:`dtheta_b` / :attr:`dv_b` hold the bridged increments and
    :attr:`var_dtheta_b` / :attr:`var_dv_b` the variances (rad^2, (m/s)^2 per body axis) to add."""

    def __init__(self, full_scale: ImuFullScale = DEFAULT_FULL_SCALE, *, clip_fraction: float = 0.98,
                 accel_jump_mps2: float = 60.0, gyro_jump_radps: float = 10.0, window: int = 9,
                 counters=None):
        self.clip_fraction = clip_fraction
        self.accel_jump_mps2 = accel_jump_mps2
        self.gyro_jump_radps = gyro_jump_radps
        self.set_full_scale(full_scale)
        self.counters = counters if counters is not None else {}
        for k in (v for n, v in vars(ImuScreenCounter).items() if not n.startswith("_")):
            self.counters.setdefault(k, 0)
        self._n = max(3, int(window))
        # ring buffers of the last n rates: gyro x,y,z then accel x,y,z
        self._win = [[0.0] * self._n for _ in range(6)]
        self._k = 0                     # samples seen
        self._prev = [0.0] * 6          # rates of the previous sample
        self._prev_ok = False           # previous sample passed both tests
        self._good: tuple | None = None   # last good rates: gyro (rad/s), specific force (m/s^2), body
        self.dtheta_b = [0.0, 0.0, 0.0]
        self.dv_b = [0.0, 0.0, 0.0]
        self.var_dtheta_b = [0.0, 0.0, 0.0]
        self.var_dv_b = [0.0, 0.0, 0.0]
        self.bridged = False            # the last rejected sample was bridged (else: drop it)
        self.last_reason = ""
        self._next_log_t = -math.inf

    def set_full_scale(self, fs: ImuFullScale) -> None:
        self.full_scale = fs
        self._clip_f = self.clip_fraction * fs.accel_mps2
        self._clip_w = self.clip_fraction * fs.gyro_radps

    # ------------------------------------------------------------------ the test
    def check(self, dtheta_b: list, dv_b: list, tau: float, t_gps: float = math.nan) -> bool:
        """True: integrate the sample as it is.  False: integrate :attr:`dtheta_b`/:attr:`dv_b`
        (bridged) and add the variances, or, if :attr:`bridged` is False (no good sample yet to
        hold), drop it."""
        r = (dtheta_b[0] / tau, dtheta_b[1] / tau, dtheta_b[2] / tau, dv_b[0] / tau, dv_b[1] / tau, dv_b[2] / tau)
        cw, cf = self._clip_w, self._clip_f
        clip_w = abs(r[0]) >= cw or abs(r[1]) >= cw or abs(r[2]) >= cw
        clip_f = abs(r[3]) >= cf or abs(r[4]) >= cf or abs(r[5]) >= cf
        bad_w, bad_f = clip_w, clip_f
        full = self._k >= self._n
        if full and not (bad_w and bad_f):
            jw, jf, p = self.gyro_jump_radps, self.accel_jump_mps2, self._prev
            quick = self._prev_ok and (abs(r[0] - p[0]) <= jw and abs(r[1] - p[1]) <= jw and abs(r[2] - p[2]) <= jw
                                       and abs(r[3] - p[3]) <= jf and abs(r[4] - p[4]) <= jf
                                       and abs(r[5] - p[5]) <= jf)
            if not quick:
                med = [sorted(col)[self._n // 2] for col in self._win]
                impl_w = not bad_w and any(abs(r[i] - med[i]) > jw for i in range(3))
                impl_f = not bad_f and any(abs(r[i] - med[i]) > jf for i in range(3, 6))
                bad_w, bad_f = bad_w or impl_w, bad_f or impl_f
            else:
                impl_w = impl_f = False
        else:
            impl_w = impl_f = False
        # every sample enters the window (a lasting real step is adopted, see the module docstring)
        j = self._k % self._n
        for i in range(6):
            self._win[i][j] = r[i]
        self._k += 1
        self._prev = r
        self._prev_ok = not (bad_w or bad_f)
        if self._prev_ok:
            self._good = r                # the tuple itself: nothing allocated per good sample
            return True
        c = self.counters
        if clip_w:
            c[ImuScreenCounter.GYRO_CLIPPED] += 1
        if clip_f:
            c[ImuScreenCounter.ACCEL_CLIPPED] += 1
        if impl_w:
            c[ImuScreenCounter.GYRO_IMPLAUSIBLE] += 1
        if impl_f:
            c[ImuScreenCounter.ACCEL_IMPLAUSIBLE] += 1
        self.last_reason = ", ".join(n for n, b in (("gyro clipped", clip_w), ("accel clipped", clip_f),
                                                    ("gyro implausible", impl_w), ("accel implausible", impl_f)) if b)
        if self._good is None:
            self.bridged = False
            c[ImuScreenCounter.DROPPED_NO_GOOD_SAMPLE] += 1
            return False
        self.bridged = True
        c[ImuScreenCounter.BRIDGED] += 1
        self._bridge(r, tau, bad_w, bad_f)
        if not t_gps < self._next_log_t:         # rate-limited by data time (replay logs the same)
            self._next_log_t = t_gps + 10.0
            log.warning("IMU sample rejected (%s): bridged with the last good one; %d so far",
                        self.last_reason, c[ImuScreenCounter.BRIDGED])
        return False

    def _bridge(self, r, tau: float, bad_w: bool, bad_f: bool) -> None:
        g = self._good
        for i in range(3):
            if bad_w:
                self.dtheta_b[i] = g[i] * tau
                s = min(abs(r[i] - g[i]), self.gyro_jump_radps) * tau
                self.var_dtheta_b[i] = s * s
            else:
                self.dtheta_b[i] = r[i] * tau
                self.var_dtheta_b[i] = 0.0
            if bad_f:
                self.dv_b[i] = g[3 + i] * tau
                s = min(abs(r[3 + i] - g[3 + i]), self.accel_jump_mps2) * tau
                self.var_dv_b[i] = s * s
            else:
                self.dv_b[i] = r[3 + i] * tau
                self.var_dv_b[i] = 0.0
