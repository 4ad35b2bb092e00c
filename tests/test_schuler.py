"""Free-inertial error of our ECEF mechanization against the analytic Schuler solution (seed 004 eqs 1-2)."""
import math

import numpy as np
import pytest

from companion.nav.free_inertial import (FreeInertialCase, fit_sinusoid_period, run_free_inertial,
                                          schuler_velocity_error)

PAPER_SCHULER_PERIOD_S = 84.4 * 60.0

CASES = [
    FreeInertialCase("initial velocity error", dv0_n_mps=(0.10, -0.05, 0.0)),
    FreeInertialCase("accelerometer bias", accel_bias_n_mps2=(2e-4, -1e-4, 0.0)),
    FreeInertialCase("tilt about north", tilt0_n_rad=(1e-4, 0.0, 0.0)),
    FreeInertialCase("gyro drift about north", gyro_bias_n_radps=(5e-8, 0.0, 0.0)),
]


@pytest.mark.parametrize("case", CASES, ids=lambda c: c.name)
def test_free_inertial_error_follows_schuler_solution(case):
    t, dv_ne, _ = run_free_inertial(case)
    analytic = schuler_velocity_error(case, t)
    amplitude = np.max(np.abs(analytic))
    rel_dev = np.max(np.abs(dv_ne - analytic)) / amplitude
    print(f"{case.name}: amplitude {amplitude:.4g} m/s, max relative deviation {rel_dev:.4f}")
    assert rel_dev < 0.05


def test_schuler_period_and_amplitude_of_initial_velocity_error():
    case = CASES[0]
    t, dv_ne, _ = run_free_inertial(case)
    period_s, amplitude = fit_sinusoid_period(t, dv_ne[:, 0], PAPER_SCHULER_PERIOD_S)
    print(f"fitted Schuler period {period_s / 60:.2f} min, amplitude {amplitude:.4f} m/s")
    assert abs(period_s - PAPER_SCHULER_PERIOD_S) / PAPER_SCHULER_PERIOD_S < 0.01
    assert abs(amplitude - 0.10) / 0.10 < 0.05


def test_error_free_stationary_ins_stays_put():
    t, dv_ne, dp_ne = run_free_inertial(FreeInertialCase("none", hours=0.5))
    assert np.max(np.abs(dv_ne)) < 1e-6
    assert np.max(np.abs(dp_ne)) < 1e-3


def test_invert_step_is_the_exact_inverse_of_strapdown_step_while_moving():
    """A moving, turning body: increments from invert_step reproduce the next state exactly
    (this caught a Coriolis sign that differed between the two)."""
    from companion.nav.earth import C_n_e, euler_to_dcm, geodetic_to_ecef, rotation_from_rotvec
    from companion.nav.strapdown import invert_step, strapdown_step
    lat, lon = math.radians(35.0), math.radians(139.0)
    r0 = geodetic_to_ecef(lat, lon, 500.0)
    C0 = C_n_e(lat, lon) @ euler_to_dcm(0.1, -0.2, 2.0)
    v0 = C_n_e(lat, lon) @ np.array([40.0, -25.0, 3.0])
    C1 = C0 @ rotation_from_rotvec([0.002, -0.001, 0.004])
    v1 = v0 + np.array([0.05, -0.03, 0.02])
    dth, dv = invert_step(r0, v0, C0, v1, C1, 0.005)
    r2, v2, C2 = strapdown_step(r0, v0, C0, dth, dv, 0.005)
    assert np.max(np.abs(v2 - v1)) < 1e-12
    assert np.max(np.abs(C2 - C1)) < 1e-14
