"""Measurement-model Jacobians against finite differences of the exact nonlinear models, with the
filter's error convention: truth = estimate + dx, C(true) = (I + [psi x]) C(est)."""
import math

import numpy as np

from companion.messages import GnssAttitude
from companion.nav.earth import C_n_e, euler_to_dcm, geodetic_to_ecef, rotation_from_rotvec
from companion.nav.filter import LAYOUT as L
from companion.nav.filter import MeasurementBatch
from companion.nav.measurements import (InsPoint, _euler_of, antenna_state, attitude_batch, nhc_batch,
                                        single_difference)

LAT, LON = math.radians(35.0), math.radians(139.0)
CNE = C_n_e(LAT, LON)
R0 = geodetic_to_ecef(LAT, LON, 50.0)
C0 = CNE @ euler_to_dcm(0.05, -0.1, 2.2)
V0 = CNE @ np.array([12.0, -5.0, 0.4])


def _perturbed(dx):
    return (R0 + dx[L.pos], V0 + dx[L.vel], rotation_from_rotvec(dx[L.att]) @ C0)


def test_nhc_jacobian_matches_finite_differences():
    b = nhc_batch(V0, C0, 0.1, 0.1)
    for j in list(range(0, 3)) + list(range(6, 9)):
        dx = np.zeros(L.n)
        dx[j] = 1e-6 if j < 3 else 1e-4
        _, v1, C1 = _perturbed(dx)
        predicted_change = (C1.T @ v1)[1:3] - (C0.T @ V0)[1:3]
        # z = 0 - h(x): the measurement model h changes by H dx
        assert np.allclose(predicted_change, b.H[:, j] * dx[j], rtol=1e-3, atol=1e-10)


def test_attitude_jacobian_matches_finite_differences_and_level_heading_is_psi_down():
    meas = GnssAttitude(0.0, heading_rad=2.2, pitch_rad=-0.1, roll_rad=0.05)
    b = attitude_batch(C0, CNE, meas)
    e0 = _euler_of(C0, CNE.T)
    for j in range(3):
        dx = np.zeros(L.n)
        dx[j] = 1e-5
        e1 = _euler_of(_perturbed(dx)[2], CNE.T)
        assert np.allclose(e1 - e0, b.H[:, j] * 1e-5, atol=1e-9)
    level = CNE @ euler_to_dcm(0.0, 0.0, 1.0)
    b = attitude_batch(level, CNE, GnssAttitude(0.0, heading_rad=1.0))
    psi_down_e = CNE[:, 2]
    assert abs(b.H[0, L.att] @ psi_down_e - 1.0) < 1e-6


def test_antenna_lever_arm_jacobian():
    lever = np.array([0.3, -0.1, -0.2])
    ins = InsPoint(0.0, R0, V0, C0, np.zeros(3), 0.0, 0.0)
    r_ant0, _, l_e = antenna_state(ins, lever)
    from companion.nav.earth import skew
    for j in range(3):
        dx = np.zeros(L.n)
        dx[j] = 1e-4   # first-order effect ~4e-5 m; second order ~4e-9 m; ECEF rounding ~1e-9 m
        r1, v1, C1 = _perturbed(dx)
        r_ant1, _, _ = antenna_state(InsPoint(0.0, r1, v1, C1, np.zeros(3), 0.0, 0.0), lever)
        assert np.allclose((r_ant1 - R0) - (r_ant0 - R0), (-skew(l_e))[:, j] * 1e-4, atol=2e-8)


def test_single_differences_cancel_the_clock_and_whiten_the_noise():
    rng = np.random.default_rng(0)
    H = rng.normal(size=(5, L.n))
    H[:, L.clk] = 1.0
    H[:, L.drift] = 1.0
    b = MeasurementBatch("pseudorange", ["G01", "G02", "G03", "G04", "G05"], rng.normal(size=5), H,
                         np.array([1.0, 4.0, 2.0, 1.0, 9.0]))
    sd = single_difference(b, "G03")
    assert len(sd) == 4 and sd.labels[0] == "G01-G03"
    assert np.allclose(sd.H[:, L.clk], 0.0) and np.allclose(sd.H[:, L.drift], 0.0)
    assert np.allclose(sd.r_var, 1.0)
    # whitening preserves the information: H^T R^-1 H of the differenced rows
    D = np.delete(np.eye(5), 2, axis=0) - np.eye(5)[2]
    R = D @ np.diag(b.r_var) @ D.T
    info = (D @ H).T @ np.linalg.solve(R, D @ H)
    assert np.allclose(sd.H.T @ sd.H, info)


def test_tdcp_displacement_error_model_against_two_integrated_trajectories():
    """The INS displacement between two epochs, integrated for a truth and an estimate that differ
    in attitude (psi) and accelerometer bias: its error is dv_k T + (T^2 / 2)([f x] psi + C dba)
    (dv_k the velocity error at the second epoch), the model tdcp_batch's attitude and bias columns
    carry (companion.nav.measurements, with the filter's convention truth = estimate + error)."""
    from companion.nav.strapdown import strapdown_step
    from companion.nav.earth import gravity_ecef, skew
    T, n = 1.0, 400
    tau = T / n
    f_b = np.array([1.5, -0.8, -9.3])           # accelerating while hovering (body, m/s^2)
    psi = np.array([2e-3, -1.5e-3, 3e-3])       # attitude error, ECEF
    dba = np.array([0.02, -0.01, 0.015])        # accelerometer bias error, body
    C_true = rotation_from_rotvec(psi) @ C0
    rt, vt, Ct = R0.copy(), V0.copy(), C_true
    re, ve, Ce = R0.copy(), V0.copy(), C0.copy()
    for _ in range(n):
        rt, vt, Ct = strapdown_step(rt, vt, Ct, np.zeros(3), f_b * tau, tau)
        re, ve, Ce = strapdown_step(re, ve, Ce, np.zeros(3), (f_b + dba) * tau, tau)   # est = true + dba
    D = (rt - R0) - (re - R0)
    dv_k = vt - ve
    f_e = C0 @ f_b
    model = dv_k * T + 0.5 * T * T * (skew(f_e) @ psi + C0 @ dba)
    assert np.linalg.norm(D - model) < 0.02 * np.linalg.norm(D - dv_k * T)
    # and the batch's columns are that model along the line of sight, per unit time
    from companion.gnss.prepare import PreparedEpoch
    from companion.nav.measurements import PhaseRecord, tdcp_batch
    r_sat = R0 + 2.2e7 * np.array([0.3, 0.5, 0.81]) / np.linalg.norm([0.3, 0.5, 0.81])
    z = np.zeros(1)
    prep = PreparedEpoch(t_gps=1.0, signal="L1C", r_approx_e=R0, sats=["G01"], r_sat_e=r_sat[None, :],
                         v_sat_e=np.zeros((1, 3)), pseudorange_m=z, sigma_pseudorange_m=z + 1.0,
                         sat_clock_bias_m=z, sat_clock_drift_mps=z, carrier_cycles=z + 1000.0,
                         wavelength_m=z + 0.19, doppler_hz=z, cn0_dbhz=z + 45.0, lock_time_s=z + 10.0,
                         half_cycle=np.zeros(1, bool), loss_of_lock=np.zeros(1, bool), elevation_rad=z + 1.0,
                         azimuth_rad=z, iode=np.zeros(1, int), dgps_age_s=z, iono_m=z, tropo_m=z)
    u = (r_sat - R0) / np.linalg.norm(r_sat - R0)
    prev = {"G01": PhaseRecord(0.0, 900.0, 0.19, float(np.linalg.norm(r_sat - R0)), 0.0, u, 10.0)}
    ins = InsPoint(1.0, R0, V0, C0, np.zeros(3), 0.0, 0.0)
    b = tdcp_batch(ins, prep, prev, np.zeros(3), 0.005, 0.005, 2.0, specific_force_e=f_e)
    assert np.allclose(b.H[0, L.att] @ psi + b.H[0, L.ba] @ dba + b.H[0, L.vel] @ dv_k,
                       -u @ model / T, rtol=1e-6)
