"""`python -m sitl fly` end to end, short: estimates arrive at the configured rate, close to the truth."""
import json
import subprocess
import sys


def test_fly_short_run_scores(tmp_path):
    out = tmp_path / "fly"
    js = tmp_path / "fly.json"
    p = subprocess.run([sys.executable, "-m", "sitl.fly", "fly", "--duration", "30", "--speedup", "2",
                        "--out", str(out), "--json", str(js)], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stdout + p.stderr
    r = json.loads(js.read_text())
    for k in ("estimates_received", "estimate_rate_hz", "estimate_rate_fraction", "rms_3d_m", "rms_h_m", "p95_3d_m",
              "latency_ms_p50", "latency_ms_p99", "companion_cpu_pct", "companion_rss_mb"):
        assert k in r
    d = r["details"]
    # initialisation takes ~3 s of the 30: the rest arrives at the configured 25 Hz
    assert d["estimate_rate_fraction_after_first"] > 0.9
    assert r["rms_h_m"] < 1.5 and r["p95_3d_m"] < 3.0
    # latency and CPU are measured, not judged, here: how fast is a benchmark's question (a loaded
    # machine must not fail the suite); that they were measured is
    assert 0.0 < r["latency_ms_p50"] <= r["latency_ms_p99"] and r["companion_cpu_pct"] > 0.0
    assert 0.0 < r["setup_s"] < d["run_s"] and r["interrupted"] is False
    assert d["companion_exit_code"] == 0
    assert any("nav init" in t for t in d["statustext"])


def test_stock_autopilot_without_raw_gnss_gets_a_loosely_coupled_estimate(tmp_path):
    """Issue 3: with GPS_RAW_INT only (no receiver tunnel, no corrections) the service falls back to
    loose coupling, says so, and still injects estimates."""
    from tests._flyhelp import final_health, run_fly
    r = run_fly(tmp_path, duration_s=30.0, speedup=2.0, gnss_source="none", use_caster=False)
    d = r.get("details", r)
    print({k: r[k] for k in ("estimates_received", "estimate_rate_fraction", "rms_h_m", "p95_3d_m")})
    assert r["estimates_received"] > 0.7 * 25 * 30
    # announced to the ground station: initialised from GPS_RAW_INT and navigating in loose mode
    assert any("GPS_RAW_INT fix (loose)" in t for t in d["statustext"])
    assert any("nav OK loose" in t for t in d["statustext"])
    # GPS_RAW_INT is a metre-class fix: the fused estimate is that good, not better
    assert r["rms_h_m"] < 5.0
    health = final_health(d["field_log_dir"])["health"]
    assert health, "the service wrote no health report"


def test_imu_cluster_drops_a_failing_unit_in_flight(tmp_path):
    """Issue 4 (IMU cluster) in the service: the autopilot reports three IMUs as ArduPilot does
    (RAW_IMU, SCALED_IMU2, SCALED_IMU3: int16 mG and mrad/s, each unit with its own turn-on biases); at 12 s unit 2's x gyro gains
    0.02 rad/s (25 x its per-sample noise).  The companion drops that unit within a fraction of a
    second, says so to the ground station, keeps navigating on the other two, and the field log
    still replays bit for bit."""
    from sitl.autopilot import Faults
    from companion.replay import replay
    from tests._flyhelp import run_fly
    # 5 % of the IMU frames lost on the link (as when a loaded companion's socket buffer
    # overflows): no healthy unit may be flagged for it (issue 9)
    r = run_fly(tmp_path, duration_s=30.0, speedup=2.0, imu_units=3, imu_message="RAW_IMU",
                faults=Faults(imu_unit_bias=[(12.0, 2, 0.02)], imu_loss=[(0.0, 1e9, 0.05)]))
    d = r.get("details", r)
    assert d["companion_exit_code"] == 0
    assert r["autopilot"]["imu_unit1_sent"] > 5000 and r["autopilot"]["imu_unit2_sent"] > 5000
    assert r["autopilot"]["imu_unit1_lost"] > 100 and r["autopilot"]["imu_lost"] > 100
    cl = r["imu_cluster"]
    assert cl is not None, "no IMU-cluster health in the field log"
    assert cl["units"]["RAW_IMU"]["healthy"] and cl["units"]["SCALED_IMU2"]["healthy"]
    assert not cl["units"]["SCALED_IMU3"]["healthy"]
    assert cl["counters"].get("imu 2 dropped") == 1 and not cl["ambiguous"]
    assert not any(k.startswith(("imu 0", "imu 1")) for k in cl["counters"]), cl["counters"]
    assert cl["counters"].get("fused from 3 units", 0) > 1000 and cl["counters"].get("fused from 2 units", 0) > 1000
    drop = [t for t in d["statustext"] if "SCALED_IMU3" in t and "dropped" in t]
    assert drop, d["statustext"]
    # the drop time, from the companion's log line (GPS time) against the fault time
    import re
    m = re.search(r"unit 2 dropped at t=([0-9.]+)", open(r["companion_log"]).read())
    from sitl.fly import load_sim
    t0 = load_sim("uav", 0, 33.0).truth.t_gps[0]
    assert -0.001 <= float(m.group(1)) - t0 - 12.0 < 0.5       # (the log prints ms)
    assert r["rms_h_m"] < 1.5 and r["p95_3d_m"] < 3.0
    c = replay(r["field_log_dir"]).comparison()
    assert c["bit_for_bit"] and c["logged_solutions"] > 300, c


def test_odometry_and_gps_input_outputs_end_to_end(tmp_path):
    """Issue 3: the two other output modes reach the emulated autopilot as real MAVLink with the
    fields ArduPilot requires, and the positions they carry are as good as the vision output's."""
    import math
    from tests._flyhelp import run_fly
    for mode in ("odometry", "gps_input"):
        r = run_fly(tmp_path / mode, duration_s=20.0, speedup=2.0, output_mode=mode)
        assert r["companion_exit_code"] == 0
        # the first ~9.2 s: initialisation, then the protection level of the initial covariance
        # (about 7 m) coming down below output.max_hpl_m (5 m)
        assert r["estimates_received"] > 0.7 * 25 * (20 - 9.5), mode
        assert r["rms_h_m"] < 1.5 and r["p95_3d_m"] < 3.0, (mode, r["rms_h_m"], r["p95_3d_m"])
        last = r["last_output"]
        if mode == "odometry":
            o = last["ODOMETRY"]
            assert o["frame_id"] == 20 and o["child_frame_id"] == 12          # LOCAL_FRD, BODY_FRD
            assert abs(math.sqrt(sum(q * q for q in o["q"])) - 1.0) < 1e-6
            assert all(math.isfinite(v) for v in (o["x"], o["y"], o["z"], o["vx"], o["vy"], o["vz"]))
            assert o["pose_covariance"][0] > 0 and 0 <= o["quality"] <= 100
            assert "VISION_POSITION_ESTIMATE" not in last
        else:
            g = last["GPS_INPUT"]
            assert g["fix_type"] >= 3 and g["time_week"] > 1000 and 0 <= g["time_week_ms"] < 604800000
            assert g["ignore_flags"] == 0 and g["horiz_accuracy"] > 0 and g["satellites_visible"] > 0
            assert "ODOMETRY" not in last


def test_output_rate_holds_when_the_autopilot_streams_the_imu_slower_than_asked(tmp_path):
    """The companion asks for 200 Hz; the autopilot delivers 50 Hz (as ArduPilot may over a busy
    link).  Solutions are paced by GPS time, so 25 Hz still comes out (a fixed decimation of 8
    would give 6.25 Hz), and the decoder's notion of the nominal interval follows the stream."""
    from tests._flyhelp import final_health, run_fly
    r = run_fly(tmp_path, duration_s=20.0, speedup=2.0, max_imu_rate_hz=50.0)
    d = r.get("details", r)
    assert d["companion_exit_code"] == 0
    assert d["estimate_rate_fraction_after_first"] > 0.9, d["estimate_rate_fraction_after_first"]
    assert r["rms_h_m"] < 1.5 and r["p95_3d_m"] < 3.0
    imu = final_health(d["field_log_dir"])["health"]["imu_decoder"]
    assert imu["samples"] > 0.9 * 50 * 17
    assert imu["gaps"] < 0.02 * imu["samples"], imu


def _heading_errors_deg(field_log_dir, duration_s):
    """Heading of every 'nav' solution in the field log minus the truth's, deg."""
    import math
    import numpy as np
    from companion.io.fieldlog import read_field_log
    from companion.nav.earth import C_n_e, ecef_to_geodetic
    from companion.log_records import decode_solution
    from sitl.fly import load_sim
    sim = load_sim("uav", 0, duration_s + 3.0)
    out = []
    for rec in read_field_log(field_log_dir):
        if rec.kind != "solution":
            continue
        s = decode_solution(rec.payload)
        if s.status != "nav":
            continue
        r, _, C_true = sim.truth_at(s.t_gps)
        lat, lon, _ = ecef_to_geodetic(r)
        Cn = C_n_e(lat, lon).T
        a, b = Cn @ s.C_b_e, Cn @ C_true
        d = math.atan2(a[1, 0], a[0, 0]) - math.atan2(b[1, 0], b[0, 0])
        out.append(math.degrees((d + math.pi) % (2 * math.pi) - math.pi))
    return np.array(out)


def test_dual_antenna_heading_end_to_end(tmp_path):
    """Issue 4 (GNSS attitude) in the service: the receiver on GPS1 also sends NAV-RELPOSNED
    (antennas 0.6 m apart, mounted across the frame and 0.2 m forward: body vector (0.2, 0.6, 0)),
    and the autopilot's GPS_RAW_INT carries a dual-antenna yaw (1 deg).  Both reach the filter and
    the heading of the injected estimates is a few hundredths of a degree good over the second
    half of the flight (measured 0.040 deg), where the same flight without them is 0.33 deg off
    (`python -m sitl fly --duration 30 --speedup 2`, same seed)."""
    import numpy as np
    from tests._flyhelp import final_health, run_fly
    b_b = (0.2, 0.6, 0.0)
    r = run_fly(tmp_path / "dual", duration_s=30.0, speedup=2.0, moving_baseline_b_m=b_b, gps_yaw_sigma_deg=1.0)
    d = r.get("details", r)
    assert d["companion_exit_code"] == 0
    h = final_health(d["field_log_dir"])["health"]
    eng, pipe = h["engine"], h["pipeline"]
    assert pipe["moving baselines (NAV-RELPOSNED)"] >= 25 and pipe["GPS_RAW_INT yaw"] >= 25
    assert eng["baseline rows used"] >= 3 * 20 and eng["attitude used"] >= 20, eng
    assert not any(k.startswith("baseline rejected") for k in eng), eng
    e = _heading_errors_deg(d["field_log_dir"], 30.0)
    late = e[len(e) // 2:]
    rms_late = float(np.sqrt(np.mean(late ** 2)))
    print(f"heading RMS, second half of the flight: {rms_late:.3f} deg with the dual antenna")
    assert rms_late < 0.15
    assert r["rms_h_m"] < 1.5


def test_rtk_scenario_reaches_fixed_through_the_service(tmp_path):
    """Issue 12 in the product: the rtk scenario's base streams GPS MSM7 (1C, 2W, 2X) + 1005
    through the NTRIP caster, the F9-like rover reports L1 C/A and L2C(L) over SERIAL_CONTROL, the
    service runs with ``filter.rtk_enabled``.  Its solutions reach 'fixed' (the rover's L2L paired
    with the base's 2X, never with 2W), GPS_INPUT carries fix type 6 (5 while float), the ground
    station hears of the fix once, the fixed estimates are centimetre-class against the truth,
    and the field log replays bit for bit."""
    from companion.replay import replay
    from tests._flyhelp import final_health, run_fly
    r = run_fly(tmp_path, scenario="rtk", duration_s=40.0, speedup=2.0, output_mode="gps_input")
    d = r.get("details", r)
    assert d["companion_exit_code"] == 0
    rtk = r["rtk"]
    print(rtk)
    assert rtk["first_fix_s"] is not None, rtk
    assert rtk["estimates_by_fix_state"].get("fixed", 0) > 100
    # what the autopilot got: fix type 6 for the fixed estimates, 5 for the float ones, nothing
    # else once RTK runs (every estimate has a base within 1.5 s here)
    assert rtk["gps_input_fix_types"].get(6, 0) == rtk["estimates_by_fix_state"]["fixed"]
    assert rtk["gps_input_fix_types"].get(5, 0) == rtk["estimates_by_fix_state"].get("float", 0)
    assert rtk["rms_h_fixed_m"] < 0.05
    fixed_texts = [t for t in d["statustext"] if t.startswith("CC: RTK fixed")]
    assert len(fixed_texts) >= 1 and len([t for t in d["statustext"] if "RTK" in t]) <= 4, d["statustext"]
    h = final_health(d["field_log_dir"])["health"]
    assert h["filter"]["rtk"]["n_ambiguities"] > 0
    assert h["pipeline"].get("rtk: rover epochs with signals renamed to their family", 0) > 10
    c = replay(r["field_log_dir"]).comparison()
    assert c["bit_for_bit"], c
