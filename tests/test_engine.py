"""The fusion engine: GPS-time interpolation, arrival-order independence, determinism, bad input,
receiver clock jumps, zero-rate updates and statistical consistency (NEES)."""
import dataclasses
import math

import numpy as np
import pytest
from scipy.stats import chi2

from companion.messages import GnssEpoch, GnssFix, ImuSample
from companion.nav.earth import C_n_e, ecef_to_geodetic, geodetic_to_ecef, rotation_from_rotvec
from companion.nav.engine import EngineConfig, NavEngine
from companion.nav.filter import LAYOUT, ProcessNoise
from companion.nav.strapdown import invert_step
from sitl.paper import initial_errors, run_ins_mode
from sitl.scenario import build_scenario
from sitl.simulate import simulate
from sitl.tuning import tuning_for

NOISE = ProcessNoise(1e-6, 1e-4, 1e-9, 1e-7)
P0 = dict(tilt_rad=1e-3, heading_rad=1e-3, pos_m=0.5, vel_mps=0.05, ba_mps2=0.03, bg_radps=1e-5)


def _straight_line_imu(v_n=(50.0, -20.0, 1.0), rate_hz=100.0, seconds=2.0):
    """Truth moving at constant ECEF velocity with a fixed attitude, and its exact increments."""
    lat, lon = math.radians(35.0), math.radians(139.0)
    r0 = geodetic_to_ecef(lat, lon, 100.0)
    C = C_n_e(lat, lon)
    v = C @ np.array(v_n)
    tau = 1.0 / rate_hz
    t0 = 1.4e9
    samples, rs = [], [r0]
    r = r0
    for k in range(int(seconds * rate_hz)):
        dth, dv = invert_step(r, v, C, v, C, tau)
        samples.append(ImuSample(t0 + (k + 1) * tau, tau, dth, dv))
        r = r + v * tau
        rs.append(r)
    return t0, r0, v, C, samples, np.array(rs)


def test_gnss_epoch_uses_ins_interpolated_to_its_gps_time():
    t0, r0, v, C, samples, rs = _straight_line_imu()
    eng = NavEngine(EngineConfig(noise=NOISE))
    eng.initialize(t0, r0, v, C, P0)
    for s in samples:
        eng.process_imu(s)
    t_epoch = t0 + 1.0037  # 3.7 ms after an IMU sample, as real receivers do
    ins = eng.ins_at(t_epoch)
    truth = r0 + v * (t_epoch - t0)
    nearest = rs[int(round((t_epoch - t0) * 100))]
    err_interp = np.linalg.norm(ins.r_e - truth)
    err_nearest = np.linalg.norm(nearest - truth)
    print(f"interpolated {err_interp:.2e} m, nearest sample {err_nearest:.3f} m")
    assert err_interp < 1e-4
    assert err_nearest > 0.1  # what the interpolation buys at 54 m/s


def _paper_sim(seconds=60.0, seed=3):
    scn = build_scenario("paper")
    scn = dataclasses.replace(scn, duration_s=seconds,
                              trajectory=dataclasses.replace(scn.trajectory, duration_s=seconds))
    return scn, simulate(scn, seed)


@pytest.fixture(scope="module")
def paper60():
    return _paper_sim()


def test_late_epochs_from_history_match_early_epochs_from_the_queue(paper60):
    scn, sim = paper60
    tun = tuning_for(scn)
    early = run_ins_mode("tdcp_dgps", sim, tun, 3, keep_engine=True)
    late = run_ins_mode("tdcp_dgps", sim, dataclasses.replace(tun, gnss_latency_s=0.08), 3, keep_engine=True)
    d = np.linalg.norm(early["engine"].r_e - late["engine"].r_e)
    print(f"final difference early/late arrival: {d * 100:.2f} cm; errors {early['err_3d_m'][-1]:.3f} "
          f"/ {late['err_3d_m'][-1]:.3f} m")
    # the last epoch (t0 + 59.994 s) arrives 80 ms later, after the IMU stream has ended
    assert early["engine"].counters["gnss epochs"] == 60
    assert late["engine"].counters["gnss epochs"] == 59
    assert d < 0.05
    assert late["err_3d_m"].max() < 3.0


def test_same_input_gives_bit_identical_output(paper60):
    scn, sim = paper60
    tun = tuning_for(scn)
    a = run_ins_mode("tdcp_dgps", sim, tun, 5, keep_engine=True)["engine"]
    b = run_ins_mode("tdcp_dgps", sim, tun, 5, keep_engine=True)["engine"]
    assert np.array_equal(a.r_e, b.r_e) and np.array_equal(a.kf.P, b.kf.P) and np.array_equal(a.C_b_e, b.C_b_e)


def test_bad_imu_samples_are_dropped_counted_and_navigation_continues():
    t0, r0, v, C, samples, rs = _straight_line_imu(seconds=1.0)
    eng = NavEngine(EngineConfig(noise=NOISE))
    eng.initialize(t0, r0, v, C, P0)
    nan = ImuSample(samples[10].t_gps, 0.01, np.array([np.nan, 0, 0]), samples[10].dv_b)
    for k, s in enumerate(samples):
        if k == 10:
            eng.process_imu(nan)
        if k == 20:
            eng.process_imu(samples[5])   # a stale sample, time going backwards
        eng.process_imu(s)
    assert eng.counters["imu sample invalid (dropped)"] == 1
    assert eng.counters["imu sample not after previous (dropped)"] == 1
    assert np.linalg.norm(eng.r_e - rs[-1]) < 1e-3
    assert np.all(np.isfinite(eng.kf.P))


def test_lost_imu_samples_are_bridged_not_skipped():
    """Half a second of IMU messages lost on the link at 54 m/s: the sample after the gap is held
    over it, so the position keeps up with the vehicle (skipping the interval left it 27 m behind,
    unseen by the covariance), and the covariance grows by what the vehicle could have done."""
    t0, r0, v, C, samples, rs = _straight_line_imu(seconds=2.0)
    eng = NavEngine(EngineConfig(noise=NOISE))
    eng.initialize(t0, r0, v, C, P0)
    lost = range(100, 150)                   # 0.5 s
    for k, s in enumerate(samples):
        if k == lost[-1] + 1:
            var_vel_before = float(np.trace(eng.kf.P[LAYOUT.vel, LAYOUT.vel]))
        if k not in lost:
            eng.process_imu(s)
        if k == lost[-1] + 1:
            grown = float(np.trace(eng.kf.P[LAYOUT.vel, LAYOUT.vel])) - var_vel_before
    assert eng.counters["imu time gap"] == 1
    assert np.linalg.norm(eng.r_e - rs[-1]) < 1e-3
    assert grown > 3 * (1.0 * 0.5) ** 2


def _shift_clock(epochs, t_from, jump_m):
    """A receiver clock reset: every pseudorange and carrier jumps by the same range."""
    out = []
    for e in epochs:
        if e.t_gps < t_from:
            out.append(e)
            continue
        obs = tuple(dataclasses.replace(o, pseudorange_m=o.pseudorange_m + jump_m,
                                        carrier_cycles=o.carrier_cycles + jump_m / o.wavelength_m)
                    for o in e.observations)
        out.append(GnssEpoch(e.t_gps, obs, e.source))
    return out


@pytest.mark.parametrize("jump_s", [1e-3, 1e-6], ids=["1 ms", "1 us"])
def test_receiver_clock_jump_is_detected_reseeded_and_navigation_recovers(paper60, jump_s):
    scn, sim = paper60
    original = sim.rover_epochs
    try:
        sim.rover_epochs = _shift_clock(original, sim.truth.t_gps[0] + 30.0, 299792458.0 * jump_s)
        res = run_ins_mode("tdcp_dgps", sim, tuning_for(scn), 3, keep_engine=True)
    finally:
        sim.rover_epochs = original
    c = res["engine"].counters
    assert c["receiver clock jump re-seeded"] == 1
    assert res["err_3d_m"][-1] < 3.0
    assert c["pseudorange used"] > 4 * 50


def test_zero_rate_updates_estimate_the_gyro_bias_at_rest():
    lat, lon = math.radians(35.0), math.radians(139.0)
    r0 = geodetic_to_ecef(lat, lon, 10.0)
    C = C_n_e(lat, lon)
    tau = 0.005
    dth, dv = invert_step(r0, np.zeros(3), C, np.zeros(3), C, tau)
    bias = np.array([0.002, -0.001, 0.004])  # rad/s, a MEMS turn-on bias
    rng = np.random.default_rng(0)
    cfg = EngineConfig(noise=ProcessNoise(5e-5, 1e-3, 1e-6, 1e-5), zupt_enabled=True)
    eng = NavEngine(cfg)
    eng.initialize(1.4e9, r0, np.zeros(3), C, dict(P0, bg_radps=0.01, ba_mps2=0.1))
    for k in range(int(20 / tau)):
        noise = rng.normal(0, 5e-5 / math.sqrt(tau), 3) * tau
        eng.process_imu(ImuSample(1.4e9 + (k + 1) * tau, tau, dth + bias * tau + noise, dv))
    print("estimated gyro bias", eng.b_g, "counters", dict(eng.counters))
    assert eng.counters["zaru used"] > 0
    assert np.max(np.abs(eng.b_g - bias)) < 1e-4
    assert np.linalg.norm(eng.v_e) < 0.01


def test_nees_is_consistent_when_the_filter_model_matches_the_truth():
    """Monte Carlo: paper IMU (white noise + constant biases, as the filter models them), loose
    position/velocity fixes with white Gaussian noise of the stated sigma.  The run-averaged NEES of
    the 9 navigation states must sit inside its two-sided 95 % chi-square band most of the time."""
    scn, sim = _paper_sim(seconds=100.0, seed=7)
    tun = tuning_for(scn)
    runs = 12
    sig_h, sig_v, sig_vel = 0.5, 0.8, 0.05
    truth = sim.truth
    nees_runs = []
    from sitl.simulate import simulate as sim_fn
    for r in range(runs):
        s = sim_fn(scn, 100 + r)
        rng = np.random.default_rng(200 + r)
        eng = NavEngine(EngineConfig(noise=tun.noise, use_pseudorange=False, use_tdcp=False, use_dgps=False))
        d_att, d_pos, d_vel = initial_errors(rng, tun.p0, truth.r_e[0])
        eng.initialize(truth.t_gps[0], s.truth.r_e[0] + d_pos, s.truth.v_e[0] + d_vel,
                       rotation_from_rotvec(d_att) @ s.truth.C_b_e[0], tun.p0)
        Cne = C_n_e(math.radians(-6.0), math.radians(22.0))
        nees = []
        next_fix = 1
        for k, smp in enumerate(s.imu, start=1):
            eng.process_imu(smp)
            if smp.t_gps - s.truth.t_gps[0] >= next_fix:
                noise_n = rng.normal(0, 1, 3) * np.array([sig_h / math.sqrt(2), sig_h / math.sqrt(2), sig_v])
                eng.process_fix(GnssFix(smp.t_gps, s.truth.r_e[k] + Cne @ noise_n,
                                        s.truth.v_e[k] + rng.normal(0, sig_vel, 3), sig_h, sig_v, sig_vel))
                next_fix += 1
                e = np.empty(9)
                dC = s.truth.C_b_e[k] @ eng.C_b_e.T
                e[0:3] = 0.5 * np.array([dC[2, 1] - dC[1, 2], dC[0, 2] - dC[2, 0], dC[1, 0] - dC[0, 1]])
                e[3:6] = s.truth.r_e[k] - eng.r_e
                e[6:9] = s.truth.v_e[k] - eng.v_e
                nav = np.r_[LAYOUT.att, LAYOUT.pos, LAYOUT.vel]     # e's order
                nees.append(float(e @ np.linalg.solve(eng.kf.P[np.ix_(nav, nav)], e)))
        nees_runs.append(nees)
    avg = np.mean(np.array(nees_runs), axis=0)
    lo, hi = chi2.ppf(0.025, 9 * runs) / runs, chi2.ppf(0.975, 9 * runs) / runs
    inside = np.mean((avg >= lo) & (avg <= hi))
    print(f"run-averaged NEES: mean {avg.mean():.2f} (expected 9), band [{lo:.2f}, {hi:.2f}], "
          f"{inside * 100:.0f} % of epochs inside")
    assert lo <= avg.mean() <= hi
    assert inside >= 0.80


def _fly_uav_with_imu_tags_late(sim, late_s, sigma_s):
    """Engine level, tdcp_dgps on the 'uav' flight: the IMU's tags are ``late_s`` behind GPS time
    (SYSTEM_TIME late), the GNSS epochs carry receiver time and arrive 80 ms late.  Returns the
    horizontal error at 1 Hz (truth at the samples' GPS time) and the engine."""
    from sitl.paper import mode_config
    tun = tuning_for(sim.scenario)
    noise = dataclasses.replace(tun.noise, imu_time_offset_rw_s_per_sqrt_s=1e-4 if sigma_s > 0 else 0.0)
    eng = NavEngine(dataclasses.replace(mode_config("tdcp_dgps", tun, sim.lever_arm_b), noise=noise,
                                        imu_time_offset_sigma_s=sigma_s))
    for e in sim.ephemerides:
        eng.process(e)
    eng.process(sim.base)
    truth = sim.truth
    d_att, d_pos, d_vel = initial_errors(np.random.default_rng(10_003), tun.p0, truth.r_e[0])
    eng.initialize(truth.t_gps[0] - late_s, truth.r_e[0] + d_pos, truth.v_e[0] + d_vel,
                   rotation_from_rotvec(d_att) @ truth.C_b_e[0], tun.p0)
    up = -C_n_e(*ecef_to_geodetic(truth.r_e[0])[:2])[:, 2]
    rov, base = sim.rover_epochs, sim.base_epochs
    i_r = i_b = 0
    err_h = []
    for k, s in enumerate(sim.imu, start=1):
        while i_b < len(base) and base[i_b].t_gps + 0.08 <= s.t_gps:
            eng.process(base[i_b])
            i_b += 1
        while i_r < len(rov) and rov[i_r].t_gps + 0.08 <= s.t_gps:
            eng.process(rov[i_r])
            i_r += 1
        eng.process_imu(ImuSample(s.t_gps - late_s, s.dt_s, s.dtheta_b, s.dv_b, s.imu_id))
        if k % 200 == 0:
            d = eng.r_e - truth.r_e[k]
            err_h.append(float(np.linalg.norm(d - up * (d @ up))))
    return np.array(err_h), eng


def test_imu_time_tag_offset_is_estimated_in_flight():
    """80 ms between the IMU's tags and GPS time: the dt_imu state finds it within 10 ms by the
    end of the 70-s flight (climb, acceleration, first turn), and the position after 40 s is as
    good as with exact tags; without the state the same flight is much worse."""
    from sitl.fly import load_sim
    from companion.nav.filter import LAYOUT
    sim = load_sim("uav", 0, 70.0)
    err_late, eng = _fly_uav_with_imu_tags_late(sim, 0.08, 0.1)
    err_exact, eng_exact = _fly_uav_with_imu_tags_late(sim, 0.0, 0.1)
    err_ignored, _ = _fly_uav_with_imu_tags_late(sim, 0.08, 0.0)
    sigma = math.sqrt(eng.kf.P[LAYOUT.toff, LAYOUT.toff])
    rms = {name: float(np.sqrt(np.mean(e[40:] ** 2))) for name, e in
           (("late", err_late), ("exact", err_exact), ("ignored", err_ignored))}
    print(f"offset {eng.imu_time_offset_s * 1e3:.1f} +- {sigma * 1e3:.1f} ms (exact tags: "
          f"{eng_exact.imu_time_offset_s * 1e3:.1f} ms); horizontal RMS after 40 s {rms}")
    assert abs(eng.imu_time_offset_s - 0.08) < 0.010 and sigma < 0.010
    assert abs(eng_exact.imu_time_offset_s) < 0.010
    assert eng.solution().extras["imu_time_offset_s"] == eng.imu_time_offset_s
    assert rms["late"] <= 1.1 * rms["exact"]
    assert rms["ignored"] > 1.5 * rms["exact"]


def test_time_offset_lookup_and_plausibility():
    """Receiver-timed messages are predicted at t - dt_imu on the IMU's tags, autopilot-timed ones
    (GPS_RAW_INT, ATTITUDE) at their own tag; an estimate beyond 3 prior sigmas is a divergence."""
    from companion.io.mavlink_time import BootToGpsTime
    from companion.io.mavlink_decode import gps_fix_from_gps_raw_int
    from companion.messages import GnssAttitude
    from pymavlink.dialects.v20 import ardupilotmega as mavlink2
    from companion.nav.integrity import IntegrityState
    t0, r0, v, C, samples, rs = _straight_line_imu(seconds=0.5)
    eng = NavEngine(EngineConfig(noise=NOISE, imu_time_offset_s=0.02, imu_time_offset_sigma_s=0.1))
    eng.initialize(t0, r0, v, C, P0)
    assert eng.imu_time_offset_s == 0.02 and eng.kf.P[eng.layout.toff, eng.layout.toff] == pytest.approx(0.01)
    eng.imu_time_offset_s = 0.08
    t = t0 + 0.3
    assert eng.imu_time_of(GnssEpoch(t, ())) == pytest.approx(t - 0.08)
    assert eng.imu_time_of(GnssAttitude(t, heading_rad=0.0)) == pytest.approx(t - 0.08)
    assert eng.imu_time_of(GnssAttitude(t, heading_rad=0.0, autopilot_clock=True)) == t
    tm = BootToGpsTime()
    tm.update_system_time(int((t0 + 1e9) * 1e6), 100_000)
    raw = mavlink2.MAVLink_gps_raw_int_message(150_000_000, 3, 350000000, 1390000000, 100000, 100, 100, 500, 9000,
                                                10, 100000, 500, 800, 300, 0, 0)
    fix = gps_fix_from_gps_raw_int(raw, tm)
    assert fix.autopilot_clock and eng.imu_time_of(fix) == fix.t_gps
    eng._check_integrity(t)
    assert eng.integrity.state == IntegrityState.OK
    eng.imu_time_offset_s = 0.02 - 0.31          # 3.1 prior sigmas from the configured mean
    eng._check_integrity(t)
    assert eng.integrity.state == IntegrityState.DIVERGED and "IMU time offset" in eng.integrity.reason
