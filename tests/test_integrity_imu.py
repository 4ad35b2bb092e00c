"""IMU screening before integration (companion.nav.imu_screen): clipped, out-of-range and
implausible samples are bridged with the last good one and the covariance grows by what they could
have hidden; in a simulated flight one corrupted sample no longer sends the filter metres off."""
import dataclasses
import math

import numpy as np
import pytest

from companion.messages import ImuSample
from companion.nav.earth import C_n_e, ecef_to_geodetic, rotation_from_rotvec
from companion.nav.engine import NavEngine
from companion.nav.imu_screen import FULL_SCALE_BY_MESSAGE, ImuScreen, ImuScreenCounter as K

G = 9.80665
TAU = 0.005


def _stream(n, rng, f=(0.3, -0.2, -G), w=(0.01, -0.02, 0.005)):
    """n samples of a hovering vehicle with MEMS-class noise: (dtheta_b, dv_b) lists."""
    out = []
    for _ in range(n):
        ww = np.asarray(w) + rng.normal(0.0, 0.02, 3)
        ff = np.asarray(f) + rng.normal(0.0, 0.5, 3)
        out.append(((ww * TAU).tolist(), (ff * TAU).tolist()))
    return out


def test_clean_stream_passes_untouched():
    scr = ImuScreen()
    ok = [scr.check(th, dv, TAU) for th, dv in _stream(2000, np.random.default_rng(1))]
    assert all(ok)
    assert scr.counters[K.BRIDGED] == 0


def test_single_16g_sample_is_clipped_and_bridged_with_the_last_good_one():
    scr = ImuScreen()
    samples = _stream(50, np.random.default_rng(2))
    for th, dv in samples[:20]:
        assert scr.check(th, dv, TAU)
    _, last_dv = samples[19]
    th, dv = samples[20]
    dv = [16.0 * G * TAU, dv[1], dv[2]]
    assert not scr.check(th, dv, TAU)
    assert scr.bridged and scr.counters[K.ACCEL_CLIPPED] == 1 and scr.counters[K.GYRO_CLIPPED] == 0
    assert scr.dv_b == pytest.approx(last_dv, abs=1e-15)         # the accelerometer triad is held
    assert scr.dtheta_b == pytest.approx(th, abs=1e-15)          # the gyro triad was fine: kept
    # what it could have hidden: min(|measured - held|, jump limit) x tau per axis
    assert math.sqrt(scr.var_dv_b[0]) == pytest.approx(60.0 * TAU)
    assert math.sqrt(scr.var_dv_b[1]) == pytest.approx(abs(dv[1] - last_dv[1]))
    assert scr.var_dtheta_b == [0.0, 0.0, 0.0]
    for th, dv in samples[21:]:
        assert scr.check(th, dv, TAU)                            # and the stream goes on


def test_implausible_jump_below_full_scale_is_caught_and_a_lasting_step_adopted():
    scr = ImuScreen()
    samples = _stream(40, np.random.default_rng(3))
    for th, dv in samples[:20]:
        assert scr.check(th, dv, TAU)
    # 9 g more on x for one sample (below the 16-g clip): no vehicle does that in 5 ms
    th, dv = samples[20]
    assert not scr.check(th, [dv[0] + 9 * G * TAU, dv[1], dv[2]], TAU)
    assert scr.counters[K.ACCEL_IMPLAUSIBLE] == 1 and scr.counters[K.ACCEL_CLIPPED] == 0
    # a real, lasting step (impact, hard landing) is adopted once it holds the median of the window
    ok = [scr.check(th, [dv[0] + 9 * G * TAU, dv[1], dv[2]], TAU) for th, dv in samples[21:35]]
    assert ok[:4] == [False] * 4 and all(ok[4:])
    # a gyro jump of 20 rad/s (below the 2000 deg/s range) is implausible too
    th, dv = samples[35]
    assert not scr.check([th[0] + 20.0 * TAU, th[1], th[2]], dv, TAU)
    assert scr.counters[K.GYRO_IMPLAUSIBLE] == 1


def test_full_scale_per_message_type():
    hr, raw = FULL_SCALE_BY_MESSAGE["HIGHRES_IMU"], FULL_SCALE_BY_MESSAGE["RAW_IMU"]
    assert hr.accel_mps2 == pytest.approx(16 * G) and hr.gyro_radps == pytest.approx(math.radians(2000))
    assert raw.gyro_radps == pytest.approx(32.767)          # int16 mrad/s saturates first
    scr = ImuScreen(raw)
    for th, dv in _stream(20, np.random.default_rng(4)):
        scr.check(th, dv, TAU)
    assert not scr.check([32.767 * TAU, 0.0, 0.0], [0.0, 0.0, -G * TAU], TAU)   # a saturated RAW_IMU gyro
    assert scr.counters[K.GYRO_CLIPPED] == 1


def test_before_any_good_sample_a_bad_one_is_dropped():
    scr = ImuScreen()
    assert not scr.check([0.0, 0.0, 0.0], [1e5 * TAU, 0.0, 0.0], TAU)
    assert not scr.bridged and scr.counters[K.DROPPED_NO_GOOD_SAMPLE] == 1


# ---------------------------------------------------------------------------------------------
# in a simulated flight (engine level, tdcp_dgps, 200 Hz MEMS 'uav' scenario)

FAULT_T_S = 30.0


def _corrupt(imu, kind):
    imu = list(imu)
    k0 = int(round(FAULT_T_S * 200.0))

    def put(k, axis, value, gyro=False):
        s = imu[k]
        th, dv = s.dtheta_b.copy(), s.dv_b.copy()
        (th if gyro else dv)[axis] = value * s.dt_s
        imu[k] = ImuSample(s.t_gps, s.dt_s, th, dv, s.imu_id)
    if kind == "16g":
        put(k0, 0, 16.0 * G)
    elif kind == "4 x full scale":
        for k in range(k0, k0 + 4):
            put(k, 2, -32.767 * G)      # RAW_IMU's full scale
    elif kind == "2000 deg/s":
        put(k0, 0, math.radians(2000.0), gyro=True)
    elif kind == "1e5 m/s^2":
        put(k0, 0, 1e5)
    return imu


def _fly(sim, fault, screen):
    from sitl.paper import initial_errors, mode_config
    from sitl.tuning import tuning_for
    tun = tuning_for(sim.scenario)
    eng = NavEngine(dataclasses.replace(mode_config("tdcp_dgps", tun, sim.lever_arm_b), imu_screen_enabled=screen))
    for e in sim.ephemerides:
        eng.process(e)
    eng.process(sim.base)
    truth = sim.truth
    d_att, d_pos, d_vel = initial_errors(np.random.default_rng(10_003), tun.p0, truth.r_e[0])
    eng.initialize(truth.t_gps[0], truth.r_e[0] + d_pos, truth.v_e[0] + d_vel,
                   rotation_from_rotvec(d_att) @ truth.C_b_e[0], tun.p0)
    lat0, lon0, _ = ecef_to_geodetic(truth.r_e[0])
    up = -C_n_e(lat0, lon0)[:, 2]
    imu = _corrupt(sim.imu, fault) if fault else sim.imu
    rov, base = sim.rover_epochs, sim.base_epochs
    i_r = i_b = 0
    err_h = []
    for k, s in enumerate(imu, start=1):
        while i_b < len(base) and base[i_b].t_gps <= s.t_gps:
            eng.process(base[i_b])
            i_b += 1
        while i_r < len(rov) and rov[i_r].t_gps <= s.t_gps:
            eng.process(rov[i_r])
            i_r += 1
        eng.process_imu(s)
        d = eng.r_e - truth.r_e[k]
        err_h.append(float(np.linalg.norm(d - up * (d @ up))))
    k0 = int(FAULT_T_S * 200.0)
    return np.array(err_h[k0:]), eng


@pytest.fixture(scope="module")
def uav70():
    from sitl.fly import load_sim
    return load_sim("uav", 0, 70.0)


@pytest.fixture(scope="module")
def clean(uav70):
    return _fly(uav70, None, True)[0]


# unscreened_min_m: what the fault does without the screen (the 4 full-scale samples: 37 m before
# the TDCP model carried the attitude/bias growth inside the interval, 15.8 m since)
@pytest.mark.parametrize("fault, unscreened_min_m", [("16g", 5.0), ("4 x full scale", 10.0), ("2000 deg/s", 100.0),
                                                     ("1e5 m/s^2", 1000.0)])
def test_one_corrupted_sample_in_flight_stays_bounded(uav70, clean, fault, unscreened_min_m):
    err_raw, _ = _fly(uav70, fault, False)
    err, eng = _fly(uav70, fault, True)
    print(f"{fault}: max horizontal error after the fault {err_raw.max():.2f} m unscreened, {err.max():.3f} m "
          f"screened, {clean.max():.3f} m clean; bridged {eng.counters[K.BRIDGED]}")
    assert err_raw.max() > unscreened_min_m              # what the screen prevents
    assert eng.counters[K.BRIDGED] == (4 if fault == "4 x full scale" else 1)
    assert err.max() < clean.max() + 0.05                 # as good as the clean flight
    assert np.all(np.isfinite(eng.kf.P))
    assert eng.counters["integrity.diverged"] == 0
