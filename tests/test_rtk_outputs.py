"""Carrier-phase RTK in the product (issue 12): the configuration key, the pairing of real
receivers' signal names and time tags, and the fix state in every output -- GPS_INPUT fix type,
VISION_POSITION_ESTIMATE covariance, STATUSTEXT on a change (with its hold), MQTT, the solution
record (version 3; older field logs still replay) and the health report."""
from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from companion.config import ConfigError, config_from_dict
from companion.io import mavlink_encode as mv
from companion.messages import GPS_L2_WAVELENGTH_M, GnssEpoch, NavSolution, SatObservation
from companion.pipeline import FIX_ANNOUNCE_HOLD_S, NavPipeline
from companion.log_records import _SOL_V2, decode_solution, encode_solution, solution_records_equal
from companion.rtk_signals import RTK_SIGNALS, canonical_signal, rtk_epoch

R_E = np.array([-3976219.5, 3382372.6, 3652513.0])
RTK_ON = {"corrections": {"source": "file", "file": {"path": "base.rtcm"}}, "filter": {"rtk_enabled": True}}


def _sol(t=100.0, fix="none", status="nav", sig=0.01, ratio=math.nan, n_fixed=0):
    return NavSolution(float(t), R_E.copy(), np.zeros(3), np.eye(3), np.array([sig, sig, 2 * sig]),
                       np.full(3, 0.02), np.full(3, 0.01), status, t - 0.5, 1,
                       {"hpl_m": 0.5, "hpl_cov_m": 0.5, "hpl_ss_m": math.nan, "integrity": "ok"},
                       fix_state=fix, fix_ratio=ratio, n_fixed=n_fixed)


# ------------------------------------------------------------------ configuration
def test_rtk_key_is_off_by_default_and_reaches_the_engine_with_the_family_signals():
    assert config_from_dict({}).engine_config().rtk_enabled is False
    ec = config_from_dict(RTK_ON).engine_config()
    assert ec.rtk_enabled and ec.rtk_signals == RTK_SIGNALS and ec.rtk_signals[0] == "L1C"
    assert NavPipeline(config_from_dict(RTK_ON)).engine.rtk is not None


@pytest.mark.parametrize("extra, needle", [
    ({"corrections": {"source": "none"}}, "needs a base station"),
    ({"gnss": {"source": "none"}}, "needs the rover's raw observations"),
    ({"filter": {"rtk_enabled": True, "use_loose": True}}, "use_loose"),
    ({"filter": {"rtk_enabled": "yes"}}, "filter.rtk_enabled: expected true or false"),
    ({"filter": {"rtk_enabled": True, "rtk_ratio_threshold": 0.5}}, "rtk_ratio_threshold: must be >= 1.0"),
    ({"filter": {"rtk_enabled": True, "rtk_rover_antenna": "TRM59800.00 SCIS"}}, "set filter.rtk_antennas"),
    ({"filter": {"rtk_enabled": False, "rtk_antennas": "igs20.atx"}}, "rtk_antennas: applies to RTK"),
])
def test_rtk_configuration_errors_say_what_is_missing(extra, needle):
    d = {k: dict(v) for k, v in RTK_ON.items()}
    for k, v in extra.items():
        d[k] = {**d.get(k, {}), **v}
    with pytest.raises(ConfigError, match=needle):
        config_from_dict(d, "x.toml")


# ------------------------------------------------------------------ signal pairing
def _obs(sat, signal, cp=1000.0):
    lam = GPS_L2_WAVELENGTH_M if signal.startswith("L2") else 0.19029367
    return SatObservation(sat, 2.2e7, cp, signal=signal, wavelength_m=lam)


def test_tracking_families_pair_like_with_like():
    # u-blox F9 rover: L1 C/A and L2C(L); a CORS base: 1C, 2W (P(Y)) and 2X (L2C M+L)
    rover = GnssEpoch(100.0, (_obs("G05", "L1C"), _obs("G05", "L2L"), _obs("E11", "L1C"), _obs("G07", "L2S"),
                              _obs("G07", "L2L", cp=7.0)))
    base = GnssEpoch(100.0, (_obs("G05", "L1C"), _obs("G05", "L2W"), _obs("G05", "L2X")), source="base")
    r, b = rtk_epoch(rover), rtk_epoch(base)
    rs = {(o.sat, o.signal) for o in r.observations}
    bs = {(o.sat, o.signal) for o in b.observations}
    assert ("G05", "L2X") in rs and ("G05", "L2X") in bs          # L2C with L2C
    assert ("G05", "L2W") in bs and ("G05", "L2W") not in rs      # P(Y) has no partner on an L2C rover
    assert ("E11", "L1C") in rs                                   # Galileo E1 C: its own family's canonical code
    g07 = [o for o in r.observations if o.sat == "G07"]
    assert len(g07) == 1 and g07[0].signal == "L2X" and g07[0].carrier_cycles == 7.0    # L2L preferred over L2S
    assert rtk_epoch(b) is b                                      # already canonical: the same object
    assert canonical_signal("G01", "L2D") == "L2W" and canonical_signal("G01", "L1W") is None
    assert canonical_signal("R01", "L1C") == "L1C" and canonical_signal("R01", "L1P") == "L1P"   # C/A and P apart


def test_pipeline_renames_both_sides_and_cuts_other_systems_from_the_base():
    pipe = NavPipeline(config_from_dict(RTK_ON))
    # Galileo is RTK-paired within Galileo (issue 12); GLONASS, not in [filter] systems here, is cut
    base = GnssEpoch(100.0, (_obs("G05", "L1C"), _obs("G05", "L2X"), _obs("E11", "L1X"), _obs("R01", "L1C")),
                     source="base")
    out = pipe._rtk_epoch(base)
    assert {(o.sat, o.signal) for o in out.observations} == {("G05", "L1C"), ("G05", "L2X"), ("E11", "L1C")}
    off = NavPipeline(config_from_dict({}))
    assert not off.rtk_enabled and off.wait_for_base is False


def test_rover_tagged_x99_is_held_for_the_base_epoch_of_the_next_whole_second():
    """A real rover's epochs are tagged x.99 s (receiver clock 10 ms behind), the base's on whole
    seconds: the rover epoch waits for the base epoch 10 ms after it (not the one 0.99 s before),
    then both reach the engine with the same signal names."""
    pipe = NavPipeline(config_from_dict(RTK_ON))
    got = []
    eng = pipe.engine
    fake = SimpleNamespace(initialized=True, base=object(), cfg=eng.cfg, ephemerides=SimpleNamespace(sats=[]),
                           base_check=eng.base_check, base_station_changes=0,
                           process=lambda m: got.append(m))
    pipe.engine = fake
    pipe.base_seen = True
    pipe.mode = "tight"
    pipe.last_imu = SimpleNamespace(t_gps=1000.2)
    pipe._feed_messages([GnssEpoch(1000.0, (_obs("G05", "L1C"), _obs("G05", "L2W")), source="base")])
    pipe._feed_messages([GnssEpoch(1000.99, (_obs("G05", "L1C"), _obs("G05", "L2L")))])
    assert [e.t_gps for e in got] == [1000.0] and pipe._held, "the x.99 epoch must wait for its base"
    pipe._feed_messages([GnssEpoch(1001.0, (_obs("G05", "L1C"), _obs("G05", "L2X")), source="base")])
    assert [e.t_gps for e in got] == [1000.0, 1001.0, 1000.99] and not pipe._held
    rover = got[-1]
    assert {o.signal for o in rover.observations} == {"L1C", "L2X"}
    assert {o.signal for o in got[1].observations} == {"L1C", "L2X"}


def _shift_rover_clock(rover, shift_s):
    """The same physical measurements from a receiver whose clock is ``shift_s`` behind: tags,
    pseudoranges and carrier phases move together (what such a receiver would report)."""
    from companion.messages import SPEED_OF_LIGHT_MPS as C
    out = []
    for ep in rover:
        obs = tuple(dataclasses.replace(o, pseudorange_m=o.pseudorange_m - C * shift_s,
                                        carrier_cycles=o.carrier_cycles - C * shift_s / o.wavelength_m)
                    for o in ep.observations)
        out.append(dataclasses.replace(ep, t_gps=ep.t_gps - shift_s, observations=obs))
    return out


def _rtk_run_rover_held_for_its_base(clock_shift_s: float, duration_s: float = 60.0) -> dict:
    """The rtk scenario (seed 0) through the engine with RTK on (sitl.rtk_score's configuration
    and start), the rover's clock ``clock_shift_s`` behind, and the rover epochs released as the
    pipeline releases them: once the base epoch within 0.05 s of the rover's tag has arrived (the
    x.99 rover waits for the base's x+1.000), else BASE_WAIT_S late.  Fixed epochs and their true
    errors."""
    from companion.nav.earth import rotation_from_rotvec
    from companion.nav.engine import NavEngine
    from companion.pipeline import BASE_WAIT_S
    from sitl.paper import initial_errors
    from sitl.rtk_score import WRONG_FIX_M, rtk_config
    from sitl.scenario import build_scenario
    from sitl.simulate import simulate
    from sitl.tuning import tuning_for
    scn = dataclasses.replace(build_scenario("rtk"), duration_s=duration_s)
    sim, tuning = simulate(scn, 0), tuning_for(scn)
    eng = NavEngine(rtk_config(scn, tuning))
    for eph in sim.ephemerides:
        eng.process(eph)
    eng.process(sim.base)
    tr = sim.truth
    d_att, d_pos, d_vel = initial_errors(np.random.default_rng(10_000), tuning.p0, tr.r_e[0])
    eng.initialize(tr.t_gps[0], tr.r_e[0] + d_pos, tr.v_e[0] + d_vel, rotation_from_rotvec(d_att) @ tr.C_b_e[0],
                   tuning.p0)
    from companion.nav.earth import C_n_e, ecef_to_geodetic
    lat0, lon0, _ = ecef_to_geodetic(tr.r_e[0])
    up_e = -C_n_e(lat0, lon0)[:, 2]
    fixed_err = []                  # (3-D, horizontal) true error after each fixed epoch's update

    def on_epoch(rep):
        if rep.fix_state == "fixed":
            d = eng.r_e - sim.truth_at(eng.t_gps)[0]
            fixed_err.append((float(np.linalg.norm(d)), float(np.linalg.norm(d - up_e * (d @ up_e)))))
    eng.on_epoch = on_epoch
    lat = tuning.gnss_latency_s
    rover, base = _shift_rover_clock(sim.rover_epochs, clock_shift_s), sim.base_epochs
    i_rov = i_base = 0
    base_seen: list[float] = []
    for s in sim.imu:
        while i_base < len(base) and base[i_base].t_gps + lat <= s.t_gps:
            eng.process(base[i_base])
            base_seen.append(base[i_base].t_gps)
            i_base += 1
        while i_rov < len(rover) and rover[i_rov].t_gps + lat <= s.t_gps and (
                any(abs(t - rover[i_rov].t_gps) < 0.05 for t in base_seen[-3:])
                or s.t_gps - rover[i_rov].t_gps > BASE_WAIT_S):
            eng.process(rover[i_rov])
            i_rov += 1
        eng.process_imu(s)
    return {"fixed_epochs": len(fixed_err), "n_epochs": len(rover),
            "wrong_fixes": sum(1 for e in fixed_err if e[0] > WRONG_FIX_M),
            "rms_h_fixed_m": float(np.sqrt(np.mean(np.square([e[1] for e in fixed_err])))) if fixed_err else math.nan,
            "no_base": eng.counters.get("rtk epochs without a base epoch", 0)}


def test_rtk_fixes_with_rover_tags_a_millisecond_off_the_base_tags():
    """u-blox class receivers keep their clock within about a millisecond of GPS time (millisecond
    jumps): tags x.999 against the base's x.000, each rover epoch held for the base epoch of its
    second (as the pipeline does).  Fixed on most epochs, no wrong fix, centimetre RMS."""
    r = _rtk_run_rover_held_for_its_base(0.001)
    print(r)
    assert r["no_base"] == 0
    assert r["fixed_epochs"] > 0.8 * r["n_epochs"] and r["wrong_fixes"] == 0 and r["rms_h_fixed_m"] < 0.02


# a 10-ms receiver clock offset is 12 cm at the drone's 12 m/s: with the rover modelled at its tag
# it gave 8 wrong fixes and 0.063 m over the fixed epochs; RtkUpdate.rows now takes the antenna
# back by the clock bias
def test_rtk_fixes_with_rover_tags_ten_milliseconds_off_the_base_tags():
    r = _rtk_run_rover_held_for_its_base(0.01)
    print(r)
    assert r["no_base"] == 0
    assert r["fixed_epochs"] > 0.8 * r["n_epochs"] and r["wrong_fixes"] == 0 and r["rms_h_fixed_m"] < 0.02


# ------------------------------------------------------------------ outputs
@pytest.mark.parametrize("status, fix, dgps, expected", [
    ("nav", "fixed", False, 6), ("coasting", "fixed", False, 6), ("nav", "float", False, 5),
    ("nav", "none", False, 3), ("nav", "none", True, 4), ("suspect", "fixed", False, 1),
    ("init", "none", False, 1), ("converging", "float", False, 1),
])
def test_gps_input_fix_type(status, fix, dgps, expected):
    sol = _sol(fix=fix, status=status)
    if dgps:
        sol.extras["dgps"] = True
    assert mv.gps_fix_type(sol) == expected
    assert mv.gps_input(sol, t_boot_us=5).fix_type == expected
    assert mv.gps_input(sol, fix_type=2).fix_type == 2            # an explicit fix type wins


def test_outputs_carry_the_filters_covariance_of_a_fixed_solution():
    sol = _sol(fix="fixed", sig=0.012, ratio=8.5, n_fixed=14)
    vpe = mv.vision_position_estimate(sol, mv.Origin.from_ecef(R_E), 0, 5)
    assert vpe.covariance[0] == pytest.approx(0.012 ** 2, rel=1e-6)
    assert vpe.covariance[6] == pytest.approx(0.012 ** 2, rel=1e-6)
    assert vpe.covariance[11] == pytest.approx(0.024 ** 2, rel=1e-6)
    gi = mv.gps_input(sol)
    assert gi.horiz_accuracy == pytest.approx(math.hypot(0.012, 0.012), rel=1e-6)
    pytest.importorskip("aiomqtt")
    from companion.io.mqtt import solution_to_json
    j = solution_to_json(sol)
    assert j["fix_state"] == "fixed" and j["fix_ratio"] == 8.5 and j["n_fixed"] == 14
    assert solution_to_json(_sol())["fix_ratio"] is None


def test_solution_record_v3_keeps_the_fix_and_v2_logs_still_replay():
    s = _sol(fix="fixed", ratio=12.345678901, n_fixed=17)
    s.extras.update({"inject": True, "mode": "tight", "imu_count": 7, "t_boot_us": 123})
    b = encode_solution(s)
    d = decode_solution(b)
    assert (d.fix_state, d.n_fixed, d.fix_ratio) == ("fixed", 17, s.fix_ratio) and encode_solution(d) == b
    v2 = _SOL_V2.pack(2, *_SOL_V2.unpack(b[:_SOL_V2.size])[1:])
    old = decode_solution(v2)
    assert old.fix_state == "none" and old.extras["hpl_m"] == 0.5 and np.array_equal(old.r_e, s.r_e)
    assert solution_records_equal(v2, b)                    # an old log replays bit for bit
    changed = bytearray(v2)
    changed[-1] ^= 1
    assert not solution_records_equal(bytes(changed), b)
    assert not solution_records_equal(encode_solution(_sol(fix="fixed")), encode_solution(_sol(fix="float")))


def _run(pipe, states, t0=100.0, dt=0.04):
    """Feed one solution per (fix state, seconds) segment every ``dt``; the events it announced."""
    t = t0
    for state, seconds in states:
        for _ in range(int(round(seconds / dt))):
            pipe._finish(_sol(t=t, fix=state, ratio=9.0 if state == "fixed" else math.nan))
            t += dt
    return [text for _, text in pipe.drain_events() if "RTK" in text]


def test_statustext_once_per_fix_state_change_that_holds():
    pipe = NavPipeline(config_from_dict(RTK_ON))
    pipe.mode = "tight"
    assert _run(pipe, [("none", 2.0)]) == []
    # float; a fix held one second (a blip: not announced); float again long enough, then fixed
    # with one float epoch and a two-second loss in between: announced once
    assert _run(pipe, [("float", FIX_ANNOUNCE_HOLD_S + 0.5), ("fixed", 1.0), ("float", 1.0)]) == ["RTK float"]
    ev = _run(pipe, [("fixed", 5.0), ("float", 0.04), ("fixed", 4.0), ("none", 2.0), ("fixed", 5.0)])
    assert ev == ["RTK fixed: 0 amb, ratio 9.0"]
    assert _run(pipe, [("none", FIX_ANNOUNCE_HOLD_S + 0.2)]) == ["RTK none (was fixed)"]
    assert _run(pipe, [("float", FIX_ANNOUNCE_HOLD_S + 0.2)]) == ["RTK float"]
    assert pipe.health()["filter"]["rtk"]["fix_state_announced"] == "float"
    # RTK off: no fix-state announcements, no rtk section in the health report
    off = NavPipeline(config_from_dict({}))
    off.mode = "tight"
    assert _run(off, [("fixed", 5.0)]) == [] and "rtk" not in off.health()["filter"]


def test_a_solution_withheld_by_the_heading_gate_says_so():
    """A good position held back by the heading gate is announced with that reason, not as
    'nav sigma_h 0.0 m' (what an rtk-gec flight's operator read after its first fix)."""
    pipe = NavPipeline(config_from_dict(RTK_ON))
    pipe.mode = "tight"
    pipe.heading.gsf = SimpleNamespace(gap_restarts=0, converged=True, settled=True, yaw_rad=math.radians(164.0),
                                       yaw_sigma_rad=math.radians(9.5))
    real_engine = pipe.engine
    pipe.engine = pipe.heading.engine = SimpleNamespace(initialized=True, t_gps=100.0, kf=object(),
                                                        rtk=real_engine.rtk,
                                                        heading_and_sigma=lambda: (0.0, math.radians(1.0)))
    pipe._finish(_sol(t=100.0, fix="fixed", ratio=9.0))
    texts = [text for _, text in pipe.drain_events()]
    assert "nav not injected: heading disputed" in texts, texts
    assert not any("sigma_h" in t for t in texts)
    pipe.heading.gsf.yaw_rad = 0.0                                   # agrees: injected, announced as usual
    pipe._finish(_sol(t=100.04, fix="fixed", ratio=9.0))
    assert any(t.startswith("nav OK tight") for _, t in pipe.drain_events())
