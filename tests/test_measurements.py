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
