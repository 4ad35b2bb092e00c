"""Overlapping Allan deviation of inertial sensor series and the fit of its noise terms.

Allan variance (IEEE Std 952-1997 Annex C; IEEE Std 1554), overlapping estimator, from the
integrated signal theta_k = sum y / fs (angle for a gyro, velocity for an accelerometer):

    sigma^2(tau) = sum_k (theta_{k+2m} - 2 theta_{k+m} + theta_k)^2 / (2 tau^2 (n - 2m)),  tau = m / fs

evaluated for log-spaced cluster sizes m (vectorised: one numpy pass per m).

Noise terms (two-sided PSD convention of IEEE 952) and their Allan variance:

* white rate noise, angle / velocity random walk N:   N^2 / tau         (slope -1/2; N = sigma(1 s))
* bias instability (flicker) B:                         (2 ln 2 / pi) B^2 (flat; minimum = 0.664 B)
* rate random walk K:                                   K^2 tau / 3       (slope +1/2; K = sigma(3 s))

Fit.  The classic readings are taken first: N from the -1/2 line through the short-tau points,
B = minimum / 0.664, K from the +1/2 line through the long-tau points (each a least-squares fit
of the intercept with the slope fixed, on log sigma, over the region whose local slope is within
0.15 of the term's slope).  Because each region is never purely one term (the flat part lifts
both ends), the final estimate fits the sum of the three terms to the whole log-log curve by
weighted least squares on log sigma, started from the classic readings; each coefficient is then
determined where its term dominates.  Weights: the number of independent clusters n/m - 1,
the inverse variance of log sigma(tau) to first order.  Both sets are returned.

Units: gyro N in rad/sqrt(s), B in rad/s, K in rad/s/sqrt(s); accelerometer N in m/s/sqrt(s),
B in m/s^2, K in m/s^2/sqrt(s).
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

BI_FACTOR = math.sqrt(2.0 * math.log(2.0) / math.pi)    # 0.6643


def cluster_sizes(n: int, per_decade: int = 8, max_fraction: float = 1.0 / 3.0) -> np.ndarray:
    """Log-spaced integer cluster sizes m = 1 .. n*max_fraction (at least 2 clusters... of 3m)."""
    m_max = max(1, int(n * max_fraction))
    m = np.unique(np.round(np.logspace(0, math.log10(m_max), int(per_decade * math.log10(max(m_max, 10))) + 1)))
    return m.astype(np.int64)


def overlapping_adev(y, fs_hz: float, m=None, per_decade: int = 8):
    """(tau_s, adev, n_clusters) of a rate series ``y`` (1-D, or (n, k) for k axes at once)."""
    y = np.asarray(y, float)
    one = y.ndim == 1
    if one:
        y = y[:, None]
    n = y.shape[0]
    theta = np.concatenate([np.zeros((1, y.shape[1])), np.cumsum(y, axis=0)]) / fs_hz
    if m is None:
        m = cluster_sizes(n, per_decade)
    m = np.asarray(m, np.int64)
    m = m[(m >= 1) & (2 * m < n)]
    tau = m / fs_hz
    avar = np.empty((len(m), y.shape[1]))
    for i, mi in enumerate(m):
        d = theta[2 * mi:] - 2.0 * theta[mi:-mi] + theta[:-2 * mi]
        avar[i] = np.einsum("ij,ij->j", d, d) / (2.0 * tau[i] ** 2 * (n + 1 - 2 * mi))
    adev = np.sqrt(avar)
    nclus = n / m - 1.0
    return tau, (adev[:, 0] if one else adev), nclus


@dataclass
class AllanFit:
    N: float                 # random walk coefficient (ARW or VRW)
    B: float                 # bias instability
    K: float                 # rate random walk
    tau_min_s: float         # tau of the curve's minimum
    adev_min: float
    N_line: float            # classic readings (fixed-slope line fits / minimum)
    B_min: float
    K_line: float | None

    def model(self, tau):
        tau = np.asarray(tau, float)
        return np.sqrt(self.N ** 2 / tau + (BI_FACTOR * self.B) ** 2 + self.K ** 2 * tau / 3.0)

    def as_dict(self) -> dict:
        return asdict(self)


def _local_slope(tau, adev):
    lt, la = np.log10(tau), np.log10(adev)
    return np.gradient(la, lt)


def fit_allan(tau, adev, nclus, slope_tol: float = 0.15) -> AllanFit:
    """Fit N, B, K to one Allan deviation curve (see the module docstring)."""
    from scipy.optimize import least_squares

    tau, adev, nclus = (np.asarray(a, float) for a in (tau, adev, nclus))
    ok = np.isfinite(adev) & (adev > 0) & (nclus >= 2)
    tau, adev, nclus = tau[ok], adev[ok], nclus[ok]
    w = np.sqrt(np.maximum(nclus - 1.0, 1.0))
    slope = _local_slope(tau, adev)
    i_min = int(np.argmin(adev))
    # classic readings
    reg_n = (np.abs(slope + 0.5) < slope_tol) & (np.arange(len(tau)) < i_min)
    if not np.any(reg_n):
        reg_n = np.arange(len(tau)) < max(3, i_min // 2)
    n_line = float(10 ** np.average(np.log10(adev[reg_n] * np.sqrt(tau[reg_n])), weights=w[reg_n] ** 2))
    reg_k = (np.abs(slope - 0.5) < slope_tol) & (np.arange(len(tau)) > i_min)
    k_line = (float(10 ** np.average(np.log10(adev[reg_k] * np.sqrt(3.0 / tau[reg_k])), weights=w[reg_k] ** 2))
              if np.any(reg_k) else None)
    b_min = float(adev[i_min] / BI_FACTOR)
    # joint weighted least squares of the three-term model on log sigma
    x0 = np.log([max(n_line, 1e-30), max(b_min, 1e-30), max(k_line or b_min / math.sqrt(tau[-1]) * 0.1, 1e-30)])

    def resid(x):
        N, B, K = np.exp(x)
        mod = np.sqrt(N * N / tau + (BI_FACTOR * B) ** 2 + K * K * tau / 3.0)
        return w * (np.log(mod) - np.log(adev))

    # bounded in log space (a term absent from the data goes to its lower bound, no overflow)
    sol = least_squares(resid, x0, bounds=(x0 - 25.0, x0 + 10.0), method="trf")
    N, B, K = (float(v) for v in np.exp(sol.x))
    return AllanFit(N, B, K, float(tau[i_min]), float(adev[i_min]), n_line, b_min, k_line)


def analyse_imu(t_s, gyro, accel, per_decade: int = 8) -> dict:
    """Allan deviation and fits of 3-axis gyro (rad/s) and accelerometer (m/s^2) series.

    Returns {'fs_hz', 'duration_s', 'gyro': {...}, 'accel': {...}, 'noise': filter block}."""
    t_s = np.asarray(t_s, float)
    dt = np.diff(t_s)
    fs = 1.0 / float(np.median(dt))
    out = {"fs_hz": fs, "duration_s": float(t_s[-1] - t_s[0]), "samples": len(t_s),
           "irregular_fraction": float(np.mean(np.abs(dt * fs - 1.0) > 0.5))}
    for name, y in (("gyro", gyro), ("accel", accel)):
        y = np.asarray(y, float)
        y = y - np.mean(y, axis=0)
        tau, adev, nclus = overlapping_adev(y, fs, per_decade=per_decade)
        fits = [fit_allan(tau, adev[:, j], nclus) for j in range(adev.shape[1])]
        out[name] = {"tau_s": tau, "adev": adev, "n_clusters": nclus, "fits": fits}
    out["noise"] = noise_block(out["gyro"]["fits"], out["accel"]["fits"])
    return out


def noise_block(gyro_fits, accel_fits) -> dict:
    """The [filter] keys of companion.nav.filter.ProcessNoise from per-axis fits (largest axis:
    the filter's noises are isotropic, so the worst axis is the honest choice).

    The filter has no flicker state: its bias random walk must cover the rate random walk K and
    the bias instability B over the time it wanders (tau at the Allan minimum), as a random walk
    that reaches sigma ~ B after that time: sqrt(K^2 + 2 B^2 / tau_min) (cf. sitl.tuning's
    sigma*sqrt(2/tau) for a Gauss-Markov bias)."""
    def bias_rw(f):
        return math.sqrt(f.K ** 2 + 2.0 * f.B ** 2 / f.tau_min_s)

    return {"gyro_arw_rad_per_sqrt_s": max(f.N for f in gyro_fits),
            "accel_vrw_mps_per_sqrt_s": max(f.N for f in accel_fits),
            "gyro_bias_rw_radps_per_sqrt_s": max(bias_rw(f) for f in gyro_fits),
            "accel_bias_rw_mps2_per_sqrt_s": max(bias_rw(f) for f in accel_fits)}


def format_noise_block(noise: dict) -> str:
    lines = ["[filter]"]
    for k, v in noise.items():
        lines.append(f"{k} = {v:.4g}")
    return "\n".join(lines)


# ------------------------------------------------------------------------- test-signal generator
def simulate_static_imu(rng: np.random.Generator, n: int, fs_hz: float, N: float, B: float, K: float,
                        axes: int = 3, bias: float = 0.0) -> np.ndarray:
    """A static sensor's rate output (n, axes): white noise of density N (per-sample std N sqrt(fs)),
    flicker (bias instability) B -- 1/f noise shaped in the frequency domain with the one-sided PSD
    B^2 / (pi f) (= IEEE 952's two-sided (B^2 / 2 pi) / f) from 1/T to fs/2 -- and rate random
    walk K (cumulative sum of white noise of density K).  Known Allan curve:
    N^2/tau + 0.664^2 B^2 + K^2 tau / 3."""
    out = rng.standard_normal((n, axes)) * (N * math.sqrt(fs_hz))
    if B > 0:
        X = np.fft.rfft(rng.standard_normal((n, axes)), axis=0)
        f = np.fft.rfftfreq(n, 1.0 / fs_hz)
        scale = np.zeros_like(f)
        scale[1:] = np.sqrt(B * B / (math.pi * f[1:]) * fs_hz / 2.0)
        out += np.fft.irfft(X * scale[:, None], n=n, axis=0)
    if K > 0:
        out += np.cumsum(rng.standard_normal((n, axes)) * (K / math.sqrt(fs_hz)), axis=0)
    return out + bias
