"""IMU increments along a recorded track: a real GNSS data set without an IMU can still drive the
tightly coupled engine, with the IMU synthesised from the vehicle's own (post-processed) positions.

The positions go through a C2 cubic spline (ECEF), the velocity is its derivative, the attitude a
car's (body x along the horizontal velocity, pitch along its slope, no roll; held while stopped,
smoothed over 1 s so the gyros see no steps), and the increments are the exact inverse of the
mechanization (:func:`companion.nav.strapdown.invert_step`) between successive samples, so the
INS follows the spline to rounding, plus white noise."""
from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import CubicSpline

from companion.messages import ImuSample
from companion.nav.earth import C_n_e, ecef_to_geodetic
from companion.nav.strapdown import invert_step


def _dcm(roll: float, pitch: float, yaw: float) -> np.ndarray:
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch),
                              math.cos(yaw), math.sin(yaw))
    return np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                     [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                     [-sp, sr * cp, cr * cp]])


def _smoothed(x: np.ndarray, n: int) -> np.ndarray:
    pad = np.pad(x, (n // 2, n - 1 - n // 2), mode="edge")
    return np.convolve(pad, np.ones(n) / n, mode="valid")


def car_imu(t_gps, r_e, rate_hz: float = 200.0, *, gyro_noise: float = 1e-4, accel_noise: float = 1e-3,
            seed: int = 1):
    """(t, r_e, v_e, C_b_e at rate_hz; [ImuSample]) along the track ``t_gps`` (s), ``r_e`` (n x 3,
    m).  Noise: white, ``gyro_noise`` rad/sqrt(s) and ``accel_noise`` m/s/sqrt(s)."""
    t_gps, r_e = np.asarray(t_gps, float), np.asarray(r_e, float)
    spline = CubicSpline(t_gps, r_e, axis=0)
    tau = 1.0 / rate_hz
    n = int(round((t_gps[-1] - t_gps[0]) * rate_hz)) + 1
    t = t_gps[0] + np.arange(n) * tau
    v = spline(t, 1)
    lat, lon, _ = ecef_to_geodetic(r_e[0])
    C_ne = C_n_e(lat, lon)
    v_n = v @ C_ne
    speed_h = np.hypot(v_n[:, 0], v_n[:, 1])
    yaw, pitch = np.zeros(n), np.zeros(n)
    last = math.atan2(v_n[0, 1], v_n[0, 0])
    for i in range(n):
        if speed_h[i] > 0.5:
            last = math.atan2(v_n[i, 1], v_n[i, 0])
            pitch[i] = math.atan2(-v_n[i, 2], speed_h[i])
        yaw[i] = last
    m = int(rate_hz)
    yaw, pitch = _smoothed(np.unwrap(yaw), m), _smoothed(pitch, m)
    C_b_e = np.array([C_ne @ _dcm(0.0, pitch[i], yaw[i]) for i in range(n)])
    r = np.empty((n, 3))
    r[0] = spline(t[0])
    for i in range(n - 1):                  # the mechanization's trapezoid rule
        r[i + 1] = r[i] + 0.5 * tau * (v[i] + v[i + 1])
    rng = np.random.default_rng(seed)
    imu = []
    for i in range(n - 1):
        dth, dv = invert_step(r[i], v[i], C_b_e[i], v[i + 1], C_b_e[i + 1], tau)
        imu.append(ImuSample(t[i + 1], tau, dth + rng.normal(0, gyro_noise * math.sqrt(tau), 3),
                             dv + rng.normal(0, accel_noise * math.sqrt(tau), 3)))
    return t, r, v, C_b_e, imu
