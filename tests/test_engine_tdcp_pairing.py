"""Base-corrected TDCP with real receivers' epoch tags (issue 11): the rover tags x.987-x.992 s
(u-blox M8P, clock bias -8.4 to -13.3 ms), the base x.000.  The 5-ms pairing matched nothing
(0 corrected epochs against 1175/1130/2005 uncorrected on three sessions)."""
from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from companion.messages import GPS_L1_WAVELENGTH_M
from companion.nav.engine import EngineConfig, NavEngine
from companion.nav.filter import ProcessNoise

LAM = GPS_L1_WAVELENGTH_M
T0 = 1354928960.0
RNG = np.random.default_rng(11)
# per satellite: range at T0 (m), range rate (m/s, up to the ~800 m/s of a low MEO satellite),
# range acceleration (m/s^2), and its slow unexplained error (orbit, satellite clock, ionosphere):
# offset (m), rate (m/s, up to 2 cm/s) and curvature (m/s^2)
SATS = {f"G{k:02d}": (2.1e7 + 1e6 * k, rr, 0.1 * (k % 3 - 1), 0.3 * k, er, 1e-4 * (k % 2 - 0.5))
        for k, (rr, er) in enumerate(zip((-780.0, -420.0, -35.0, 260.0, 610.0, 795.0),
                                         (0.02, -0.015, 0.004, 0.0, -0.02, 0.011)), start=1)}


def _rho(sat, t):
    r0, rr, ra, *_ = SATS[sat]
    dt = t - T0
    return r0 + rr * dt + 0.5 * ra * dt * dt


def _err(sat, t):
    *_, e0, er, ea = SATS[sat]
    dt = t - T0
    return e0 + er * dt + 0.5 * ea * dt * dt


def _base_clock_m(t):
    return 30.0 + 0.9 * (t - T0)         # a drifting base clock: common to all satellites


def _engine_with_base_history(base_times):
    eng = NavEngine(EngineConfig(noise=ProcessNoise(1e-4, 1e-3, 1e-5, 1e-4)))
    for sat in SATS:
        hist = eng.base_carrier.history.setdefault(sat, deque(maxlen=8))
        for t in base_times:
            carrier = (_rho(sat, t) + _base_clock_m(t) + _err(sat, t)) / LAM
            # the satellite clock change is "explained" (broadcast): it enters both sides alike
            hist.append((t, carrier, LAM, _rho(sat, t), 0.0))
    return eng


def _truth(t_a, t_b):
    """What the rover's TDCP over its own (t_a, t_b) needs: minus the per-satellite error change,
    common part removed (median, as the engine does)."""
    d = {sat: _err(sat, t_b) - _err(sat, t_a) for sat in SATS}
    common = float(np.median(list(d.values())))
    return {sat: -(v - common) for sat, v in d.items()}


def test_tdcp_base_pairing_with_real_rover_tags():
    base_times = [T0 + k for k in range(8)]
    eng = _engine_with_base_history(base_times)
    worst = 0.0
    n = 0
    for k in range(1, 7):
        # rover tags 8-13 ms before the base's, varying epoch to epoch as the clock drifts
        t_a = T0 + k - 1 - RNG.uniform(0.008, 0.013)
        t_b = T0 + k - RNG.uniform(0.008, 0.013)
        # the defect: the old 5-ms tolerance pairs nothing
        assert eng.base_carrier.tdcp_corrections(t_a, t_b, tol_s=0.005) == {}
        corr = eng.base_carrier.tdcp_corrections(t_a, t_b)
        want = _truth(t_a, t_b)
        assert set(corr) == set(SATS)
        worst = max(worst, max(abs(corr[s] - want[s]) for s in SATS))
        n += 1
    # the uncorrected alternative errs by the per-satellite error change itself (cm)
    uncorrected = max(abs(v) for v in _truth(T0 - 0.01, T0 + 0.99).values())
    print(f"pairing at 8-13 ms offsets: {n} intervals, worst correction error {worst * 1e3:.4f} mm "
          f"(uncorrected {uncorrected * 1e3:.1f} mm)")
    assert worst < 2e-4 and uncorrected > 0.01


def test_tdcp_base_pairing_is_unambiguous_and_bounded():
    base_times = [T0 + 0.2 * k for k in range(8)]          # a 5-Hz base
    eng = _engine_with_base_history(base_times)
    # 100 ms from every base epoch (a 10-Hz rover between the base's): no pairing, never a wrong one
    assert eng.base_carrier.tdcp_corrections(T0 + 0.1, T0 + 0.3) == {}
    # the same base epoch for both ends (an interval shorter than the base's): no correction
    assert eng.base_carrier.tdcp_corrections(T0 + 0.19, T0 + 0.21) == {}
    corr = eng.base_carrier.tdcp_corrections(T0 + 0.19, T0 + 0.39)
    want = _truth(T0 + 0.19, T0 + 0.39)
    assert max(abs(corr[s] - want[s]) for s in SATS) < 2e-4


def test_tdcp_base_phase_needs_no_shift_to_the_rover_instant():
    """The range changes by up to 10 m over the 13-ms offset, yet the correction is right without
    any shift: the base residual is formed against ranges at the base's own epochs (a Doppler shift
    of the carrier alone would need the ranges shifted too, and would add the Doppler noise)."""
    eng = _engine_with_base_history([T0, T0 + 1.0])
    t_a, t_b = T0 - 0.013, T0 + 1.0 - 0.008
    range_change = max(abs(_rho(s, T0) - _rho(s, t_a)) for s in SATS)
    assert range_change > 10.0
    corr = eng.base_carrier.tdcp_corrections(t_a, t_b)
    want = _truth(t_a, t_b)
    assert max(abs(corr[s] - want[s]) for s in SATS) < 2e-4
