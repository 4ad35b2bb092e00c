"""Tests of the SITL simulator (sitl.scenario / trajectory / sensors / sky / simulate)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.messages import GPS_L1_WAVELENGTH_M as LAMBDA
from companion.messages import gps_time
from companion.nav.earth import C_n_e, geodetic_to_ecef
from companion.nav.strapdown import _log_rotation, strapdown_step
from sitl import sensors
from sitl.scenario import build_scenario
from sitl.simulate import simulate
from sitl.sky import light_time_range, paper_ephemerides, sky_table

_SLOW = ("iono_m", "tropo_m", "orbit_m", "sat_clock_err_m", "sa_m")


@pytest.fixture(scope="module")
def paper():
    return simulate(build_scenario("paper"), 0)


@pytest.fixture(scope="module")
def uav():
    return simulate(build_scenario("uav"), 0)


def _replay(sim, n=None):
    t0, r, v, C = sim.initial_state()
    tr = sim.truth
    n = len(sim.imu) if n is None else n
    dr = dv = da = 0.0
    for i, s in enumerate(sim.imu_ideal[:n]):
        r, v, C = strapdown_step(r, v, C, s.dtheta_b, s.dv_b, s.dt_s)
        dr = max(dr, float(np.linalg.norm(r - tr.r_e[i + 1])))
        dv = max(dv, float(np.linalg.norm(v - tr.v_e[i + 1])))
        da = max(da, float(np.linalg.norm(_log_rotation(C.T @ tr.C_b_e[i + 1]))))
    return dr, dv, da


def test_ideal_imu_reproduces_paper_truth(paper):
    dr, dv, da = _replay(paper)
    assert dr < 1e-3 and dv < 1e-6 and da < 1e-8, (dr, dv, da)


def test_ideal_imu_reproduces_uav_truth(uav):
    dr, dv, da = _replay(uav)
    assert dr < 1e-3 and dv < 1e-6 and da < 1e-8, (dr, dv, da)


def test_imu_errors_applied(paper):
    ie = paper.errors["imu"]
    dt = 1.0 / paper.scenario.imu.rate_hz
    dth = np.array([s.dtheta_b for s in paper.imu])
    np.testing.assert_allclose(dth - paper.imu_ideal_dtheta_b, ie["gyro_error"] * dt, atol=1e-15)
    np.testing.assert_allclose(np.abs(ie["gyro_turn_on_bias"]), 2.424068e-6)
    np.testing.assert_allclose(np.abs(ie["accel_turn_on_bias"]), 0.0249)
    assert np.abs(ie["accel_noise"]).max() <= 0.00637
    assert abs(np.std(ie["accel_noise"]) - 0.00637 / math.sqrt(3)) < 1e-4


def test_paper_sky_at_6s_22e(paper):
    scn = paper.scenario
    r = geodetic_to_ecef(math.radians(-6.0), math.radians(22.0), 1000.0)
    tab = sky_table(paper_ephemerides(1316), r, scn.t0_gps + np.arange(0.0, 501.0, 50.0))
    for sat in ("G01", "G02", "G03", "G05", "G06"):
        assert 10.0 < tab[sat].min() and tab[sat].max() < 30.0, (sat, tab[sat])
    assert tab["G04"].max() < 0.0
    seen = {o.sat for ep in paper.rover_epochs for o in ep.observations}
    assert seen == {"G01", "G02", "G03", "G05", "G06"}
    assert abs(scn.t0_gps - gps_time(1316, 252000.0)) < 0.01


def test_gnss_epochs_not_aligned_with_imu(paper, uav):
    for sim in (paper, uav):
        t_true = sim.errors["rover"]["t_gps"]
        dt = 1.0 / sim.scenario.imu.rate_hz
        off = np.mod(t_true - sim.truth.t_gps[0], dt)
        assert np.all(np.abs(off - 0.0037) < 1e-5)
        b = sim.errors["rover"]["rx_clock_m"]
        assert np.abs(b).max() < 300.0           # steered receiver: sub-microsecond


def _model_check(sim, who):
    e = sim.errors[who]
    kidx = {t: i for i, t in enumerate(e["t_rx_gps"])}
    res_p, res_c, n = [], [], 0
    for ep in (sim.rover_epochs if who == "rover" else sim.base_epochs):
        k = kidx[ep.t_gps]
        assert abs(ep.t_gps - e["rx_clock_m"][k] / 299792458.0 - e["t_gps"][k]) < 1e-12
        for o in ep.observations:
            j = e["sats"].index(o.sat)
            assert e["elevation_rad"][k, j] >= math.radians(sim.scenario.mask_deg)
            common = (e["geometric_m"][k, j] + e["rx_clock_m"][k] - e["sat_clock_brdc_m"][k, j]
                      + e["tropo_m"][k, j] + e["orbit_m"][k, j] + e["sat_clock_err_m"][k, j]
                      + e["sa_m"][k, j])
            res_p.append(o.pseudorange_m - (common + e["iono_m"][k, j] + e["code_mp_m"][k, j]
                                            + e["code_noise_m"][k, j]))
            res_c.append(o.carrier_cycles - e["ambiguity_cycles"][k, j]
                         - (common - e["iono_m"][k, j] + e["carrier_mp_m"][k, j]
                            + e["carrier_noise_m"][k, j]) / LAMBDA)
            n += 1
            if n % 97 == 0:   # independent recomputation of the geometric range from truth
                if who == "rover":
                    r_ant = sim.antenna_at(e["t_gps"][k])
                else:
                    r_ant = sim.base.r_e
                eph = next(x for x in sim.ephemerides if x.sat == o.sat)
                rho = light_time_range(eph, e["t_gps"][k], r_ant)[0]
                assert abs(rho - e["geometric_m"][k, j]) < 1e-3
    return np.abs(res_p).max(), np.abs(res_c).max() * LAMBDA


@pytest.mark.parametrize("who", ["rover", "base"])
def test_observables_equal_geometry_plus_injected_errors(paper, uav, who):
    for sim in (paper, uav):
        rp, rc = _model_check(sim, who)
        assert rp < 1e-3 and rc < 1e-3, (sim.scenario.name, who, rp, rc)


def test_doppler_consistent_with_carrier(uav):
    """TDCP over 1 s vs the mean of the two Dopplers: differ only by noise and clock white FM."""
    eps = uav.rover_epochs
    d = []
    for a, b in zip(eps[:-1], eps[1:]):
        if b.t_gps - a.t_gps > 1.5:
            continue
        oa = {o.sat: o for o in a.observations}
        for o in b.observations:
            if o.sat in oa and not o.loss_of_lock:
                tdcp = (o.carrier_cycles - oa[o.sat].carrier_cycles) * LAMBDA
                d.append(tdcp + 0.5 * (o.doppler_hz + oa[o.sat].doppler_hz) * LAMBDA)
    d = np.array(d)
    assert abs(d.mean()) < 0.02 and d.std() < 0.2


def test_dgps_residuals_match_table1(paper):
    er, eb = paper.errors["rover"], paper.errors["base"]
    scn = paper.scenario
    # the common parts cancel exactly; what is left is the differential (DGPS column) part
    for c in ("sat_clock_err_m", "sa_m"):
        assert np.nanmax(np.abs(er[c] - eb[c])) < 1e-6   # epochs differ by the clocks (sub-us)
    assert np.nanstd(er["sa_m"]) > 20.0                      # SA present at both receivers
    # between-satellite single difference of base-corrected pseudoranges, minus geometry
    sats = er["sats"]
    i, j = sats.index("G02"), sats.index("G03")

    def corrected(k, s):
        pr = lambda eps, kk: next(o.pseudorange_m for o in eps[kk].observations if o.sat == sats[s])
        return (pr(paper.rover_epochs, k) - pr(paper.base_epochs, k)
                - (er["geometric_m"][k, s] - eb["geometric_m"][k, s]))

    K = len(paper.rover_epochs)
    sd = np.array([corrected(k, i) - corrected(k, j) for k in range(K)])
    sig_d2 = (sum(getattr(scn, s).sigma_diff_m ** 2 for s in ("iono", "tropo", "sat_clock", "sa"))
              + scn.orbit.sigma_los_diff_m ** 2
              + scn.rover_rx.code_mp_m ** 2 + scn.rover_rx.code_noise_m ** 2
              + scn.base_rx.code_mp_m ** 2 + scn.base_rx.code_noise_m ** 2)
    # Table 1 DGPS column as uniform bounds: (0.5^2+0.2^2+0+0.3^2+1+1)/3 per satellite
    assert abs(sig_d2 - (0.25 + 0.04 + 0.09 + 1 + 1) / 3 - 0.1 ** 2 - 0.15 ** 2) < 1e-9
    expected = math.sqrt(2.0 * sig_d2)
    assert 0.7 * expected < sd.std() < 1.3 * expected, (sd.std(), expected)
    assert abs(sd.mean()) < 0.6
    # fast part (many independent samples): tight
    fast = (er["code_mp_m"] + er["code_noise_m"] - eb["code_mp_m"] - eb["code_noise_m"])[:, [i, j]]
    exp_fast = math.sqrt(scn.rover_rx.code_mp_m ** 2 + scn.rover_rx.code_noise_m ** 2
                         + scn.base_rx.code_mp_m ** 2 + scn.base_rx.code_noise_m ** 2)
    assert abs(fast.std() / exp_fast - 1.0) < 0.1
    # without the base correction the rover errors are the GPS column (SA dominated)
    raw = sum(er[c] for c in _SLOW)[:, [i, j]]
    assert raw.std() > 10 * sd.std()


def test_gm2_process_statistics():
    rng = np.random.default_rng(5)
    tau = 20.0
    x = sensors.gm2_unit_grid(rng, 1000, 1.0, tau, 400)
    assert abs(x.std() - 1.0) < 0.05
    rate = sensors.SmoothProcess(np.arange(1000.0), x).rate(np.arange(10.0, 990.0))
    assert abs(rate.std() * tau - 1.0) < 0.1
    # smooth: the 1-s change is small compared with the std
    assert np.abs(np.diff(x, axis=0)).max() < 0.5


def test_reproducible_and_seed_dependent():
    for name in ("paper", "uav"):
        scn = dataclasses.replace(build_scenario(name), duration_s=8.0)
        a, b, c = simulate(scn, 7), simulate(scn, 7), simulate(scn, 8)
        pa = np.array([o.pseudorange_m for ep in a.rover_epochs for o in ep.observations])
        pb = np.array([o.pseudorange_m for ep in b.rover_epochs for o in ep.observations])
        pc = np.array([o.pseudorange_m for ep in c.rover_epochs for o in ep.observations])
        ia = np.array([s.dv_b for s in a.imu])
        ib = np.array([s.dv_b for s in b.imu])
        ic = np.array([s.dv_b for s in c.imu])
        assert np.array_equal(pa, pb) and np.array_equal(ia, ib)
        assert not np.array_equal(pa, pc) and not np.array_equal(ia, ic)
        np.testing.assert_array_equal(a.truth.r_e, c.truth.r_e)     # truth is seed-free


def test_cycle_slip_injection():
    scn = dataclasses.replace(build_scenario("paper"), duration_s=12.0)
    t_slip = scn.t0_gps + 6.5
    slipped = dataclasses.replace(scn, cycle_slips=((t_slip, "G02", 7),))
    a, b = simulate(scn, 1), simulate(slipped, 1)
    for ea, eb in zip(a.rover_epochs, b.rover_epochs):
        oa = {o.sat: o for o in ea.observations}
        for o in eb.observations:
            d = o.carrier_cycles - oa[o.sat].carrier_cycles
            if o.sat == "G02" and ea.t_gps >= t_slip:
                assert d == pytest.approx(7.0, abs=1e-6)
                assert o.lock_time_s == ea.t_gps - math.ceil(t_slip)
                assert o.loss_of_lock == (ea.t_gps == math.ceil(t_slip))
            else:
                assert d == 0.0 and not o.loss_of_lock
    lt = [o.lock_time_s for ep in a.rover_epochs for o in ep.observations if o.sat == "G02"]
    assert lt == sorted(lt) and lt[0] == 0.0


def test_uav_flight_profile(uav):
    scn = uav.scenario
    tr = uav.truth
    lat, lon, _ = scn.trajectory.origin_llh
    ned = (tr.r_e - tr.r_e[0]) @ C_n_e(lat, lon)
    t_rel = tr.t_gps - tr.t_gps[0]
    ev = {name: (a, b) for name, a, b in scn.trajectory.events}
    # climb to ~50 m and back down
    assert -ned[:, 2].max() < 0.01 and 49.0 < -ned[:, 2].min() < 51.0
    assert abs(ned[-1, 2]) < 0.5
    # hover: still, at 50 m
    a, b = ev["hover"]
    m = (t_rel > a + 1) & (t_rel < b - 1)
    assert np.linalg.norm(tr.v_e[m], axis=1).max() < 0.05 and np.all(-ned[m, 2] > 49.0)
    # survey legs at 9 m/s, turns of 180 deg at ~0.45 rad/s with ~22 deg bank
    a, b = ev["leg2"]
    m = (t_rel > a + 1) & (t_rel < b - 1)
    assert np.allclose(np.linalg.norm(tr.v_e[m], axis=1), 9.0, atol=0.01)
    dth = uav.imu_ideal_dtheta_b * scn.imu.rate_hz
    a, b = ev["turn1"]
    m = (t_rel[1:] > a) & (t_rel[1:] < b)
    yaw_rate_n = np.abs((tr.C_b_e[1:][m] @ dth[m][:, :, None])[:, :, 0] @ C_n_e(lat, lon)[:, 2])
    assert 0.43 < yaw_rate_n.max() < 0.47
    roll = np.degrees(np.arctan2((tr.C_b_e @ np.array([0, 1.0, 0]) @ C_n_e(lat, lon))[:, 2],
                                 (tr.C_b_e @ np.array([0, 0, 1.0]) @ C_n_e(lat, lon))[:, 2]))
    assert 20.0 < np.abs(roll[(t_rel > a) & (t_rel < b)]).max() < 25.0
    # smooth: angular rate continuous (no jump larger than 0.01 rad/s between 5-ms samples)
    assert np.abs(np.diff(dth, axis=0)).max() < 0.01
    # 30-s rover outage, base keeps going
    t_r = uav.errors["rover"]["t_gps"][uav.errors["rover"]["emitted"]]
    gaps = np.diff(t_r)
    assert gaps.max() == pytest.approx(31.0, abs=1e-3) and np.sum(gaps > 1.5) == 1
    assert len(uav.base_epochs) == len(uav.errors["base"]["t_gps"])
    # after the outage every satellite re-acquires: new lock, loss_of_lock flagged
    k = int(np.argmax(gaps)) + 1
    ep = uav.rover_epochs[k]
    assert all(o.loss_of_lock and o.lock_time_s == 0.0 for o in ep.observations)
    assert len(ep.observations) >= 6
