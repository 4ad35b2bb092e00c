"""Stillness from the raw IMU: the standard deviation of the rates over a window, for the
zero-velocity and zero-rotation updates (companion.nav.engine)."""
from __future__ import annotations

import math
from collections import deque

import numpy as np


class StillnessDetector:
    """Stillness test on the last ``zupt_window_s`` of raw IMU rates.

    Samples are appended to a bounded deque (no numpy at IMU rate); the window statistics are
    computed with numpy every half window only (the engine's compiled path keeps its own ring and
    computes them in companion.nav.imu_fused.still_window_std: both end in :meth:`decide`).
    """

    def __init__(self, window_s: float, gyro_std_radps: float, accel_std_mps2: float):
        self.window_s = window_s
        self.gyro_std_radps, self.accel_std_mps2 = gyro_std_radps, accel_std_mps2
        self.buf: deque = deque(maxlen=2)   # resized to one window of samples at the IMU's rate
        self._since_check_s = 0.0
        self._since_update_s = 0.0
        self._gyro_mean = np.zeros(3)          # the last still window's (gyro_mean_and_sigma)
        self._gyro_sigma_of_mean = math.inf

    def add(self, dtheta, dv, tau: float) -> bool:
        """Add one sample (raw increments); True when the last window is still and an update is due."""
        self.buf.append((dtheta[0], dtheta[1], dtheta[2], dv[0], dv[1], dv[2], tau))
        self._since_check_s += tau
        self._since_update_s += tau
        if self._since_check_s < 0.5 * self.window_s:
            return False
        self._since_check_s = 0.0
        m = self.window_samples(tau)
        if self.buf.maxlen != m:
            self.buf = deque(self.buf, maxlen=m)
        if len(self.buf) < m:
            return False
        return self.evaluate(np.array(self.buf))

    def window_samples(self, tau: float) -> int:
        """One window at the current IMU rate."""
        return max(2, int(round(self.window_s / tau)))

    def evaluate(self, w: np.ndarray) -> bool:
        """The test on one full window (rows: raw dtheta 3, dv 3, tau; oldest first): its statistics
        in numpy, then :meth:`decide` (the compiled path computes the same numbers on its ring)."""
        rates = w[:, 0:6] / w[:, 6:7]
        std = rates.std(axis=0)
        return self.decide(float(std[0:3].max()), float(std[3:6].max()), rates[:, 0:3].mean(axis=0), len(w))

    def decide(self, gyro_std_max: float, accel_std_max: float, gyro_mean, n: int) -> bool:
        """The test on a window's statistics (``n`` samples): the largest standard deviation of the
        gyro axes' rates and of the accelerometer axes', the gyro axes' mean rates (kept for
        :meth:`gyro_mean_and_sigma` when the window is still and an update is due)."""
        still = gyro_std_max < self.gyro_std_radps and accel_std_max < self.accel_std_mps2
        if still and self._since_update_s >= self.window_s:
            self._since_update_s = 0.0
            self._gyro_mean = np.array(gyro_mean, dtype=float)
            self._gyro_sigma_of_mean = gyro_std_max / math.sqrt(n)
            return True
        return False

    def gyro_mean_and_sigma(self):
        """Mean raw gyro rate over the last still window and the standard error of that mean."""
        return self._gyro_mean.copy(), self._gyro_sigma_of_mean
