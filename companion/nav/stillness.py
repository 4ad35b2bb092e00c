"""Stillness from the raw IMU: the standard deviation of the rates over a window, for the
zero-velocity and zero-rotation updates (companion.nav.engine)."""
from __future__ import annotations

import math
from collections import deque

import numpy as np


class StillnessDetector:
    """Stillness test on the last ``zupt_window_s`` of raw IMU rates.

    Samples are appended to a bounded deque (no numpy at IMU rate); the window statistics are
    computed with numpy every half window only.
    """

    def __init__(self, window_s: float, gyro_std_radps: float, accel_std_mps2: float):
        self.window_s = window_s
        self.gyro_std_radps, self.accel_std_mps2 = gyro_std_radps, accel_std_mps2
        self.buf: deque = deque(maxlen=2)   # resized to one window of samples at the IMU's rate
        self._since_check_s = 0.0
        self._since_update_s = 0.0
        self._window: np.ndarray | None = None

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
        """The test on one full window (rows: raw dtheta 3, dv 3, tau; oldest first), shared with
        the compiled path's ring (companion.nav.imu_fused)."""
        rates = w[:, 0:6] / w[:, 6:7]
        std = rates.std(axis=0)
        return self.decide(float(std[0:3].max()), float(std[3:6].max()), lambda: rates)

    def decide(self, gyro_std_max: float, accel_std_max: float, window_rates) -> bool:
        """The test on a window's statistics: the largest standard deviation of the gyro axes'
        rates and of the accelerometer axes'.  ``window_rates()`` gives the window's rates (rows:
        gyro 3, accel 3), asked for only when the window is still and an update is due."""
        still = gyro_std_max < self.gyro_std_radps and accel_std_max < self.accel_std_mps2
        if still and self._since_update_s >= self.window_s:
            self._since_update_s = 0.0
            self._window = window_rates()
            return True
        return False

    def gyro_mean_and_sigma(self):
        """Mean raw gyro rate over the still window and the standard error of that mean."""
        w = self._window
        mean = w[:, 0:3].mean(axis=0)
        return mean, float(w[:, 0:3].std(axis=0).max() / math.sqrt(len(w)))
