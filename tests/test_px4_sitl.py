"""A real PX4 (v1.15 SITL, SIH) flies on our estimate (``python -m sitl px4``), plus the pieces of
that harness, of deploy/px4-vision.params and of the clock mapping it needs that can be checked
without it."""
from __future__ import annotations

import math
import struct
import tomllib

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.io import mavlink_time
from sitl.px4 import DEPLOY, PARAM_FILE, imu_noise_overrides, param_value
from sitl.px4_gcs import mode_name
from sitl.px4_procs import (
    dist_problem,
    find_dist,
    hardware_only,
    parse_listener_flags,
    read_params,
)
from sitl.px4_result import ekf_flag_figures, failsafes


# -- deploy/ ---------------------------------------------------------------------------------
def test_px4_params_fuse_our_position_not_our_yaw_and_not_gnss():
    p = read_params(PARAM_FILE)
    ev = int(p["EKF2_EV_CTRL"])
    assert ev & 0b0011 == 0b0011, "horizontal and vertical position from VISION_POSITION_ESTIMATE"
    assert not ev & 0b1000, "yaw stays the compass: the companion holds its heading on PX4's at rest"
    assert not ev & 0b0100, "VISION_POSITION_ESTIMATE carries no velocity"
    assert p["EKF2_GPS_CTRL"] == 0 and p["EKF2_HGT_REF"] == 3
    assert p["EKF2_EV_DELAY"] == 0, "stamps are PX4's own IMU times"
    cfg = tomllib.loads((DEPLOY / "companion.toml").read_text())
    assert cfg["mavlink"]["autopilot_heading_on_ground"] and cfg["output"]["mode"] == "vision"
    assert cfg["output"]["set_ekf_origin"], "EKF2 without GNSS takes its origin from us"
    # only serial-port parameters may be absent on SITL
    assert [k for k in p if hardware_only(k)] == ["MAV_1_CONFIG", "SER_TEL2_BAUD"]
    assert not hardware_only("MAV_1_MODE") and not hardware_only("EKF2_EV_CTRL")


def test_int_parameters_arrive_bytewise():
    as_float = struct.unpack("<f", struct.pack("<i", 102))[0]       # what PX4 puts in param_value
    msg = mav.MAVLink_param_value_message(b"MAV_1_CONFIG", as_float, mav.MAV_PARAM_TYPE_INT32, 1, 0)
    assert param_value(msg) == 102.0
    msg = mav.MAVLink_param_value_message(b"EKF2_EVP_NOISE", 0.2, mav.MAV_PARAM_TYPE_REAL32, 1, 0)
    assert param_value(msg) == pytest.approx(0.2)


def test_imu_noise_overrides_never_go_below_deploy():
    text = (DEPLOY / "companion.toml").read_text()
    f = tomllib.loads(text)["filter"]
    quiet = {"gyro_arw_rad_per_sqrt_s": f["gyro_arw_rad_per_sqrt_s"] / 2, "accel_vrw_mps_per_sqrt_s": 0.05}
    assert imu_noise_overrides(text, quiet) == {"filter.accel_vrw_mps_per_sqrt_s": "0.05"}
    assert imu_noise_overrides(text, None) == {}


# -- PX4 specifics -----------------------------------------------------------------------------
def test_listener_flags_and_modes():
    text = "TOPIC: estimator_status_flags\n    timestamp: 11424000\n    cs_ev_pos: True\n    cs_gps: False\n"
    assert parse_listener_flags(text) == {"cs_ev_pos": True, "cs_gps": False}
    assert parse_listener_flags("never published") is None
    assert mode_name(6 << 16) == "OFFBOARD" and mode_name((4 << 16) | (6 << 24)) == "AUTO.LAND"


def test_ext_nav_used_needs_vision_in_every_flight_sample_and_no_gnss():
    ok = {"cs_ev_pos": True, "cs_gps": False}
    assert ekf_flag_figures([(1.0, ok), (2.0, ok), (9.0, {"cs_ev_pos": False})], (0.0, 5.0))["ext_nav_used"]
    assert not ekf_flag_figures([(1.0, ok), (2.0, {"cs_ev_pos": False})], (0.0, 5.0))["ext_nav_used"]
    assert not ekf_flag_figures([(1.0, ok), (2.0, {"cs_ev_pos": True, "cs_gps": True})], (0.0, 5.0))["ext_nav_used"]
    assert not ekf_flag_figures([(1.0, ok)], (0.0, 5.0))["ext_nav_used"], "one sample proves nothing"


def test_failsafes_from_mode_changes_state_and_text():
    offboard, land, hold = 6 << 16, (4 << 16) | (6 << 24), (4 << 16) | (3 << 24)
    commanded = [(10.0, offboard), (50.0, land)]
    modes = [(1.0, hold, False), (10.5, offboard, True), (50.5, land, True), (60.0, hold, False)]
    assert failsafes([], [], [(5.0, 3, False), (11.0, 4, True)], modes, commanded) == []
    modes_fs = modes[:2] + [(30.0, hold, True)]
    assert failsafes([], [], [], modes_fs, commanded) == ["mode changed to AUTO.LOITER by the autopilot"]
    assert failsafes([], [], [(31.0, 5, True)], modes, commanded) == ["state 5 while armed"]
    assert failsafes(["Failsafe activated: Land"], ["WARN  [commander] Failsafe: no offboard"], [], modes,
                     commanded) == ["Failsafe activated: Land", "console: WARN  [commander] Failsafe: no offboard"]


# -- clock mapping: PX4 SITL's lockstep clock is not UTC's -------------------------------------
def test_boot_to_gps_time_follows_a_drifting_boot_clock_without_jumps():
    """SITL: the boot clock runs 1.3 % slow against SYSTEM_TIME's UTC (measured on PX4 SIH), with
    a 0.3-s stall once; the mapping must neither lag 0.1 s behind nor 'jump' every 5 s."""
    tm = mavlink_time.BootToGpsTime()
    unix0, t_boot, errs = 1_796_165_576.0, 13.24, []
    for k in range(120):
        unix = unix0 + k * 1.013 + (0.3 if k == 40 else 0.0)
        tm.update_system_time(int(unix * 1e6), int(round(t_boot * 1e3)))
        if k > 10 and k != 40:
            errs.append(tm.to_gps(t_boot) - mavlink_time.unix_to_gps_s(unix))
        t_boot += 1.0
    assert tm.jumps == 0 and tm.rate == pytest.approx(0.013, abs=5e-4)
    assert max(abs(e) for e in errs) < 0.01
    t_gps = tm.to_gps(50.0)
    assert tm.to_boot(t_gps) == pytest.approx(50.0, abs=1e-6)


def test_boot_to_gps_time_still_takes_a_real_step():
    tm = mavlink_time.BootToGpsTime()
    for k in range(20):
        tm.update_system_time(int((1.7e9 + k) * 1e6), 1000 * k)
    assert tm.rate == pytest.approx(0.0, abs=1e-6)
    for k in range(20, 23):
        tm.update_system_time(int((1.7e9 + k + 2.0) * 1e6), 1000 * k)
    assert tm.jumps == 1 and tm.to_gps(22.0) == pytest.approx(mavlink_time.unix_to_gps_s(1.7e9 + 24.0), abs=1e-3)


# -- the real thing -----------------------------------------------------------------------------
@pytest.mark.slow
def test_px4_sitl_arms_hovers_and_flies_a_leg_on_our_estimate(tmp_path):
    """Short variant of ``python -m sitl px4``: 20 s on the ground, one 10-m leg, land (~2.5 min)."""
    problem = dist_problem(find_dist())
    if problem:
        pytest.skip(problem)
    from sitl.px4 import run
    r = run(duration_s=20.0, out_dir=str(tmp_path), side_m=10.0, legs=1)
    assert r["param_problems"] == {}, "every line of deploy/px4-vision.params exists on PX4 (serial ports aside)"
    assert r["armed"] and r["box_completed"], r.get("statustext")
    assert r["ext_nav_used"], r.get("ekf_flags_flight")
    assert r["failsafes"] == []
    assert r["estimate_rate_hz"] > 22.0                  # 25 Hz configured
    assert r["ekf_origin_minus_ours_m"] == [0.0, 0.0]    # EKF2 took our origin
    assert r["rms_h_m"] <= 0.3 and r["max_error_h_m"] < 1.0
    assert r["ekf_rms_h_m"] < 0.8
    assert r["companion_exit_code"] == 0
    # at rest our heading is held on PX4's compass heading (mavlink.autopilot_heading_on_ground),
    # and SIH's compass yaw itself wanders 4-17 deg off its truth from run to run: ours is judged
    # against EKF2's own error on the same samples, not against a fixed figure (5.54 deg failed a
    # fixed 5 deg while the flight was flawless)
    assert not math.isnan(r["yaw_rms_deg_ground"])
    assert r["yaw_rms_deg_ground"] <= r["ekf_yaw_rms_deg_ground"] + 2.0, (r["yaw_rms_deg_ground"],
                                                                          r["ekf_yaw_rms_deg_ground"])
    assert np.isfinite(r["companion_cpu_pct"])


def test_ardupilot_command_runs_px4_with_autopilot_px4():
    import argparse

    from sitl import ardupilot, px4
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd")
    ardupilot.register(sub)
    px4.register(sub)
    a = p.parse_args(["ardupilot", "--autopilot", "px4", "--px4-dir", "/nowhere", "--legs", "1"])
    assert a.func is ardupilot.cmd_ardupilot and a.autopilot == "px4" and a.px4_dir == "/nowhere"
    assert ardupilot.cmd_ardupilot(a) == 2          # the missing PX4 folder is reported, not raised
    b = p.parse_args(["px4", "--duration", "5"])
    assert b.func is px4.cmd_px4 and b.duration == 5.0 and b.out == "out/px4"
