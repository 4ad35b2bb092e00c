"""Error-state EKF: state layout, IMU-rate covariance propagation, gated Joseph-form update.

Error-state convention ("correction" form, truth = estimate + error):

* attitude ``psi`` (rad, ECEF axes):  C_b_e(true) = (I + [psi x]) C_b_e(est)
* position ``dr`` (m, ECEF), velocity ``dv`` (m/s, ECEF)
* accelerometer bias ``dba`` (m/s^2, body), gyro bias ``dbg`` (rad/s, body): b(true) = b(est) + db
* receiver clock bias ``dclk`` (m) and drift ``ddrift`` (m/s)
* IMU time-tag offset ``dt_imu`` (s): the GPS time of an IMU sample is its mapped time tag (autopilot
  boot time through :class:`~companion.io.mavlink_time.BootToGpsTime`) plus ``dt_imu``.  The INS runs on
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
accurate to ~1e-7).

The states are named blocks (:mod:`.state_layout`): the INS errors and the clock form the core
with the transition above; ``dt_imu``, inter-system biases (``isb_E`` etc., the pseudorange of a
non-GPS satellite depends on the clock plus its system's bias, each a random walk of
``inter_system_bias_rw_m_per_sqrt_s``) and blocks added at run time (carrier ambiguities) have the
identity as transition and cost no dense product (:meth:`ErrorStateKalmanFilter.propagate`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.linalg import cho_factor, cho_solve
from scipy.linalg.lapack import dpotrf as _potrf, dtrtri as _trtri, dtrtrs as _trtrs
from .chi2 import chi2_ppf

from . import imu_kernel
from .imu_fused import new_filter_buffer, unpack_filter_buffer
from .earth import OMEGA_IE_RADPS, skew
from .state_layout import DEFAULT_LAYOUT, DT_IMU, StateLayout, delete_block, insert_block, isb_block_name


LAYOUT = DEFAULT_LAYOUT   # the standard 18-state layout (frozen: filters take their own copy)


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
    inter_system_bias_rw_m_per_sqrt_s: float = 1e-3  # random walk of each inter-system bias block


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
    this class owns P, builds Phi from the current nominal quantities and computes corrections.

    The filter works on its own copy of ``layout`` (:mod:`.state_layout`): blocks added or removed
    at run time (:meth:`add_block`, :meth:`remove_block`) change ``self.layout`` only.  Propagation
    is by blocks: the core (INS and clock) densely with Phi_core, the identity blocks by their
    process noise alone, their cross-covariance with the core by Phi_core (see :meth:`propagate`).
    """

    on_update = None   # optional callable(P_prior, dx) at every update (companion.nav.smoother)

    def __init__(self, P0: np.ndarray, noise: ProcessNoise, gate_probability: float = 0.999,
                 layout: StateLayout = LAYOUT):
        self.layout = layout.copy()
        self.P = np.array(P0, dtype=float)
        if self.P.shape != (self.layout.n, self.layout.n):
            raise ValueError(f"P0 is {self.P.shape}, the layout has {self.layout.n} states")
        self.noise = noise
        self.gate_chi2_1dof = float(chi2_ppf(gate_probability, 1))
        # random-walk PSD (units^2/s) of every identity block, by name
        self._block_psd = {DT_IMU: noise.imu_time_offset_rw_s_per_sqrt_s ** 2}
        for system in self.layout.isb_index:
            self._block_psd[isb_block_name(system)] = noise.inter_system_bias_rw_m_per_sqrt_s ** 2
        self._build_transition()

    # ------------------------------------------------------------------ layout changes
    def add_block(self, name: str, size: int, initial_sigma, random_walk_psd: float = 0.0) -> None:
        """Append an identity block (e.g. a float ambiguity), uncorrelated with everything, with
        1-sigma ``initial_sigma`` (scalar or per state) and a random walk of ``random_walk_psd``
        (units^2/s; 0 = a constant).  The other blocks' covariance is kept as it is."""
        b = self.layout.add_block(name, size)
        self.P = insert_block(self.P, b.start, b.size, np.asarray(initial_sigma, float) ** 2)
        self._block_psd[name] = float(random_walk_psd)
        self._build_transition()

    def remove_block(self, name: str) -> None:
        """Drop a block with its covariance rows and columns; the others keep theirs."""
        b = self.layout.remove_block(name)
        self.P = delete_block(self.P, b.start, b.size)
        self._block_psd.pop(name, None)
        self._build_transition()

    # ------------------------------------------------------------------ propagation
    # Up to this many states the whole matrix is propagated as one dense product: below it Python's
    # per-call overhead, not arithmetic, decides, and three numpy calls beat the six of the block
    # form (measured, 2 shared cores: n = 18 dense 6.0 us, blocks 7.6 us; n = 23 8.3 / 8.9 us;
    # n = 28 8.2 / 8.4 us; n = 38 11.6 / 8.5 us; n = 58 24.8 / 9.0 us; both include the rewrite of Phi).
    # The numbers are the same either way (the identity rows of Phi add exact zeros).
    DENSE_MAX_STATES = 24

    def _build_transition(self) -> None:
        """Preallocate Phi of the densely propagated group -- the core, and the identity blocks
        too while the whole state is small (DENSE_MAX_STATES) -- and views of the blocks of Phi
        rewritten at IMU rate.  Called again after every change of the layout."""
        L = self.layout
        nd = L.n if L.n <= self.DENSE_MAX_STATES else L.n_core
        self._n_dense = nd
        # the compiled step's matrices in one buffer (numba unboxes every array argument, ~0.1 us
        # each, at every IMU sample): Phi, Qd (nd x nd), the identity tail's noise (n - nd), a
        # work buffer (nd x n) and another (nd x nd), views of it here as in the kernel
        self._kernel_buf = new_filter_buffer(nd, L.n)
        (self._phi, self._Qd, self._kernel_tail_q, self._kernel_work, self._kernel_work_cc,
         _scratch) = unpack_filter_buffer(self._kernel_buf, L.n)
        self._phi[...] = np.eye(nd)     # constant entries stay; the rest is rewritten every step
        self._phi_T = self._phi.T                   # a view: follows every in-place write to Phi
        self._phi_att_att = self._phi[L.att, L.att]
        self._phi_pos_vel = self._phi[L.pos, L.vel]
        self._phi_vel_att = self._phi[L.vel, L.att]
        self._phi_vel_pos = self._phi[L.vel, L.pos]
        self._phi_vel_vel = self._phi[L.vel, L.vel]
        self._phi_att_bg = self._phi[L.att, L.bg]
        self._phi_vel_ba = self._phi[L.vel, L.ba]
        self._grad_tau = None
        self._last_tau = -1.0
        # random-walk PSD of every identity state (indices n_core .. n-1)
        self._tail_psd = np.zeros(L.n - L.n_core)
        for b in L.identity_blocks():
            self._tail_psd[b.start - L.n_core:b.stop - L.n_core] = self._block_psd.get(b.name, 0.0)
        self._tail_q_scalar = []
        self._views_of = None
        # the compiled kernel's block starts
        self._kernel_idx = (L.att.start, L.vel.start, L.ba.start, L.bg.start)

    def _set_interval(self, tau: float) -> None:
        """Entries of Phi and Qd that depend only on the interval length (constant at a fixed IMU rate)."""
        L, q = self.layout, self.noise
        omega_tau = skew(np.array([0.0, 0.0, OMEGA_IE_RADPS])) * tau
        self._phi_att_att[...] = np.eye(3) - omega_tau          # -Omega_ie psi
        self._phi_pos_vel[...] = np.eye(3) * tau                # dr' = dv
        self._phi_vel_vel[...] = np.eye(3) - 2.0 * omega_tau    # -2 Omega_ie dv
        self._phi[L.clk, L.drift] = tau
        nc, nd = L.n_core, self._n_dense
        d = np.zeros(nd)
        d[L.att] = q.gyro_arw_rad_per_sqrt_s ** 2 * tau
        d[L.vel] = q.accel_vrw_mps_per_sqrt_s ** 2 * tau
        d[L.ba] = q.accel_bias_rw_mps2_per_sqrt_s ** 2 * tau
        d[L.bg] = q.gyro_bias_rw_radps_per_sqrt_s ** 2 * tau
        d[L.clk] = q.clock_bias_psd_m2ps * tau + q.clock_drift_psd_m2ps3 * tau ** 3 / 3.0
        d[L.drift] = q.clock_drift_psd_m2ps3 * tau
        d[nc:] = self._tail_psd[:nd - nc] * tau                 # identity blocks in the dense group
        Qd = np.diag(d)
        Qd[L.clk, L.drift] = Qd[L.drift, L.clk] = q.clock_drift_psd_m2ps3 * tau ** 2 / 2.0
        self._Qd[...] = Qd
        # identity blocks outside the dense group: their process noise alone
        self._tail_q = self._tail_psd * tau
        nz = np.flatnonzero(self._tail_q) if nd < L.n else []
        self._tail_q_scalar = ([((nc + int(i), nc + int(i)), float(self._tail_q[i])) for i in nz]
                               if len(nz) <= self._SCALAR_TAIL_NOISE_MAX else None)
        self._kernel_tail_q[...] = self._tail_q[nd - nc:]
        self._last_tau = tau
        self._grad_tau = None  # the gravity-gradient block scales with tau: rewrite it

    # up to this many identity states with process noise get it by scalar additions (a ufunc on a
    # strided view costs about 1 us, five scalar additions as much)
    _SCALAR_TAIL_NOISE_MAX = 4

    def _make_views(self, P: np.ndarray) -> None:
        """Views of P's core rows, core block, cross blocks and identity diagonal, and the buffer
        of Phi_core P[core rows] (rebuilt when P is replaced, e.g. by an update)."""
        nc, n = self.layout.n_core, self.layout.n
        self._P_rows = P[:nc]
        self._P_core = P[:nc, :nc]
        self._P_cx = P[:nc, nc:]
        self._P_xc = P[nc:, :nc]
        s0, s1 = P.strides
        self._P_tail_diag = np.lib.stride_tricks.as_strided(P[nc:, nc:], shape=(n - nc,), strides=(s0 + s1,))
        self._phi_P = np.empty((nc, n))             # Phi_core @ P[core rows]: [Phi P_cc | Phi P_cx]
        self._phi_P_core = self._phi_P[:, :nc]
        self._phi_P_cx = self._phi_P[:, nc:]
        self._P_cc_new = np.empty((nc, nc))
        self._views_of = P

    def propagate(self, C_b_e: np.ndarray, dv_e: np.ndarray, gravity_gradient: np.ndarray, tau: float) -> None:
        """P <- Phi P Phi^T + Qd over one IMU interval (see :meth:`propagate_reference`), by the
        compiled kernel (:mod:`.imu_kernel`: the same BLAS products, P updated in place, the
        Python around them gone) when numba is there, else by :meth:`propagate_reference`."""
        k = imu_kernel.compiled()
        if k is None:
            self.propagate_reference(C_b_e, dv_e, gravity_gradient, tau)
            return
        if tau != self._last_tau:
            self._set_interval(tau)
        if gravity_gradient is not self._grad_tau:
            np.multiply(gravity_gradient, tau, out=self._phi_vel_pos)
            self._grad_tau = gravity_gradient
        P = self.P
        if not P.flags.c_contiguous or P.dtype != np.float64:
            P = self.P = np.ascontiguousarray(P, dtype=float)    # one compiled specialisation
        fx, fy, fz = dv_e
        i_att, i_vel, i_ba, i_bg = self._kernel_idx
        k.propagate(self._phi, P, self._Qd, self._kernel_tail_q, C_b_e, fx, fy, fz, tau,
                    i_att, i_vel, i_ba, i_bg, self._kernel_work, self._kernel_work_cc)

    def propagate_reference(self, C_b_e: np.ndarray, dv_e: np.ndarray, gravity_gradient: np.ndarray,
                            tau: float) -> None:
        """P <- Phi P Phi^T + Qd over one IMU interval, by blocks (c: the core, x: identity blocks):

            P_cc <- Phi_c P_cc Phi_c^T + Q_c,   P_cx <- Phi_c P_cx,   P_xx <- P_xx + Q_x

        which is the dense product exactly (Phi = diag(Phi_c, I)) at O(n_c^2 n) instead of O(n^3),
        P updated in place.  A small state (DENSE_MAX_STATES) takes the dense product, which is
        cheaper there.

        ``dv_e`` is the specific-force velocity increment over the interval in ECEF (f_e * tau,
        i.e. C_b_e times the compensated body increment); ``C_b_e`` the attitude at its start.
        Isotropic sensor noises make C Q C^T = Q, so Qd is constant for a fixed interval.
        ``gravity_gradient`` is re-entered only when a new array object is passed (it is refreshed
        every few hundred metres by the engine).
        """
        if tau != self._last_tau:
            self._set_interval(tau)
        if gravity_gradient is not self._grad_tau:
            np.multiply(gravity_gradient, tau, out=self._phi_vel_pos)
            self._grad_tau = gravity_gradient
        np.multiply(C_b_e, -tau, out=self._phi_att_bg)       # -C dbg
        self._phi_vel_ba[...] = self._phi_att_bg              # -C dba
        fx, fy, fz = dv_e                                    # -[f x] psi, times tau
        va = self._phi_vel_att
        va[0, 1] = fz
        va[0, 2] = -fy
        va[1, 0] = -fz
        va[1, 2] = fx
        va[2, 0] = fy
        va[2, 1] = -fx
        P = self.P
        if self._n_dense == P.shape[0]:
            if P is not self._views_of:
                self._phi_P = np.empty_like(P)
                self._views_of = P
            np.matmul(self._phi, P, out=self._phi_P)
            P = self._phi_P @ self._phi_T
            P += self._Qd
            self.P = self._views_of = P
            return
        if P is not self._views_of:
            self._make_views(P)
        np.matmul(self._phi, self._P_rows, out=self._phi_P)
        np.matmul(self._phi_P_core, self._phi_T, out=self._P_cc_new)
        np.add(self._P_cc_new, self._Qd, out=self._P_core)
        self._P_cx[...] = self._phi_P_cx
        self._P_xc[...] = self._phi_P_cx.T
        if self._tail_q_scalar is None:
            self._P_tail_diag += self._tail_q
        else:
            for ij, q in self._tail_q_scalar:
                P[ij] += q

    def transition_matrix(self) -> np.ndarray:
        """The dense n x n Phi of the last propagation step (diag(Phi_core, I)): a reference."""
        nd = self._n_dense
        phi = np.eye(self.layout.n)
        phi[:nd, :nd] = self._phi
        return phi

    def dense_transition(self) -> np.ndarray:
        """Phi of the densely propagated group (the leading k x k block; the identity beyond it)
        of the last propagation step: a view, valid until the next step (companion.nav.smoother)."""
        return self._phi

    def process_noise_matrix(self) -> np.ndarray:
        """The dense n x n Qd of the last propagation step: a reference."""
        L, nd = self.layout, self._n_dense
        Q = np.zeros((L.n, L.n))
        Q[:nd, :nd] = self._Qd
        Q[nd:, nd:] = np.diag(self._tail_q[nd - L.n_core:])
        return Q

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
        S = ((H @ P) * H).sum(axis=1) + batch.r_var        # diag(H P H^T) (einsum costs 3x more here)
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
            Sa.flat[::len(Sa) + 1] += batch.r_var[active]
            lam = spd_inverse(Sa)
            lz = lam @ batch.z[active]
            r = lz * lz / (np.diag(lam) * self.gate_chi2_1dof)
            ratio[active] = r
            worst = int(np.argmax(r))
            if r[worst] <= 1.0:
                break
            active = np.delete(active, worst)   # rejected: its ratio stays > 1
        return ratio

    def update(self, batches: list[MeasurementBatch], reports: list[UpdateReport]) -> np.ndarray:
        """Update with the accepted rows of all batches at once.  Returns dx.

        On the columns the rows touch only (an RTK epoch's rows see the INS core and the
        ambiguities of the signals present, not the rest of the state), with S = C C^T:

            W = P H^T C^-T,   dx = W C^-1 z,   P <- P - W W^T

        which is the Joseph form (:meth:`update_joseph`) for the optimal gain up to rounding, at
        O(n^2 m) instead of O(n^3) (W W^T symmetric by construction, P symmetrised).  A diagonal that this
        leaves negative (a cancellation the subtraction cannot afford) falls back to the
        Joseph form, whose products of PSD terms keep it."""
        H, z, r = _accepted_rows(batches, reports)
        n = self.layout.n
        if H is None:
            return np.zeros(n)
        P = self.P
        cols = np.flatnonzero(np.any(H != 0.0, axis=0))
        Hc = H[:, cols]
        PHt = P[:, cols] @ Hc.T                       # (n, m)
        S = Hc @ PHt[cols]
        S.flat[::len(S) + 1] += r
        C = cholesky_lower(S)
        # one triangular solve for C^-1 [H P | z] (LAPACK directly: scipy's wrapper costs more
        # than the solve at these sizes)
        B = np.empty((len(z), n + 1), order="F")
        B[:, :n] = PHt.T
        B[:, n] = z
        X = solve_lower(C, B)
        W = X[:, :n].T                                # P H^T C^-T
        dx = W @ X[:, n]
        if self.on_update is not None:
            self.on_update(P, dx)
        P_new = P - W @ W.T
        if not np.all(np.diagonal(P_new) >= 0.0):
            return self._joseph(H, z, r)
        # the propagation's rounding leaves P a little asymmetric: not carried on
        P_new += P_new.T
        P_new *= 0.5
        self.P = P_new
        return dx

    def update_joseph(self, batches: list[MeasurementBatch], reports: list[UpdateReport]) -> np.ndarray:
        """The dense Joseph-form update (the reference of :meth:`update`, and its fallback)."""
        H, z, r = _accepted_rows(batches, reports)
        if H is None:
            return np.zeros(self.layout.n)
        return self._joseph(H, z, r)

    def _joseph(self, H: np.ndarray, z: np.ndarray, r: np.ndarray) -> np.ndarray:
        n = self.layout.n
        P = self.P
        PHt = P @ H.T
        S = H @ PHt
        S.flat[::len(S) + 1] += r
        # K = P H^T S^-1 via a Cholesky solve (S is symmetric positive definite)
        c, low = _cho_factor(S)
        K = _cho_solve((c, low), PHt.T).T
        dx = K @ z
        if self.on_update is not None:
            self.on_update(P, dx)
        IKH = np.eye(n) - K @ H
        P = IKH @ P @ IKH.T + (K * r) @ K.T
        self.P = 0.5 * (P + P.T)
        return dx


def _accepted_rows(batches, reports):
    """(H, z, r) of the accepted rows of all batches, (None, None, None) when there are none."""
    rows_H, rows_z, rows_r = [], [], []
    for b, rep in zip(batches, reports):
        if rep.n_accepted:
            if rep.accepted.all():
                rows_H.append(b.H)
                rows_z.append(b.z)
                rows_r.append(b.r_var)
            else:
                rows_H.append(b.H[rep.accepted])
                rows_z.append(b.z[rep.accepted])
                rows_r.append(b.r_var[rep.accepted])
    if not rows_H:
        return None, None, None
    if len(rows_H) == 1:
        return rows_H[0], rows_z[0], np.asarray(rows_r[0], float)
    return np.vstack(rows_H), np.concatenate(rows_z), np.concatenate(rows_r)


def cholesky_lower(S: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor of a symmetric positive definite S (its lower triangle is read);
    LinAlgError otherwise.  LAPACK's potrf without scipy's checks."""
    C, info = _potrf(S, lower=1, clean=1)
    if info != 0:
        raise np.linalg.LinAlgError("matrix not positive definite")
    return C


def spd_inverse(S: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive definite S from its Cholesky factor C (S^-1 = C^-T C^-1;
    LAPACK potrf + trtri, about half of np.linalg.inv's cost at these sizes); np.linalg.inv when
    S is not positive definite in floating point."""
    C, info = _potrf(S, lower=1, clean=1)
    if info == 0:
        Ci, info = _trtri(C, lower=1)
        if info == 0:
            return Ci.T @ Ci
    return np.linalg.inv(S)


def solve_lower(C: np.ndarray, B: np.ndarray) -> np.ndarray:
    """C^-1 B for a lower triangular C (LAPACK trtrs: scipy's solve_triangular, its checks aside)."""
    X, info = _trtrs(C, B, lower=1)
    if info != 0:
        raise np.linalg.LinAlgError("singular triangular factor")
    return X


def _cho_factor(S):
    return cho_factor(S, lower=True, check_finite=False)


def _cho_solve(cf, b):
    return cho_solve(cf, b, check_finite=False)


def nees(error: np.ndarray, P: np.ndarray) -> float:
    """Normalised estimation error squared of an error vector against its covariance."""
    return float(error @ np.linalg.solve(P, error))

