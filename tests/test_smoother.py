"""The RTS recorder (companion.nav.smoother) against the exact answer of a linear-Gaussian problem.

A closed-loop error-state filter on a linear model (constant velocity plus random walks, the
standard 18-state layout, one extra block that appears and disappears like a float ambiguity)
drives the recorder through the same hooks as the engine.  The fixed-interval smoothed mean and
covariance of such a problem are the posterior of one batch least-squares over all states at all
steps, which the test solves densely.
"""
from __future__ import annotations

import numpy as np
import pytest

from companion.messages import NavSolution
from companion.nav.smoother import SmootherRecorder
from companion.nav.state_layout import StateLayout, delete_block, insert_block

DT = 0.5
STEPS = 40
R0 = np.array([6378137.0, 0.0, 0.0])       # the toy's positions are offsets from this ECEF point
SIGMA_POS_M = 0.5
SIGMA_BIAS_M = 2.0
BIAS_FROM, BIAS_TO = 8, 26                 # steps during which the x measurement has a bias block
OUTAGE = range(15, 24)                     # no measurement here
PRE_UPDATE_NOTES = (5, 12, 30)             # steps with a solution noted before the update too


class _ToyFilter:
    """What the recorder sees of ErrorStateKalmanFilter: P, layout, dense_transition, on_update."""

    on_update = None

    def __init__(self, layout, P0, Phi_core, q_diag):
        self.layout, self.P, self._phi, self.q_diag = layout, P0, Phi_core, q_diag

    def dense_transition(self):
        return self._phi

    def full_phi(self):
        F = np.eye(self.layout.n)
        F[:self.layout.n_core, :self.layout.n_core] = self._phi
        return F


class _ToyEngine:
    def __init__(self, kf):
        self.kf, self.t_gps, self.initialized, self.smoother = kf, 0.0, True, None


def _model():
    L = StateLayout.standard()
    nc = L.n_core
    Phi = np.eye(nc)
    Phi[L.pos, L.vel] = np.eye(3) * DT
    q = np.full(L.n, 1e-6)
    q[L.vel] = 0.05 ** 2 * DT
    q[L.att] = 1e-4 ** 2 * DT
    P0 = np.diag(np.r_[np.full(3, 0.01 ** 2), np.full(3, 3.0 ** 2), np.full(3, 1.0 ** 2), np.full(L.n - 9, 0.1 ** 2)])
    return L, Phi, q, P0


def _run(rng):
    """Simulate truth and measurements, run the closed-loop filter with the recorder."""
    L, Phi, q, P0 = _model()
    n = L.n
    F = np.eye(n)
    F[:L.n_core, :L.n_core] = Phi
    truth = [rng.multivariate_normal(np.zeros(n), P0)]
    for _ in range(STEPS):
        truth.append(F @ truth[-1] + rng.normal(0.0, np.sqrt(q)))
    bias = rng.normal(0.0, SIGMA_BIAS_M)
    meas = {}
    for j in range(1, STEPS + 1):
        if j not in OUTAGE:
            z = truth[j][L.pos] + rng.normal(0.0, SIGMA_POS_M, 3)
            if BIAS_FROM <= j < BIAS_TO:
                z[0] += bias
            meas[j] = z

    layout = L.copy()
    kf = _ToyFilter(layout, P0.copy(), Phi, q)
    eng = _ToyEngine(kf)
    rec = SmootherRecorder(checkpoint_interval_s=DT)   # a checkpoint at every step: no interpolation
    rec.attach(eng)
    x = np.zeros(n)                 # nominal state (the toy's truth = nominal + error)
    forward = []                    # (step, solution)

    def note(j):
        forward.append((j, _solution(eng.t_gps, x, L)))
        rec.note_solution(forward[-1][1])

    note(0)
    for j in range(1, STEPS + 1):
        rec.before_step(eng)
        Fk = kf.full_phi()
        x = Fk @ x
        kf.P = Fk @ kf.P @ Fk.T + np.diag(kf.q_diag)
        rec.after_step(eng)
        eng.t_gps = j * DT
        if j == BIAS_FROM:
            b = layout.add_block("amb", 1)
            kf.P = insert_block(kf.P, b.start, 1, np.array([SIGMA_BIAS_M ** 2]))
            kf.q_diag = np.r_[kf.q_diag, 0.0]
            x = np.r_[x, 0.0]
            rec.layout_changed(eng)
        if j in PRE_UPDATE_NOTES:
            note(j)
        if j in meas:
            H = np.zeros((3, layout.n))
            H[:, L.pos] = np.eye(3)
            if "amb" in layout and j < BIAS_TO:
                H[0, layout.index("amb")] = 1.0
            z = meas[j] - H @ x
            S = H @ kf.P @ H.T + np.eye(3) * SIGMA_POS_M ** 2
            K = np.linalg.solve(S, H @ kf.P).T
            dx = K @ z
            kf.on_update(kf.P, dx)
            IKH = np.eye(layout.n) - K @ H
            kf.P = IKH @ kf.P @ IKH.T + K @ K.T * SIGMA_POS_M ** 2
            x = x + dx
        if j == BIAS_TO:
            b = layout.remove_block("amb")
            kf.P = delete_block(kf.P, b.start, 1)
            kf.q_diag = np.delete(kf.q_diag, b.start)
            x = np.delete(x, b.start)
            rec.layout_changed(eng)
        note(j)
    return L, F, q, P0, meas, forward, rec.smoothed_solutions()


def _solution(t, x, L):
    return NavSolution(t, R0 + x[L.pos], x[L.vel].copy(), np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), "nav")


def _batch_posterior(L, F, q, P0, meas):
    """Mean and covariance of all states at all steps (and the bias) given every measurement."""
    n = L.n
    N = (STEPS + 1) * n + 1
    ib = N - 1
    rows, w, z = [], [], []

    def add(row, value, var):
        rows.append(row)
        z.append(value)
        w.append(1.0 / var)

    for i in range(n):                      # prior on the initial state (diagonal P0)
        row = np.zeros(N)
        row[i] = 1.0
        add(row, 0.0, P0[i, i])
    row = np.zeros(N)
    row[ib] = 1.0
    add(row, 0.0, SIGMA_BIAS_M ** 2)
    for j in range(STEPS):                  # dynamics: x_{j+1} - F x_j = w_j
        for i in range(n):
            row = np.zeros(N)
            row[(j + 1) * n + i] = 1.0
            row[j * n:(j + 1) * n] -= F[i]
            add(row, 0.0, q[i])
    for j, zj in meas.items():
        for a in range(3):
            row = np.zeros(N)
            row[j * n + L.pos.start + a] = 1.0
            if a == 0 and BIAS_FROM <= j < BIAS_TO:
                row[ib] = 1.0
            add(row, zj[a], SIGMA_POS_M ** 2)
    J, W, zz = np.array(rows), np.array(w), np.array(z)
    info = J.T @ (J * W[:, None])
    cov = np.linalg.inv(info)
    return cov @ (J.T @ (W * zz)), cov


def test_rts_matches_batch_least_squares_through_outage_and_layout_changes():
    rng = np.random.default_rng(7)
    L, F, q, P0, meas, forward, smoothed = _run(rng)
    mean, cov = _batch_posterior(L, F, q, P0, meas)
    n = L.n
    assert len(smoothed) == len(forward)
    worst_forward_gap = 0.0
    for (j, fwd), sm in zip(forward, smoothed):
        i = j * n + L.pos.start
        expected = mean[i:i + 3]
        np.testing.assert_allclose(sm.r_e - R0, expected, atol=1e-6)
        iv = j * n + L.vel.start
        np.testing.assert_allclose(sm.v_e, mean[iv:iv + 3], atol=1e-6)
        P = sm.extras["smoothed_cov_nav_e"]
        np.testing.assert_allclose(P[3:6, 3:6], cov[i:i + 3, i:i + 3], rtol=1e-6, atol=1e-9)
        worst_forward_gap = max(worst_forward_gap, float(np.max(np.abs(fwd.r_e - R0 - expected))))
    # the comparison is not vacuous: in the outage the forward solution is far from the smoothed one
    assert worst_forward_gap > 0.1



@pytest.mark.real_data
def test_replay_smooth_on_a_real_ulog():
    """`replay(..., smooth=True)` on the PX4 SIH box flight (tests/data): every solution is the
    smoothed counterpart of a forward one (same time), with a covariance no larger than the
    forward filter's, and the forward pass is scored beside it."""
    from companion.log_records import decode_solution
    from companion.replay import replay
    from tests._data import data_path
    res = replay(data_path("px4-sih-ulog/box-flight.ulg.xz"), smooth=True)
    forward = [decode_solution(b) for b in res.produced]
    assert len(forward) == len(res.solutions) > 400
    assert all(s.extras.get("smoothed") for s in res.solutions)
    assert [s.t_gps for s in forward] == [s.t_gps for s in res.solutions]
    sig_f = np.array([np.hypot(*s.sigma_r_n_m[:2]) for s in forward])
    sig_s = np.array([np.hypot(*s.sigma_r_n_m[:2]) for s in res.solutions])
    assert np.all(sig_s <= sig_f * (1.0 + 1e-6))
    assert np.mean(sig_s) < np.mean(sig_f)
    moved = np.array([np.linalg.norm(a.r_e - b.r_e) for a, b in zip(forward, res.solutions)])
    assert np.max(moved) > 0.01
    assert res.forward_score["ours"]["horizontal"]["n"] == res.truth_score["ours"]["horizontal"]["n"]


def test_cli_smooth_refuses_a_tlog(tmp_path):
    from companion.run_cli import main
    tlog = tmp_path / "flight.tlog"
    tlog.write_bytes(b"")
    assert main(["replay", str(tlog), "--smooth"]) == 2
