"""The real ArduCopter SITL flies on our estimate (``python -m sitl ardupilot``), plus the pieces
of that harness and of deploy/ that can be checked without it."""
from __future__ import annotations

import asyncio
import math
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mav

from companion.config import load_config
from companion.io import mavlink as M
from companion.io import imu_streams
from sitl import ardupilot_score as S
from sitl.ardupilot import DEPLOY, read_parm
from sitl.ardupilot_procs import binary_problem, companion_config, find_binary
from sitl.fly import free_udp_port


# -- deploy/ ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["ardupilot-vision.parm", "ardupilot-gps-input.parm"])
def test_parm_files_fit_ardupilot(name):
    path = DEPLOY / name
    long_lines = [n for n, line in enumerate(path.read_text().splitlines(), 1) if len(line) > 99]
    assert not long_lines, f"{name}: lines over ArduPilot's 99 characters: {long_lines}"
    p = read_parm(path)
    assert not [k for k in p if k[:2] == "SR" and k[2].isdigit()], "SRn_* do not exist on 4.7: MAVn_*"
    assert p["EK3_SRC1_YAW"] == 1, "yaw from the compass until our heading is observable"
    assert p["MAV3_RAW_SENS"] == 0, "the companion requests one IMU stream itself"


def test_vision_parm_uses_mavlink_backend_and_gps_input_is_gps2():
    v = read_parm(DEPLOY / "ardupilot-vision.parm")
    assert v["VISO_TYPE"] == 1 and v["EK3_SRC1_POSXY"] == 6 and v["EK3_SRC1_POSZ"] == 6
    g = read_parm(DEPLOY / "ardupilot-gps-input.parm")
    assert g["GPS2_TYPE"] == 14 and g["GPS_PRIMARY"] == 1 and g["GPS_AUTO_SWITCH"] == 0
    assert g.get("GPS1_TYPE", 1) != 14, "GPS1 stays the autopilot's own receiver"
    cfg = load_config(DEPLOY / "companion.toml")
    assert cfg.output.gps_input_id == 1            # GPS_INPUT addressed to GPS2
    assert cfg.output.rate_hz == 25.0
    assert not Path(cfg.log.dir).is_absolute()     # no root needed
    assert cfg.filter.zupt_enabled                 # else the heading runs away at rest (issue 13)
    assert cfg.gnss.gps_raw_latency_s > 0          # GPS_RAW_INT is stamped when the fix arrived
    assert cfg.mavlink.autopilot_heading_on_ground  # ArduPilot's yaw is its compass: hold ours on it at rest


def test_companion_config_changes_only_connection_log_source_and_mode():
    shipped = (DEPLOY / "companion.toml").read_text()
    text = companion_config(shipped, connection="tcp:127.0.0.1:5763", log_dir="/tmp/x", gnss_source="none",
                            output_mode="odometry", overrides={"filter.zupt_enabled": "true"})
    a, b = tomllib.loads(shipped), tomllib.loads(text)
    assert b["mavlink"]["connection"] == "tcp:127.0.0.1:5763" and b["log"]["dir"] == "/tmp/x"
    assert b["gnss"]["source"] == "none" and b["output"]["mode"] == "odometry"
    assert b["filter"]["zupt_enabled"] is True
    for sec, key in [("mavlink", "connection"), ("log", "dir"), ("gnss", "source"), ("output", "mode"),
                     ("filter", "zupt_enabled")]:
        del a[sec][key], b[sec][key]
    assert a == b
    # an experiment's key the file does not show lands in its own section; an unknown section fails
    c = tomllib.loads(companion_config(shipped, connection="x", log_dir="y", gnss_source="none",
                                       output_mode="vision", overrides={"gnss.extra_key_s": "0.1"}))
    assert c["gnss"]["extra_key_s"] == 0.1 and c["gnss"]["source"] == "none"
    with pytest.raises(ValueError):
        companion_config(shipped, connection="x", log_dir="y", gnss_source="none", output_mode="vision",
                         overrides={"no_section.key": "1"})


# -- one IMU stream ---------------------------------------------------------------------------
def test_auto_imu_requests_highres_only():
    cfg = load_config(DEPLOY / "companion.toml").mavlink
    assert cfg.imu_message == "auto"
    rates = M.message_rates_from_config(cfg)
    assert [k for k in rates if k in imu_streams.IMU_MESSAGES] == ["HIGHRES_IMU"]


class _Autopilot(asyncio.DatagramProtocol):
    """Acks SET_MESSAGE_INTERVAL, except for message ids in ``refuse``."""

    def __init__(self, refuse=()):
        self.refuse = set(refuse)
        self.enc = mav.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = mav.MAVLink(None)
        self.requested: list[int] = []

    def connection_made(self, transport):
        self.transport = transport

    def datagram_received(self, data, addr):
        for msg in self.parser.parse_buffer(data) or []:
            if msg.get_type() == "COMMAND_LONG" and msg.command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
                self.requested.append(int(msg.param1))
                result = mav.MAV_RESULT_DENIED if int(msg.param1) in self.refuse else mav.MAV_RESULT_ACCEPTED
                self.send(mav.MAVLink_command_ack_message(msg.command, result, 0, 0, 1, 191))

    def send(self, msg):
        self.transport.sendto(bytes(msg.pack(self.enc)))


async def _requests_with(refuse, send_highres: bool, wait_s: float):
    port = free_udp_port()
    cfg = load_config(DEPLOY / "companion.toml").mavlink
    link = M.MavlinkLink(f"udpin:127.0.0.1:{port}", message_rates_hz=M.message_rates_from_config(cfg),
                         fallback_streams=M.IMU_AUTO_FALLBACK, fallback_after_s=0.5, interval_retry_s=0.2)
    await link.start()
    loop = asyncio.get_running_loop()
    transport, ap = await loop.create_datagram_endpoint(lambda: _Autopilot(refuse), remote_addr=("127.0.0.1", port))
    try:
        ap.send(mav.MAVLink_heartbeat_message(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3))
        t_end = time.monotonic() + wait_s
        while time.monotonic() < t_end:
            if send_highres:
                ap.send(mav.MAVLink_highres_imu_message(int(time.monotonic() * 1e6), 0, 0, -9.8, 0, 0, 0,
                                                        0, 0, 0, 0, 0, 0, 0, 0))
            await asyncio.sleep(0.02)
        return ap.requested, link.counters["stream_fallbacks"]
    finally:
        transport.close()
        await link.close()


def test_imu_fallback_only_when_highres_is_refused_or_silent():
    hi, raw = mav.MAVLINK_MSG_ID_HIGHRES_IMU, mav.MAVLINK_MSG_ID_RAW_IMU
    # served: HIGHRES_IMU alone, never RAW_IMU
    req, n = asyncio.run(_requests_with((), send_highres=True, wait_s=1.5))
    assert hi in req and raw not in req and n == 0
    # refused: RAW_IMU instead
    req, n = asyncio.run(_requests_with((hi,), send_highres=False, wait_s=1.5))
    assert raw in req and n == 1
    # accepted but never sent: RAW_IMU after fallback_after_s
    req, n = asyncio.run(_requests_with((), send_highres=False, wait_s=1.5))
    assert raw in req and n == 1


# -- scoring -----------------------------------------------------------------------------------
def test_truth_mapping_and_errors_are_exact_for_a_known_offset():
    # SIMSTATE arrives 7 ms after it is sent, ATTITUDE 2-12 ms: the floor (2 ms) maps receive to boot
    rng = np.random.default_rng(1)
    t_boot = np.arange(0.0, 20.0, 0.02)
    recv_att = t_boot + 100.0 + 0.002 + 0.01 * rng.random(t_boot.size)
    recv_att[::50] = t_boot[::50] + 100.002
    to_boot = S.boot_offset(recv_att, t_boot)
    assert np.allclose(to_boot(t_boot + 100.0), 100.002, atol=1e-9)
    lat0, lon0 = -353632610.0, 1491652300.0
    lat = lat0 + np.arange(t_boot.size) * 10.0        # 11 cm per step northwards
    truth = S.Truth(t_boot, lat, np.full(t_boot.size, lon0), np.full(t_boot.size, 3.0))
    ne_true = truth.ne(t_boot[100:200], lat0, lon0)
    assert ne_true[-1, 0] == pytest.approx(199 * 10 * S.LOCATION_SCALING_FACTOR_M)
    t, err = S.horizontal_errors(t_boot[100:200], ne_true + [0.3, 0.4], truth, lat0, lon0)
    assert len(t) == 100 and np.allclose(err, 0.5)
    # yaw wraps: 3.0 rad against -3.0 rad is 0.283 rad, not 6 rad
    assert S.yaw_errors_deg([1.0], [-3.0], truth)[0] == pytest.approx(math.degrees(2 * math.pi - 6.0))
    assert S.failsafes(["EKF3 IMU0 is using external nav data", "EKF Failsafe: changed to LAND"]) == \
        ["EKF Failsafe: changed to LAND"]


# -- the real thing -----------------------------------------------------------------------------
@pytest.mark.slow
def test_arducopter_sitl_arms_hovers_and_flies_a_leg_on_our_estimate(tmp_path):
    """Short variant of ``python -m sitl ardupilot``: 20 s on the ground, one 10-m leg (~90 s)."""
    problem = binary_problem(find_binary())
    if problem:
        pytest.skip(problem)
    from sitl.ardupilot import run
    r = run(duration_s=20.0, output="vision", out_dir=str(tmp_path), side_m=10.0, legs=1)
    assert r["param_problems"] == {}, "every line of deploy/ardupilot-vision.parm exists on this firmware"
    assert r["armed"] and r["box_completed"] and r["ext_nav_used"], r.get("statustext")
    assert r["failsafes"] == []
    assert r["estimate_rate_hz"] > 22.0                  # 25 Hz configured
    assert r["ekf_origin_minus_ours_m"] == [0.0, 0.0]    # EKF3 took our origin
    assert r["rms_h_m"] < 0.6 and r["max_error_h_m"] < 1.5
    assert r["ekf_rms_h_m"] < 0.8
    assert r["companion_exit_code"] == 0


@pytest.mark.slow
def test_arducopter_sitl_flies_on_tightly_coupled_raw_gnss(tmp_path):
    """Short variant of ``python -m sitl ardupilot --gnss raw``: our receiver on SITL's truth (UBX
    on a pseudo-terminal) and base station (RTCM through the NTRIP caster), 40 s on the ground
    (SFRBX brings every ephemeris within 36 s of the first epoch), one 10-m leg at 5 m (~80 s)."""
    problem = binary_problem(find_binary())
    if problem:
        pytest.skip(problem)
    from sitl.ardupilot import run
    r = run(duration_s=40.0, output="vision", out_dir=str(tmp_path), side_m=10.0, legs=1, alt_m=5.0, gnss="raw")
    assert r["armed"] and r["box_completed"] and r["ext_nav_used"], r.get("statustext")
    assert r["failsafes"] == []
    assert r["companion_mode_flight"] == {"tight": 1.0}     # CC_MODE: tightly coupled all the flight
    h = r["companion_health"]
    assert h["ubx"]["rawx"] > 30 and h["ubx"]["ephemerides"] >= 6 and h["rtcm"]["msm4"] > 30
    assert h["engine"]["tdcp base-corrected epochs"] > 0 and h["engine"]["pseudorange used"] > 0
    assert h["filter"]["reset_counter"] == 1                # never re-initialised
    rx = r["gnss_receiver"]
    assert rx["receiver"]["rover_epochs_without_truth"] == 0 and rx["truth"]["paired"] > 1000
    assert r["rms_h_m"] < 0.5 and r["ekf_rms_h_m"] < 0.6
    assert r["companion_exit_code"] == 0 and r["gnss_receiver_exit_code"] == 0
