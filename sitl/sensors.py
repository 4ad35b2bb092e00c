"""Random processes and sensor error models for the simulator (all seeded by the caller's rng).

* :func:`gm2_unit_grid` -- critically damped 2nd-order Gauss-Markov, unit variance, exact
  discretisation on a uniform grid, started stationary; :class:`SmoothProcess` evaluates it (and
  its rate) anywhere by cubic spline.
* :func:`gm1` -- 1st-order Gauss-Markov on a uniform grid, started stationary (exact).
* :func:`clock_process` -- steered TCXO receiver clock (bias m, drift m/s).
* :func:`imu_errors` -- per-interval gyro/accel rate errors (bias + instability + white noise).
"""
from __future__ import annotations

import math

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.linalg import expm, solve_continuous_lyapunov
from scipy.signal import lfilter


def _discretize(F: np.ndarray, Q: np.ndarray, dt: float):
    """Van Loan: (Phi, Qd) of x' = F x + w, E[w w^T] = Q delta."""
    n = F.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n] = -F
    M[:n, n:] = Q
    M[n:, n:] = F.T
    E = expm(M * dt)
    phi = E[n:, n:].T
    qd = phi @ E[:n, n:]
    return phi, 0.5 * (qd + qd.T)


def _simulate_linear(rng, F, Q, dt, n_steps, n_series):
    """n_series independent realisations of a stationary linear SDE at n_steps grid points.
    Returns (n_steps, n_series, dim)."""
    dim = F.shape[0]
    P0 = solve_continuous_lyapunov(F, -Q)
    phi, qd = _discretize(F, Q, dt)
    L0 = np.linalg.cholesky(0.5 * (P0 + P0.T) + 1e-300 * np.eye(dim))
    Ld = np.linalg.cholesky(qd + 1e-30 * np.eye(dim))
    x = np.empty((n_steps, n_series, dim))
    x[0] = rng.standard_normal((n_series, dim)) @ L0.T
    w = rng.standard_normal((n_steps - 1, n_series, dim)) @ Ld.T
    for k in range(1, n_steps):
        x[k] = x[k - 1] @ phi.T + w[k - 1]
    return x


def gm2_unit_grid(rng, n_steps: int, dt: float, tau_s: float, n_series: int = 1) -> np.ndarray:
    """Unit-variance critically damped GM2 x'' + 2x'/tau + x/tau^2 = w on a grid, (n_steps, n_series).
    Stationary std of x is 1 and of x' is 1/tau (white-noise PSD q = 4/tau^3)."""
    w0 = 1.0 / tau_s
    F = np.array([[0.0, 1.0], [-w0 * w0, -2.0 * w0]])
    Q = np.array([[0.0, 0.0], [0.0, 4.0 * w0 ** 3]])
    return _simulate_linear(rng, F, Q, dt, n_steps, n_series)[:, :, 0]


class SmoothProcess:
    """A set of smooth scalar processes sampled on a uniform grid, evaluated by cubic spline."""

    def __init__(self, t_grid: np.ndarray, values: np.ndarray):
        self._spline = CubicSpline(t_grid, values, axis=0)
        self._rate = self._spline.derivative()

    def value(self, t):
        return self._spline(t)

    def rate(self, t):
        return self._rate(t)


def smooth_processes(rng, t_start: float, t_end: float, tau_s: float, n_series: int,
                     sigma: float = 1.0, dt: float = 1.0) -> SmoothProcess:
    """n_series GM2 processes with std ``sigma`` on [t_start, t_end] (1-s grid + margins).
    The grid is relative to t_start to keep spline arithmetic well conditioned; callers pass
    times relative to the same t_start."""
    n = int(math.ceil((t_end - t_start) / dt)) + 3
    tg = (np.arange(n) - 1) * dt
    x = sigma * gm2_unit_grid(rng, n, dt, tau_s, n_series)
    return SmoothProcess(tg, x)


def gm1(rng, n_steps: int, dt: float, tau_s: float, sigma: float, shape=()) -> np.ndarray:
    """1st-order GM (exact discretisation, stationary start) along axis 0: (n_steps, *shape)."""
    shape = tuple(np.atleast_1d(shape)) if shape != () else ()
    if sigma == 0.0:
        return np.zeros((n_steps,) + shape)
    a = math.exp(-dt / tau_s)
    w = rng.standard_normal((n_steps,) + shape) * sigma * math.sqrt(1.0 - a * a)
    w[0] = rng.standard_normal(shape) * sigma
    return lfilter([1.0], [1.0, -a], w, axis=0)


def clock_process(rng, model, n_steps: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Steered-TCXO receiver clock: (bias m, drift m/s) at n_steps uniform grid points."""
    w0 = 1.0 / model.steer_tau_s
    F = np.array([[0.0, 1.0], [-w0 * w0, -2.0 * w0]])
    Q = np.diag([model.s_f, model.s_g])
    x = _simulate_linear(rng, F, Q, dt, n_steps, 1)[:, 0, :]
    return x[:, 0], x[:, 1]


def imu_errors(rng, model, n_intervals: int) -> dict[str, np.ndarray]:
    """Rate errors over each IMU interval: gyro (rad/s), accel (m/s^2), each (n_intervals, 3),
    plus their parts.  Increment errors are these times dt."""
    dt = 1.0 / model.rate_hz
    out = {}
    for kind, fixed, sig, bi_sig, bi_tau, uni, dens in (
            ("gyro", model.gyro_bias_fixed_radps, model.gyro_bias_sigma_radps,
             model.gyro_bi_sigma_radps, model.gyro_bi_tau_s, model.gyro_noise_uniform_radps,
             model.gyro_arw_radps_per_sqrthz),
            ("accel", model.accel_bias_fixed_mps2, model.accel_bias_sigma_mps2,
             model.accel_bi_sigma_mps2, model.accel_bi_tau_s, model.accel_noise_uniform_mps2,
             model.accel_vrw_mps2_per_sqrthz)):
        signs = rng.choice([-1.0, 1.0], size=3)
        turn_on = fixed * signs + sig * rng.standard_normal(3)
        instab = gm1(rng, n_intervals, dt, bi_tau, bi_sig, 3)
        noise = np.zeros((n_intervals, 3))
        if uni > 0.0:
            noise += rng.uniform(-uni, uni, (n_intervals, 3))
        if dens > 0.0:
            noise += rng.standard_normal((n_intervals, 3)) * (dens / math.sqrt(dt))
        out[f"{kind}_turn_on_bias"] = turn_on
        out[f"{kind}_bias"] = turn_on[None, :] + instab
        out[f"{kind}_noise"] = noise
        out[f"{kind}_error"] = out[f"{kind}_bias"] + noise
    return out


def elevation_factor(el_rad, enabled: bool):
    if not enabled:
        return np.ones_like(np.asarray(el_rad, float))
    return 1.0 / np.sin(np.maximum(np.asarray(el_rad, float), math.radians(5.0)))


def iono_obliquity(el_rad, shell_height_m: float = 350e3, earth_radius_m: float = 6371e3):
    """Thin-shell mapping 1/sqrt(1 - (R cos el / (R + H))^2)."""
    x = earth_radius_m * np.cos(np.asarray(el_rad, float)) / (earth_radius_m + shell_height_m)
    return 1.0 / np.sqrt(1.0 - x * x)


def tropo_obliquity(el_rad):
    s = np.sin(np.maximum(np.asarray(el_rad, float), 0.0))
    return 1.001 / np.sqrt(0.002001 + s * s)


def cn0_dbhz(el_rad):
    return 32.0 + 18.0 * np.sin(np.maximum(np.asarray(el_rad, float), 0.0))
