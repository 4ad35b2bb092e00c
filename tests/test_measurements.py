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
# ---------------------------------------------------------------------------------------------
# IMU time-tag offset dt_imu: the INS point of a measurement is taken dt_imu earlier on the IMU's
# tags, so every GNSS-timed prediction changes by H[:, toff] * dt_imu (companion.nav.filter)

from types import SimpleNamespace  # noqa: E402

from companion.nav.earth import OMEGA_IE_RADPS  # noqa: E402
from companion.nav.measurements import (PhaseRecord, attitude_rate_e, baseline_batch, doppler_batch,  # noqa: E402
                                        horizontal_velocity_fix_batch, line_of_sight, position_fix_batch,
                                        pseudorange_batch, tdcp_batch, velocity_fix_batch)

A0 = CNE @ np.array([1.5, 2.5, -0.8])           # turning and climbing: acceleration in all axes
W0 = np.array([0.05, -0.08, 0.45])              # body rate, rad/s (a coordinated turn)
LEVER = np.array([0.3, -0.1, -0.2])
H_S = 1e-3                                      # finite-difference step of dt_imu, s


def _ins_shifted(dt, t=0.0, r=R0, v=V0, C=C0):
    """The INS point dt seconds earlier along its own motion (constant acceleration and rates):
    what the engine looks up for a measurement when the offset estimate grows by dt."""
    ins = InsPoint(t, r, v, C, W0, 10.0, 0.3, A0)
    rate = attitude_rate_e(ins)
    return InsPoint(t - dt, r - v * dt + 0.5 * A0 * dt * dt, v - A0 * dt, rotation_from_rotvec(-rate * dt) @ C,
                    W0, 10.0, 0.3, A0)


def _prep(t=0.0, r_ant=R0):
    """Five satellites 20,000 km away with orbital velocities, measurements near the truth."""
    rng = np.random.default_rng(4)
    up = CNE[:, 2] * -1.0
    dirs = []
    for k in range(5):
        d = rng.normal(size=3)
        d = d / np.linalg.norm(d)
        dirs.append(d if d @ up > 0.3 else d + up)
    u = np.array([d / np.linalg.norm(d) for d in dirs])
    r_sat = r_ant + 2.0e7 * u
    v_sat = np.cross(u, rng.normal(size=(5, 3))) * 3000.0
    r_sat = r_sat + v_sat * t
    rho, _ = line_of_sight(r_sat, r_ant)
    n = len(rho)
    return SimpleNamespace(t_gps=t, sats=[f"G{k + 1:02d}" for k in range(n)], r_sat_e=r_sat, v_sat_e=v_sat,
                           pseudorange_m=rho + 12.0 + rng.normal(size=n), sigma_pseudorange_m=np.ones(n),
                           doppler_hz=rng.normal(size=n) * 100.0, wavelength_m=np.full(n, 0.19029367),
                           sat_clock_drift_mps=np.zeros(n), sat_clock_bias_m=np.zeros(n),
                           carrier_cycles=(rho + 3.0) / 0.19029367, elevation_rad=np.full(n, 0.5))


def _column_by_differences(batch_of, h=H_S):
    """-(z(+h) - z(-h)) / 2h: the change of the prediction with dt_imu (z = measured - predicted)."""
    return -(batch_of(h).z - batch_of(-h).z) / (2.0 * h)


def _check_column(batch_of, rtol=1e-6, atol=1e-7, h=H_S):
    fd = _column_by_differences(batch_of, h)
    col = batch_of(0.0).H[:, L.toff]
    print(np.c_[col, fd])
    assert np.all(np.abs(col) > 10 * atol), "the test must exercise a non-zero column"
    assert np.allclose(col, fd, rtol=rtol, atol=atol)


def test_time_offset_column_of_pseudoranges():
    prep = _prep()
    _check_column(lambda dt: pseudorange_batch(_ins_shifted(dt), prep, LEVER))


def test_time_offset_column_of_doppler():
    prep = _prep()
    _check_column(lambda dt: doppler_batch(_ins_shifted(dt), prep, LEVER, 0.1), atol=1e-8)


def test_time_offset_column_of_tdcp():
    """Both epochs carry the same tag error: the record of the earlier one is rebuilt with it too."""
    T = 0.2
    r_prev, v_prev = R0 - V0 * T + 0.5 * A0 * T * T, V0 - A0 * T
    C_prev = rotation_from_rotvec(-attitude_rate_e(InsPoint(0.0, R0, V0, C0, W0, 0.0, 0.0)) * T) @ C0
    prep_prev, prep = _prep(-T), _prep(0.0)

    def batch_of(dt):
        ins_prev = _ins_shifted(dt, -T, r_prev, v_prev, C_prev)
        r_ant, v_ant, _ = antenna_state(ins_prev, LEVER)
        rho, u = line_of_sight(prep_prev.r_sat_e, r_ant)
        prev = {s: PhaseRecord(-T, prep_prev.carrier_cycles[i], prep_prev.wavelength_m[i], float(rho[i]), 0.0,
                               u[i], 10.0, float(u[i] @ v_ant)) for i, s in enumerate(prep_prev.sats)}
        return tdcp_batch(_ins_shifted(dt), prep, prev, LEVER, 0.005, 0.01, 1.5)
    # the column is a difference of 2e7-m ranges over T: their rounding (4e-9 m) / T / 2h is 1e-6 at
    # h = 10 ms, where the truncation error (h^2) is 1e-7 (measured: 1.3e-6 at 10 ms, 1.2e-5 at 0.1 s)
    _check_column(batch_of, atol=3e-6, h=1e-2)


def test_time_offset_columns_of_position_and_velocity_fixes():
    cov = np.diag([0.5, 0.7, 1.1]) ** 2
    _check_column(lambda dt: position_fix_batch(_ins_shifted(dt), R0 + 1.0, cov, LEVER))
    _check_column(lambda dt: velocity_fix_batch(_ins_shifted(dt), V0 + 0.1, cov * 0.01, LEVER), atol=1e-8)
    _check_column(lambda dt: horizontal_velocity_fix_batch(_ins_shifted(dt), V0 + 0.1, 0.2, CNE, LEVER), atol=1e-8)
    # a fix tagged on the autopilot's clock (GPS_RAW_INT) shares the IMU's offset: no column
    for b in (position_fix_batch(_ins_shifted(0.0), R0, cov, LEVER, autopilot_clock=True),
              velocity_fix_batch(_ins_shifted(0.0), V0, cov, LEVER, autopilot_clock=True),
              horizontal_velocity_fix_batch(_ins_shifted(0.0), V0, 0.2, CNE, LEVER, autopilot_clock=True)):
        assert np.all(b.H[:, L.toff] == 0.0)


def test_time_offset_columns_of_attitude_and_baseline():
    ins0 = _ins_shifted(0.0)
    rate = attitude_rate_e(ins0)
    assert abs(rate[2] - (C0 @ W0)[2] + OMEGA_IE_RADPS) < 1e-15
    meas = GnssAttitude(0.0, heading_rad=2.2, pitch_rad=-0.1, roll_rad=0.05)
    _check_column(lambda dt: attitude_batch(_ins_shifted(dt).C_b_e, CNE, meas, rate_e=rate), atol=1e-9)
    bl = SimpleNamespace(rel_pos_ned_m=np.array([0.5, 0.2, 0.0]), sigma_ned_m=np.full(3, 0.01))
    _check_column(lambda dt: baseline_batch(_ins_shifted(dt).C_b_e, CNE, bl, np.array([0.6, 0.0, 0.0]),
                                            rate_e=rate), atol=1e-9)
    assert np.all(attitude_batch(C0, CNE, meas).H[:, L.toff] == 0.0)     # autopilot clock: none
