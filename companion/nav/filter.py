"""Error-state EKF: state layout, IMU-rate covariance propagation, gated Joseph-form update.

Error-state convention ("correction" form, truth = estimate + error):

* attitude ``psi`` (rad, ECEF axes):  C_b_e(true) = (I + [psi x]) C_b_e(est)
* position ``dr`` (m, ECEF), velocity ``dv`` (m/s, ECEF)
* accelerometer bias ``dba`` (m/s^2, body), gyro bias ``dbg`` (rad/s, body): b(true) = b(est) + db
* receiver clock bias ``dclk`` (m) and drift ``ddrift`` (m/s)
* IMU time-tag offset ``dt_imu`` (s): the GPS time of an IMU sample is its mapped time tag (autopilot
  boot time through :class:`~companion.io.mavlink.BootToGpsTime`) plus ``dt_imu``.  The INS runs on
  the tags; a GNSS measurement at receiver time t is compared with the INS at tag t - dt_imu (see
  :mod:`.engine`).  ArduPilot's SYSTEM_TIME lags GPS time by the receiver's output latency, so a
  lagging clock gives a positive ``dt_imu``.  Observable when the motion changes (accelerations,
  turn entries and exits); in a steady turn it looks like a heading error, so an estimate beyond 3
  prior sigmas is treated as a divergence (:meth:`.engine.NavEngine._check_integrity`).

Continuous error dynamics (derived from the ECEF mechanization in :mod:`.strapdown`):

    psi'  = -Omega_ie psi - C_b_e dbg
    dr'   = dv
    dv'   = -[(C_b_e f_b) x] psi + G(r) dr - 2 Omega_ie dv - C_b_e dba
    dclk' = ddrift
    dt_imu' = white noise (a random walk: the mapping drifts slowly, e.g. as the latency changes)

with G the gravity gradient (its horizontal part is what makes the Schuler oscillation).
Discretisation: Phi = I + F tau (tau = one IMU interval, 2.5-20 ms, where the first-order form is
accurate to ~1e-7).  The layout leaves room for more states (carrier ambiguities for RTK,
inter-system biases) appended after the clock.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from .chi2 import chi2_ppf

from .earth import OMEGA_IE_RADPS


class StateLayout:
    """Indices of the error-state vector (class attributes: slices are not dataclass-friendly)."""

    n = 18
    att = slice(0, 3)
    pos = slice(3, 6)
    vel = slice(6, 9)
    ba = slice(9, 12)
    bg = slice(12, 15)
    clk = 15
    drift = 16
    toff = 17      # IMU time-tag offset dt_imu, s


LAYOUT = StateLayout()


@dataclass(frozen=True)
class ProcessNoise:
    """Continuous-time noise densities (one-sided PSD square roots) of the error model."""

    gyro_arw_rad_per_sqrt_s: float          # angle random walk
    accel_vrw_mps_per_sqrt_s: float         # velocity random walk
    gyro_bias_rw_radps_per_sqrt_s: float    # gyro bias random walk
    accel_bias_rw_mps2_per_sqrt_s: float    # accelerometer bias random walk
    clock_bias_psd_m2ps: float = 0.1        # receiver clock phase noise, m^2/s
    clock_drift_psd_m2ps3: float = 0.01     # receiver clock frequency random walk, m^2/s^3
    imu_time_offset_rw_s_per_sqrt_s: float = 0.0   # random walk of the IMU time-tag offset


@dataclass
class MeasurementBatch:
    """Innovations of one measurement kind at one epoch: z = measured - predicted ~ H dx + noise."""

    kind: str
    labels: list[str]
    z: np.ndarray           # (m,)
    H: np.ndarray           # (m, n)
    r_var: np.ndarray       # (m,) measurement noise variances (uncorrelated)

    def __len__(self) -> int:
        return len(self.labels)


@dataclass
class UpdateReport:
    """What an update did, per measurement: for integrity monitoring and the health report."""

    kind: str
    labels: list[str]
    innovation: np.ndarray
    innovation_var: np.ndarray
    test_ratio: np.ndarray          # z^2 / (S * gate): > 1 means rejected by the gate
    accepted: np.ndarray            # bool
    rejected_reason: dict = field(default_factory=dict)

    @property
    def n_accepted(self) -> int:
        return int(np.count_nonzero(self.accepted))


class ErrorStateKalmanFilter:
    """Covariance bookkeeping of the error-state EKF.  The nominal state lives in the engine;
    this class owns P, builds Phi from the current nominal quantities and computes corrections."""

    def __init__(self, P0: np.ndarray, noise: ProcessNoise, gate_probability: float = 0.999,
                 layout: StateLayout = LAYOUT):
        self.layout = layout
        self.P = np.array(P0, dtype=float)
        self.noise = noise
        self.gate_chi2_1dof = float(chi2_ppf(gate_probability, 1))
        n = layout.n
        self._phi = np.eye(n)   # constant entries stay; the rest is rewritten every step
        self._phi_T = self._phi.T                  # a view: follows every in-place write to Phi
        self._phi_att_bg = self._phi[0:3, 12:15]   # views of the blocks rewritten at IMU rate
        self._phi_vel_ba = self._phi[6:9, 9:12]
        self._phi_P = np.empty((n, n))             # Phi @ P, preallocated
        self._Qd = np.zeros((n, n))
        self._grad_tau = None
        self._last_tau = -1.0

    # ------------------------------------------------------------------ propagation
    def _set_interval(self, tau: float) -> None:
        """Entries of Phi and Qd that depend only on the interval length (constant at a fixed IMU rate)."""
        L, q, phi = self.layout, self.noise, self._phi
        w_tau = OMEGA_IE_RADPS * tau
        phi[0, 1], phi[1, 0] = w_tau, -w_tau                 # -Omega_ie psi
        phi[3, 6] = phi[4, 7] = phi[5, 8] = tau              # dr' = dv
        phi[6, 7], phi[7, 6] = 2.0 * w_tau, -2.0 * w_tau     # -2 Omega_ie dv
        phi[L.clk, L.drift] = tau
        d = np.zeros(L.n)
        d[L.att] = q.gyro_arw_rad_per_sqrt_s ** 2 * tau
        d[L.vel] = q.accel_vrw_mps_per_sqrt_s ** 2 * tau
        d[L.ba] = q.accel_bias_rw_mps2_per_sqrt_s ** 2 * tau
        d[L.bg] = q.gyro_bias_rw_radps_per_sqrt_s ** 2 * tau
        d[L.clk] = q.clock_bias_psd_m2ps * tau + q.clock_drift_psd_m2ps3 * tau ** 3 / 3.0
        d[L.drift] = q.clock_drift_psd_m2ps3 * tau
        d[L.toff] = q.imu_time_offset_rw_s_per_sqrt_s ** 2 * tau
        Qd = np.diag(d)
        Qd[L.clk, L.drift] = Qd[L.drift, L.clk] = q.clock_drift_psd_m2ps3 * tau ** 2 / 2.0
        self._Qd = Qd
        self._last_tau = tau
        self._grad_tau = None  # the gravity-gradient block scales with tau: rewrite it

    def propagate(self, C_b_e: np.ndarray, dv_e: np.ndarray, gravity_gradient: np.ndarray, tau: float) -> None:
        """P <- Phi P Phi^T + Qd over one IMU interval.

        ``dv_e`` is the specific-force velocity increment over the interval in ECEF (f_e * tau,
        i.e. C_b_e times the compensated body increment); ``C_b_e`` the attitude at its start.
        Isotropic sensor noises make C Q C^T = Q, so Qd is constant for a fixed interval.
        ``gravity_gradient`` is re-entered only when a new array object is passed (it is refreshed
        every few hundred metres by the engine).
        """
        if tau != self._last_tau:
            self._set_interval(tau)
        phi = self._phi
        if gravity_gradient is not self._grad_tau:
            phi[6:9, 3:6] = gravity_gradient * tau
            self._grad_tau = gravity_gradient
        np.multiply(C_b_e, -tau, out=self._phi_att_bg)       # -C dbg
        self._phi_vel_ba[...] = self._phi_att_bg              # -C dba
        fx, fy, fz = dv_e                                    # -[f x] psi, times tau
        phi[6, 1] = fz
        phi[6, 2] = -fy
        phi[7, 0] = -fz
        phi[7, 2] = fx
        phi[8, 0] = fy
        phi[8, 1] = -fx
        np.matmul(phi, self.P, out=self._phi_P)
        P = self._phi_P @ self._phi_T
        P += self._Qd
        self.P = P

    def add_body_noise(self, C_b_e: np.ndarray, var_att_b, var_vel_b) -> None:
        """Extra process noise of one interval, given per body axis (rad^2 of attitude, (m/s)^2 of
        velocity), e.g. what a bridged IMU sample could have hidden: P += C diag(var) C^T."""
        L = self.layout
        P = self.P
        P[L.att, L.att] += (C_b_e * np.asarray(var_att_b, float)) @ C_b_e.T
        P[L.vel, L.vel] += (C_b_e * np.asarray(var_vel_b, float)) @ C_b_e.T

    # ------------------------------------------------------------------ update
    def gate(self, batch: MeasurementBatch, leave_one_out: bool = False) -> UpdateReport:
        """Per-measurement chi-square test (1 dof) of the innovation against its predicted variance.

        With ``leave_one_out`` each row is tested against its prediction from the *other* rows of
        the batch (the Gaussian conditional: residual (S^-1 z)_i / (S^-1)_ii, variance 1/(S^-1)_ii),
        the worst row is rejected and the test repeated.  This removes what the rows share, e.g. the
        receiver clock drift in TDCP, whose prior uncertainty would otherwise hide a one-cycle slip
        (seed 004 eq 16 applied after the common mode is explained by the other satellites).
        """
        P, H = self.P, batch.H
        S = np.einsum("ij,jk,ik->i", H, P, H) + batch.r_var
        finite = np.isfinite(batch.z) & np.isfinite(S) & (S > 0)
        ratio = np.full(len(batch), np.inf)
        ratio[finite] = batch.z[finite] ** 2 / (S[finite] * self.gate_chi2_1dof)
        if leave_one_out and np.count_nonzero(finite) >= 3:
            ratio = self._leave_one_out_ratios(batch, finite, ratio)
        accepted = finite & (ratio <= 1.0)
        reasons = {}
        for i, lab in enumerate(batch.labels):
            if not finite[i]:
                reasons[lab] = "non-finite"
            elif not accepted[i]:
                reasons[lab] = "innovation gate"
        return UpdateReport(batch.kind, list(batch.labels), batch.z.copy(), S, ratio, accepted, reasons)

    def _leave_one_out_ratios(self, batch: MeasurementBatch, finite: np.ndarray, ratio: np.ndarray) -> np.ndarray:
        ratio = ratio.copy()
        active = np.flatnonzero(finite)
        while len(active) >= 3:
            Ha = batch.H[active]
            Sa = Ha @ self.P @ Ha.T
            Sa[np.diag_indices_from(Sa)] += batch.r_var[active]
            lam = np.linalg.inv(Sa)
            lz = lam @ batch.z[active]
            r = lz * lz / (np.diag(lam) * self.gate_chi2_1dof)
            ratio[active] = r
            worst = int(np.argmax(r))
            if r[worst] <= 1.0:
                break
            active = np.delete(active, worst)   # rejected: its ratio stays > 1
        return ratio

    def update(self, batches: list[MeasurementBatch], reports: list[UpdateReport]) -> np.ndarray:
        """Joseph-form update with the accepted rows of all batches at once.  Returns dx."""
        rows_H, rows_z, rows_r = [], [], []
        for b, rep in zip(batches, reports):
            if rep.n_accepted:
                rows_H.append(b.H[rep.accepted])
                rows_z.append(b.z[rep.accepted])
                rows_r.append(b.r_var[rep.accepted])
        n = self.layout.n
        if not rows_H:
            return np.zeros(n)
        H = np.vstack(rows_H)
        z = np.concatenate(rows_z)
        r = np.concatenate(rows_r)
        P = self.P
        PHt = P @ H.T
        S = H @ PHt
        S[np.diag_indices_from(S)] += r
        # K = P H^T S^-1 via a Cholesky solve (S is symmetric positive definite)
        c, low = _cho_factor(S)
        K = _cho_solve((c, low), PHt.T).T
        dx = K @ z
        IKH = np.eye(n) - K @ H
        P = IKH @ P @ IKH.T + (K * r) @ K.T
        self.P = 0.5 * (P + P.T)
        return dx


def _cho_factor(S):
    return cho_factor(S, lower=True, check_finite=False)


def _cho_solve(cf, b):
    return cho_solve(cf, b, check_finite=False)


def nees(error: np.ndarray, P: np.ndarray) -> float:
    """Normalised estimation error squared of an error vector against its covariance."""
    return float(error @ np.linalg.solve(P, error))

