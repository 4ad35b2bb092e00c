"""Heading from motion when nobody knows it: a Gaussian-sum yaw estimator (after the EKF-GSF of
ArduPilot EKF3 / PX4 ekf2, own implementation).

A single EKF cannot start from an unknown heading: linearised about a heading 180 deg off it
settles somewhere wrong.  A *bank* of ``n_models`` small filters, each started from a different
heading (0, 72, 144, 216, 288 deg for five), can: the model whose heading is right predicts the
GNSS velocity from the accelerometer best, and Bayes' rule moves the weight onto it.

Each model
  * has an AHRS: the body-to-NED rotation, integrated from the gyro and pulled towards the
    accelerometer's gravity direction (tilt only).  The models' AHRSs differ by a rotation about
    the vertical only, and both the gyro integration (right-multiplied) and the tilt correction (a
    nav-frame rotation about a horizontal axis, computed from the accelerometer alone) commute
    with a rotation about down; so they are carried exactly as one shared AHRS ``C_b_n`` and a
    yaw offset per model;
  * runs a 3-state EKF ``[v_north, v_east, yaw]``, predicted with its own rotated delta velocity
    (no assumption about the direction of motion: a multirotor moving sideways, a car, a fixed
    wing or a person carrying the unit all work) and updated with the GNSS horizontal velocity;
  * has a weight, multiplied by the Gaussian likelihood of every velocity innovation.

The composite yaw is the weighted circular mean, its variance the weighted model variances plus
the spread of the models about the mean (so an undecided bank says so).

The accelerometer is a gravity reference only when the vehicle does not accelerate: the tilt
correction is faded out when the specific force is far from 1 g and when the GNSS velocity shows
a horizontal acceleration (measured over a second or more, without any heading); a turning
multirotor or a braking car then holds its tilt on the gyro.

Frames: local NED at the vehicle (earth rate and transport rate ignored: 0.004 deg/s over the
half a minute a convergence takes).  Units SI; angles in rad.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from .earth import euler_to_dcm

G0_MPS2 = 9.80665


@dataclass(frozen=True)
class YawGsfConfig:
    n_models: int = 5
    step_s: float = 0.02                    # IMU increments are summed to about this before the bank runs
    tilt_gain_per_s: float = 0.2            # AHRS tilt correction rate (time constant 5 s), as EKF-GSF
    gyro_bias_gain_per_s: float = 0.04      # AHRS gyro bias learning (tilt axes only), as EKF-GSF
    gyro_bias_limit_radps: float = 0.05
    accel_lowpass_s: float = 0.5            # accelerometer low-pass for the tilt reference (vibration)
    accel_norm_tolerance: float = 0.2       # tilt correction off when |f| is 20 % off 1 g
    kinematic_accel_limit_mps2: float = 0.5   # ... and when GNSS shows this much horizontal acceleration
    # velocity prediction noise (white, PSD): tilt error x g, accelerometer bias, vibration; the
    # EKF-GSF's 2 m/s^2 per 10-ms step is 0.04 m^2/s^3
    accel_noise_psd_m2ps3: float = 0.15
    # yaw random walk: the unestimated vertical gyro bias (0.25 deg/s turn-on on a MEMS flight
    # controller is 7.5 deg in 30 s, i.e. a random walk of 1.4 deg/sqrt(s) over that time)
    yaw_noise_psd_rad2ps: float = math.radians(1.4) ** 2
    innovation_limit_sigma: float = 5.0     # larger innovations move a model's state as if this large
    log_weight_floor: float = math.log(1e-5)  # a model's weight never falls below this (it can come back)
    velocity_gap_s: float = 3.0             # no GNSS velocity for this long: the models' velocities restart
    # converged: yaw 1-sigma below this after at least min_moving_fusions fusions at speed, and the
    # yaw observed (a fusion that shrank its variance by observed_fraction) in the last observed_within_s:
    # in steady straight motion the yaw is unobservable and integrated from the gyro alone, which
    # may be faulty (a 3 deg/s rate error is invisible to the screen), so it neither initialises
    # nor overrules a heading then
    converged_sigma_rad: float = math.radians(10.0)
    min_moving_fusions: int = 2             # 3 made the first-motion gate 0.44-0.60 s on PX4 SIH (5 Hz): EKF2
                                            # calls vision intermittent beyond 0.4 s; 2: 0.24-0.40 s
    observed_fraction: float = 0.01
    observed_within_s: float = 5.0
    moving_speed_mps: float = 0.5
    # in motion (heading matters) is judged on the speed the INS may have reached since the last
    # GNSS velocity (see in_motion), not on the specific force itself: a hover's wobble and PX4
    # SIH's IMU noise (1.2 m/s^2 per 125-Hz sample) exceed any useful acceleration threshold
    # (0.3 m/s^2 flapped 164 times in 20 s at rest; 5 sigma of the measured scatter still took a
    # vertical take-off for motion and withheld 1.3 s of output, EKF2 lost our position) while
    # their velocity change between two GNSS velocities stays centimetres per second
    motion_start_dv_mps: float = 0.25       # half of moving_speed_mps: a start from rest shows before the speed does
    # a complementary filter carries no covariance: the 1-sigma tilt error stated for it (MEMS IMU,
    # 5-s correction time constant; the tests measure < 1 deg on a multirotor and a car)
    tilt_sigma_rad: float = math.radians(2.0)


def _wrap(a):
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _rotation_from_vector(x: float, y: float, z: float) -> tuple:
    """Rotation matrix of the rotation vector (x, y, z) (Rodrigues), row-major 9-tuple of floats.
    Scalar arithmetic: at the bank's 50 Hz, 3x3 numpy operations cost several times the flops."""
    th2 = x * x + y * y + z * z
    if th2 < 1e-18:
        a, b = 1.0, 0.0
    else:
        th = math.sqrt(th2)
        a, b = math.sin(th) / th, (1.0 - math.cos(th)) / th2
    # I + a K + b K^2, K = [[0, -z, y], [z, 0, -x], [-y, x, 0]]
    return (1.0 - b * (y * y + z * z), -a * z + b * x * y, a * y + b * x * z,
            a * z + b * x * y, 1.0 - b * (x * x + z * z), -a * x + b * y * z,
            -a * y + b * x * z, a * x + b * y * z, 1.0 - b * (x * x + y * y))


def _mul3(A: tuple, B: tuple) -> tuple:
    """A @ B of row-major 9-tuples."""
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = A
    b0, b1, b2, b3, b4, b5, b6, b7, b8 = B
    return (a0 * b0 + a1 * b3 + a2 * b6, a0 * b1 + a1 * b4 + a2 * b7, a0 * b2 + a1 * b5 + a2 * b8,
            a3 * b0 + a4 * b3 + a5 * b6, a3 * b1 + a4 * b4 + a5 * b7, a3 * b2 + a4 * b5 + a5 * b8,
            a6 * b0 + a7 * b3 + a8 * b6, a6 * b1 + a7 * b4 + a8 * b7, a6 * b2 + a7 * b5 + a8 * b8)


def _orthonormalise(C: np.ndarray) -> np.ndarray:
    u, _, vt = np.linalg.svd(C)
    return u @ vt


class YawGsf:
    """Feed :meth:`update_imu` with every (screened) IMU sample and :meth:`fuse_velocity` with every
    GNSS velocity; read :attr:`yaw_rad`, :attr:`yaw_var_rad2`, :attr:`converged`, :attr:`roll_rad`,
    :attr:`pitch_rad`."""

    def __init__(self, config: YawGsfConfig = YawGsfConfig()):
        self.cfg = config
        self.reset()

    def reset(self) -> None:
        n = self.cfg.n_models
        self.aligned = False                 # AHRS tilt aligned to the accelerometer
        self.C_b_n = np.eye(3)               # the shared AHRS (model 0's yaw = its yaw)
        self.b_g = np.zeros(3)               # AHRS gyro bias (body, rad/s)
        self.f_lp_b = np.zeros(3)            # low-passed specific force (body)
        self.x = np.zeros((n, 3))            # per model: v_north, v_east (m/s), yaw (rad)
        self.P = np.zeros((n, 3, 3))
        self.log_w = np.full(n, -math.log(n))
        self.vel_initialised = False
        self.n_fusions = 0
        self.n_moving_fusions = 0
        self.gap_restarts = 0                # bank restarts after a gap in the GNSS velocities
        self.t_last_vel = -math.inf
        self.moving = False                  # the last GNSS velocity showed horizontal motion
        self.t_yaw_observed = -math.inf      # last fusion that shrank the yaw variance
        self.dv_since_velocity_n = np.zeros(2)   # horizontal delta velocity since the last GNSS velocity, AHRS level frame
        self._v_hist: deque = deque(maxlen=64)   # (t, v_n, v_e) of the GNSS velocities
        self.kinematic_accel_mps2 = 0.0
        self._acc = [0.0] * 7                # summed dtheta (3), dv (3), dt: plain floats at IMU rate
        self._yaw_cache: tuple[float, float] | None = None
        self._n_steps = 0
        self.omega_b_radps = np.zeros(3)
        self.t_gps = math.nan

    def _restart_bank(self) -> None:
        """The models spread over the circle again (model 0 on the AHRS's yaw), equal weights,
        velocities to be re-initialised by the next GNSS velocity; the AHRS keeps its tilt."""
        n = self.cfg.n_models
        self._yaw_cache = None
        yaw0 = math.atan2(self.C_b_n[1, 0], self.C_b_n[0, 0])
        self.x[:] = 0.0
        self.x[:, 2] = _wrap(yaw0 + np.arange(n) * (2.0 * math.pi / n))
        self.P[:] = 0.0
        self.P[:, 2, 2] = (math.pi / n) ** 2
        self.log_w[:] = -math.log(n)
        self.vel_initialised = False
        self.n_moving_fusions = 0
        self.t_yaw_observed = -math.inf

    # ------------------------------------------------------------------ IMU
    def update_imu(self, dtheta_b, dv_b, dt_s: float, t_gps: float = math.nan) -> None:
        """One IMU sample: delta angle (rad) and delta velocity (m/s, specific force) over ``dt_s``."""
        if not (0.0 < dt_s < 0.5):
            return
        self.t_gps = t_gps
        w0, w1, w2 = float(dtheta_b[0]), float(dtheta_b[1]), float(dtheta_b[2])
        v0, v1, v2 = float(dv_b[0]), float(dv_b[1]), float(dv_b[2])
        a = self._acc
        # sum to the bank's step; the delta velocity in the body frame at the start of the step
        # (turned by the rotation so far: dv + theta x dv)
        a[3] += v0 + a[1] * v2 - a[2] * v1
        a[4] += v1 + a[2] * v0 - a[0] * v2
        a[5] += v2 + a[0] * v1 - a[1] * v0
        a[0] += w0
        a[1] += w1
        a[2] += w2
        a[6] += dt_s
        if a[6] < self.cfg.step_s * (1.0 - 1e-6):
            return
        dth, dv, dt = a[0:3], a[3:6], a[6]
        self._acc = [0.0] * 7
        self.omega_b_radps = np.array(dth) / dt
        self._step(dth, dv, dt)

    def _step(self, dth: list, dv: list, dt: float) -> None:
        """One bank step over ``dt``: summed delta angle ``dth`` and delta velocity ``dv`` (body,
        plain floats).  The AHRS part is scalar arithmetic (see :func:`_rotation_from_vector`)."""
        cfg = self.cfg
        self._yaw_cache = None
        fx, fy, fz = dv[0] / dt, dv[1] / dt, dv[2] / dt
        if not self.aligned:
            # level the AHRS on the accelerometer when it is near 1 g (not thrown about)
            if abs(math.sqrt(fx * fx + fy * fy + fz * fz) / G0_MPS2 - 1.0) < 0.1:
                roll = math.atan2(-fy, -fz)
                pitch = math.atan2(fx, math.hypot(fy, fz))
                self.C_b_n = euler_to_dcm(roll, pitch, 0.0)
                self.f_lp_b = np.array([fx, fy, fz])
                n = cfg.n_models
                self.x[:, 2] = np.arange(n) * (2.0 * math.pi / n)
                self.P[:] = 0.0
                self.P[:, 2, 2] = (math.pi / n) ** 2
                self.aligned = True
            return
        a = dt / (cfg.accel_lowpass_s + dt)
        lx, ly, lz = self.f_lp_b.tolist()
        lx += a * (fx - lx)
        ly += a * (fy - ly)
        lz += a * (fz - lz)
        self.f_lp_b = np.array([lx, ly, lz])
        C0 = tuple(self.C_b_n.ravel().tolist())
        c0, c1, c2, c3, c4, c5, c6, c7, c8 = C0
        yaw0 = math.atan2(c3, c0)
        # tilt correction: rotate the nav frame so that the measured specific force points up
        nx, ny, nz = c0 * lx + c1 * ly + c2 * lz, c3 * lx + c4 * ly + c5 * lz, c6 * lx + c7 * ly + c8 * lz
        norm = math.sqrt(nx * nx + ny * ny + nz * nz)
        w = max(0.0, 1.0 - abs(norm / G0_MPS2 - 1.0) / cfg.accel_norm_tolerance)
        w *= max(0.0, 1.0 - self.kinematic_accel_mps2 / cfg.kinematic_accel_limit_mps2)
        if math.isfinite(self.t_last_vel) and self.t_gps - self.t_last_vel > cfg.velocity_gap_s:
            # GNSS velocity lost (none yet: levelling at rest, as at the alignment): the acceleration is unknown and |f| near 1 g does not mean level
            # (3 m/s^2 along a leg is 17 deg of 'tilt' at 5 % off 1 g): the gyro alone holds the tilt
            w = 0.0
        kx = ky = 0.0
        bx, by, bz = self.b_g.tolist()
        if w > 0.0 and norm > 0.0:
            ex, ey = -ny / norm, nx / norm                 # u x (0, 0, -1): horizontal axis, |.| = sin(tilt error)
            kx, ky = cfg.tilt_gain_per_s * w * ex, cfg.tilt_gain_per_s * w * ey
            g = cfg.gyro_bias_gain_per_s * w * dt          # b_g -= g C0^T err_n, clipped
            lim = cfg.gyro_bias_limit_radps
            bx = min(lim, max(-lim, bx - g * (c0 * ex + c3 * ey)))
            by = min(lim, max(-lim, by - g * (c1 * ex + c4 * ey)))
            bz = min(lim, max(-lim, bz - g * (c2 * ex + c5 * ey)))
            self.b_g = np.array([bx, by, bz])
        C1 = _mul3(_mul3(_rotation_from_vector(kx * dt, ky * dt, 0.0), C0),
                   _rotation_from_vector(dth[0] - bx * dt, dth[1] - by * dt, dth[2] - bz * dt))
        self._n_steps += 1
        C1m = np.array(C1).reshape(3, 3)
        self.C_b_n = _orthonormalise(C1m) if self._n_steps % 50 == 0 else C1m
        d_yaw = _wrap(math.atan2(self.C_b_n[1, 0], self.C_b_n[0, 0]) - yaw0)
        if not self.vel_initialised:
            self.x[:, 2] = _wrap(self.x[:, 2] + d_yaw)
            self.P[:, 2, 2] += cfg.yaw_noise_psd_rad2ps * dt
            return
        # each model's delta velocity: the shared one turned by the model's yaw offset
        dv_n0 = c0 * dv[0] + c1 * dv[1] + c2 * dv[2]
        dv_n1 = c3 * dv[0] + c4 * dv[1] + c5 * dv[2]
        d = self.dv_since_velocity_n
        d[0] += dv_n0
        d[1] += dv_n1
        c = self.x[:, 2] - yaw0
        cs, sn = np.cos(c), np.sin(c)
        dvn = cs * dv_n0 - sn * dv_n1
        dve = sn * dv_n0 + cs * dv_n1
        self.x[:, 0] += dvn
        self.x[:, 1] += dve
        self.x[:, 2] = _wrap(self.x[:, 2] + d_yaw)
        # F = [[1, 0, -dve], [0, 1, dvn], [0, 0, 1]]: P <- F P F^T + Q, written out per model
        P = self.P
        p02, p12, p22 = P[:, 0, 2].copy(), P[:, 1, 2].copy(), P[:, 2, 2].copy()
        P[:, 0, 0] += -2.0 * dve * p02 + dve * dve * p22
        P[:, 1, 1] += 2.0 * dvn * p12 + dvn * dvn * p22
        P[:, 0, 1] += -dve * p12 + dvn * p02 - dve * dvn * p22
        P[:, 1, 0] = P[:, 0, 1]
        P[:, 0, 2] = p02 - dve * p22
        P[:, 2, 0] = P[:, 0, 2]
        P[:, 1, 2] = p12 + dvn * p22
        P[:, 2, 1] = P[:, 1, 2]
        q_v = cfg.accel_noise_psd_m2ps3 * dt
        P[:, 0, 0] += q_v
        P[:, 1, 1] += q_v
        P[:, 2, 2] += cfg.yaw_noise_psd_rad2ps * dt

    # ------------------------------------------------------------------ GNSS
    def fuse_velocity(self, t_gps: float, v_ne_mps, sigma_mps: float) -> bool:
        """GNSS horizontal velocity (north, east; m/s) with its 1-sigma per axis.  Returns True
        when it was fused (not before the AHRS is levelled)."""
        v = np.asarray(v_ne_mps, float)[:2]
        if not (self.aligned and np.all(np.isfinite(v)) and math.isfinite(sigma_mps) and sigma_mps > 0.0):
            return False
        cfg = self.cfg
        self._yaw_cache = None
        self.dv_since_velocity_n[:] = 0.0
        self._update_kinematic_accel(t_gps, v, sigma_mps)
        r = sigma_mps ** 2
        if self.vel_initialised and t_gps - self.t_last_vel > cfg.velocity_gap_s:
            # without GNSS velocity the AHRS cannot tell acceleration from tilt: its tilt, and the
            # yaw through it, wander in every turn (30 deg in a 60-s outage of the survey flight, and
            # a converged-looking bank then reset a good heading onto 157 deg off).  Start the bank
            # over: it must converge again before it vouches for or overrules a heading
            self._restart_bank()
            self.gap_restarts += 1
        if not self.vel_initialised:
            self.x[:, 0:2] = v
            self.P[:, 0:2, :] = 0.0
            self.P[:, :, 0:2] = 0.0
            self.P[:, 0, 0] = self.P[:, 1, 1] = r
            self.vel_initialised = True
            self.t_last_vel = t_gps
            return True
        self.t_last_vel = t_gps
        var_before = self.yaw_var_rad2
        P = self.P
        nu = v[None, :] - self.x[:, 0:2]                       # (n, 2)
        s00, s01, s11 = P[:, 0, 0] + r, P[:, 0, 1], P[:, 1, 1] + r
        det = s00 * s11 - s01 * s01
        i00, i01, i11 = s11 / det, -s01 / det, s00 / det       # S^-1
        nis = nu[:, 0] ** 2 * i00 + 2.0 * nu[:, 0] * nu[:, 1] * i01 + nu[:, 1] ** 2 * i11
        # likelihood with the full innovation; the state moves as if it were at most k sigma
        ll = -0.5 * nis - 0.5 * np.log(det)
        lim = cfg.innovation_limit_sigma ** 2
        scale = np.where(nis > lim, np.sqrt(lim / np.maximum(nis, 1e-30)), 1.0)
        nu_s = nu * scale[:, None]
        # K = P[:, :, :2] S^-1  (n, 3, 2)
        Pc = P[:, :, 0:2]
        K = np.empty((len(nu), 3, 2))
        K[:, :, 0] = Pc[:, :, 0] * i00[:, None] + Pc[:, :, 1] * i01[:, None]
        K[:, :, 1] = Pc[:, :, 0] * i01[:, None] + Pc[:, :, 1] * i11[:, None]
        self.x += np.einsum("nij,nj->ni", K, nu_s)
        self.x[:, 2] = _wrap(self.x[:, 2])
        self.P = P - np.einsum("nij,nkj->nik", K, Pc)          # (I - K H) P, H = [I2 0]
        self.P = 0.5 * (self.P + np.transpose(self.P, (0, 2, 1)))
        lw = self.log_w + ll
        lw -= lw.max()
        lw -= math.log(float(np.exp(lw).sum()))
        self.log_w = np.maximum(lw, cfg.log_weight_floor)
        self.log_w -= math.log(float(np.exp(self.log_w).sum()))
        self._yaw_cache = None
        self.n_fusions += 1
        if self.yaw_var_rad2 < (1.0 - cfg.observed_fraction) * var_before:
            self.t_yaw_observed = t_gps
        self.moving = math.hypot(v[0], v[1]) > max(cfg.moving_speed_mps, 3.0 * sigma_mps)
        if self.moving:
            self.n_moving_fusions += 1
        return True

    def _update_kinematic_accel(self, t_gps: float, v: np.ndarray, sigma_mps: float) -> None:
        """Horizontal acceleration from the GNSS velocity over at least a second (heading-free).
        Its noise (sqrt(2) sigma / span) is left in: noise only slows the tilt correction down,
        while an acceleration taken for noise would pull the tilt off."""
        h = self._v_hist
        h.append((t_gps, float(v[0]), float(v[1])))
        while len(h) > 2 and t_gps - h[1][0] >= 1.0:
            h.popleft()
        t0, vn0, ve0 = h[0]
        span = t_gps - t0
        if not (0.5 <= span <= 3.0):
            self.kinematic_accel_mps2 = 0.0 if span > 3.0 else self.kinematic_accel_mps2
            return
        self.kinematic_accel_mps2 = math.hypot(v[0] - vn0, v[1] - ve0) / span

    # ------------------------------------------------------------------ output
    @property
    def weights(self) -> np.ndarray:
        return np.exp(self.log_w)

    def _composite(self) -> tuple[float, float]:
        """(yaw, variance) of the bank, computed once per change of the models: the injection gate
        asks for them several times per solution.  Every method that changes ``x``, ``P`` or
        ``log_w`` clears the cache (``self._yaw_cache = None``)."""
        c = self._yaw_cache
        if c is None:
            w = np.exp(self.log_w)
            yaw = self.x[:, 2]
            mean = math.atan2(float(w @ np.sin(yaw)), float(w @ np.cos(yaw)))
            d = _wrap(yaw - mean)
            var = float(w @ (self.P[:, 2, 2] + d * d)) if self.aligned else math.pi ** 2
            c = self._yaw_cache = (mean, var)
        return c

    @property
    def yaw_rad(self) -> float:
        return self._composite()[0]

    @property
    def yaw_var_rad2(self) -> float:
        return self._composite()[1]

    @property
    def yaw_sigma_rad(self) -> float:
        return math.sqrt(self.yaw_var_rad2)

    @property
    def settled(self) -> bool:
        """Yaw sigma below the limit after enough fusions in motion (possibly not observed lately)."""
        cfg = self.cfg
        return (self.aligned and self.vel_initialised and self.n_moving_fusions >= cfg.min_moving_fusions
                and self.yaw_var_rad2 < cfg.converged_sigma_rad ** 2)

    @property
    def converged(self) -> bool:
        """Settled, and the yaw observed in the last ``observed_within_s``."""
        return self.settled and self.t_last_vel - self.t_yaw_observed <= self.cfg.observed_within_s

    @property
    def dv_since_velocity_mps(self) -> float:
        """|horizontal delta velocity| the IMU measured since the last GNSS velocity (any heading)."""
        d = self.dv_since_velocity_n
        return math.hypot(float(d[0]), float(d[1]))

    @property
    def in_motion(self) -> bool:
        """Moving horizontally, or starting to: the IMU measured a horizontal velocity change of
        ``motion_start_dv_mps`` since the last GNSS velocity (seen at IMU rate, before a 1-Hz GNSS
        velocity shows the speed).  A wrong heading now corrupts an INS."""
        return self.moving or (self.vel_initialised and self.dv_since_velocity_mps > self.cfg.motion_start_dv_mps)

    @property
    def roll_rad(self) -> float:
        C = self.C_b_n
        return math.atan2(C[2, 1], C[2, 2])

    @property
    def pitch_rad(self) -> float:
        return -math.asin(max(-1.0, min(1.0, float(self.C_b_n[2, 0]))))

    @property
    def tilt_sigma_rad(self) -> float:
        return self.cfg.tilt_sigma_rad

    def C_b_n_estimate(self) -> np.ndarray:
        """Body-to-NED rotation with the composite yaw (a yaw turn leaves roll and pitch alone)."""
        return euler_to_dcm(self.roll_rad, self.pitch_rad, self.yaw_rad)

    def snapshot(self) -> dict:
        return {"aligned": self.aligned, "converged": self.converged, "settled": self.settled,
                "yaw_deg": round(math.degrees(self.yaw_rad), 2),
                "yaw_sigma_deg": round(math.degrees(self.yaw_sigma_rad), 2),
                "velocity_fusions": self.n_fusions, "moving_fusions": self.n_moving_fusions,
                "gap_restarts": self.gap_restarts,
                "weights": [round(float(x), 4) for x in self.weights]}


__all__ = ["YawGsf", "YawGsfConfig"]
