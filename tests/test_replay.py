"""`companion replay`: a short run's field log replays bit for bit; a .tlog replays (loose)."""
import json
import math
import struct
import subprocess
import sys

import pytest

from companion.io.fieldlog import read_field_log
from companion.replay import replay

from _flyhelp import run_fly


def test_replay_bit_for_bit_and_tlog(tmp_path):
    r = run_fly(tmp_path, duration_s=20.0, speedup=2.0)
    assert r["estimates_received"] > 100
    logdir = r["field_log_dir"]
    res = replay(logdir)
    c = res.comparison()
    assert c["logged_solutions"] > 100
    assert c["bit_for_bit"], c
    assert c["identical"] == c["logged_solutions"] == c["replayed_solutions"]
    # the per aid source status records: logged by the service, recomputed identically by the replay
    assert c["aid_status"]["logged"] > 10 and c["aid_status"]["identical"] == c["aid_status"]["logged"]
    assert all(math.isfinite(s.extras["hpl_m"]) for s in res.solutions if s.extras["inject"])

    # an old field log (solution records version 1, no aid_status records) still replays bit for bit
    from companion.io.fieldlog import FieldLogWriter
    from companion.log_records import _SOL_V1
    old = tmp_path / "old_log"
    w = FieldLogWriter(old)
    for rec in read_field_log(logdir):
        if rec.kind == "aid_status":
            continue
        payload = rec.payload
        if rec.kind == "solution":
            payload = _SOL_V1.pack(1, *_SOL_V1.unpack(payload[:_SOL_V1.size])[1:])
        w.write(rec.kind, payload, rec.t_mono_ns, rec.t_wall_ns)
    w.close()
    res_old = replay(old)
    c_old = res_old.comparison()
    assert c_old["bit_for_bit"] and c_old["logged_solutions"] == c["logged_solutions"], c_old
    assert "aid_status" not in c_old and len(res_old.aid_status) == len(res.aid_status)   # recomputed

    # the CLI says so too, and writes JSON and a plot
    js, png = tmp_path / "replay.json", tmp_path / "replay.png"
    p = subprocess.run([sys.executable, "-m", "companion.run_cli", "replay", logdir, "--json", str(js),
                        "--plot", str(png), "--no-progress"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "BIT FOR BIT" in p.stdout
    obj = json.loads(js.read_text())
    assert obj["comparison"]["bit_for_bit"] and obj["solutions"][0]["status"] in ("nav", "coasting")
    assert png.stat().st_size > 1000
    assert (tmp_path / "replay.aid.png").stat().st_size > 1000      # innovations, test ratios, HPL

    # the MAVLink part of the field log as a .tlog (8-byte big-endian UNIX us + frame)
    tlog = tmp_path / "flight.tlog"
    n = 0
    with tlog.open("wb") as fh:
        for rec in read_field_log(logdir):
            if rec.kind == "mavlink":
                fh.write(struct.pack(">Q", rec.t_wall_ns // 1000) + rec.payload)
                n += 1
    cfg_toml = (tmp_path / "fly" / "companion.toml")
    from companion.config import load_config
    t = replay(str(tlog), load_config(cfg_toml))
    assert t.records >= n * 0.99
    # no RTCM in a tlog: no ephemerides, so the pipeline falls back to GPS_RAW_INT (loose)
    assert t.solutions and t.solutions[-1].extras["mode"] == "loose"
    assert t.pipeline_health["pipeline"].get("loose fixes fused", 0) > 5


def test_replay_of_a_log_whose_config_this_version_cannot_read_says_so(tmp_path):
    """A field log written by a newer version (a config key this one does not know) is not
    silently replayed with defaults: the CLI names the problem and the way out (--config)."""
    from companion.config import config_from_dict
    from companion.io.fieldlog import FieldLogWriter
    from companion.log_records import config_event
    logdir = tmp_path / "log"
    w = FieldLogWriter(logdir)
    ev = json.loads(config_event(config_from_dict({})))
    ev["toml"] = ev["toml"].replace("[mavlink]", "[mavlink]\nsome_future_key = 1", 1)
    w.write("event", json.dumps(ev).encode())
    w.write("solution", b"\x00" * 8)
    w.close()
    p = subprocess.run([sys.executable, "-m", "companion.run_cli", "replay", str(logdir), "--no-progress"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == 2, p.stdout + p.stderr
    assert "cannot be read by this version" in p.stderr and "some_future_key" in p.stderr
    assert "--config" in p.stderr


def test_replay_of_a_log_made_with_antenna_calibrations_finds_them_or_says_why(tmp_path):
    """A field log of a service with [filter] rtk_antennas replayed on a machine without that file:
    the replay runs and its notes say why RTK solutions will differ; given the file
    (--antennas-file) it says nothing."""
    from companion.config import loads_config
    from companion.io.fieldlog import FieldLogWriter
    from companion.log_records import config_event
    from tests.test_rtk_antennas import _antex_text
    atx = tmp_path / "flight.atx"
    atx.write_text(_antex_text({"JAVGRANT_G5T    NONE": (0.0, {"G01": ([0.0, 0.0, 60.0], [0.0] * 19, None)})}))
    cfg = loads_config("[corrections]\nsource = 'file'\n[corrections.file]\npath = 'base.rtcm3'\n"
                       f"[filter]\nrtk_enabled = true\nrtk_antennas = '{atx}'\n")
    logdir = tmp_path / "log"
    w = FieldLogWriter(logdir)
    w.write("event", config_event(cfg))
    w.close()
    kept = tmp_path / "kept.atx"
    kept.write_bytes(atx.read_bytes())
    atx.unlink()
    out = {}
    for name, extra in (("without", []), ("given", ["--antennas-file", str(kept)])):
        js = tmp_path / f"{name}.json"
        subprocess.run([sys.executable, "-m", "companion.run_cli", "replay", str(logdir), "--no-progress",
                        "--json", str(js), *extra], capture_output=True, text=True, timeout=60)
        out[name] = json.loads(js.read_text())
    assert out["without"]["config_from"] == "field log"
    assert any("replayed without them" in n for n in out["without"]["notes"])
    assert not any("antenna" in n for n in out["given"]["notes"])


def _write_tlog(path, imu_hz: float, duration_s: float = 30.0, system_time: bool = True):
    """A ground-station tlog of a vehicle at rest: HEARTBEAT, SYSTEM_TIME, ATTITUDE and
    GPS_RAW_INT at 1 Hz, RAW_IMU at ``imu_hz`` (as a GCS streams them), 8-byte UNIX-us stamps."""
    import os
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import ardupilotmega as m
    mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
    unix0_us, boot0_ms = 1_700_000_000_000_000, 60_000
    events = [(k * 1000.0, "slow", k) for k in range(int(duration_s))]
    events += [(k * 1000.0 / imu_hz, "imu", k) for k in range(int(duration_s * imu_hz))]
    with open(path, "wb") as fh:
        for t_ms, kind, k in sorted(events):
            boot_ms = boot0_ms + int(round(t_ms))
            if kind == "imu":
                msgs = [m.MAVLink_raw_imu_message(boot_ms * 1000, 0, 0, -1000, 0, 0, 0, 0, 0, 0)]
            else:
                msgs = [m.MAVLink_heartbeat_message(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0,
                                                    m.MAV_STATE_STANDBY, 3),
                        m.MAVLink_attitude_message(boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
                        m.MAVLink_gps_raw_int_message(boot_ms * 1000, 3, -353632613, 1491652297, 584090,
                                                      80, 120, 0, 0, 12)]
                if system_time:
                    msgs.append(m.MAVLink_system_time_message(unix0_us + int(t_ms * 1000), boot_ms))
            for msg in msgs:
                fh.write(struct.pack(">Q", unix0_us + int(t_ms * 1000)) + bytes(msg.pack(mav)))
    return path


def test_tlog_with_1hz_imu_says_why_and_exits_nonzero(tmp_path):
    """Issue 15: a real ground-station tlog with RAW_IMU at ~1 Hz gave 0 solutions, exit 0 and no
    reason.  Now it names the rate found and the rate needed and exits with EXIT_NO_SOLUTION."""
    from companion.replay import EXIT_NO_SOLUTION, IMU_RATE_NEEDED_HZ
    tlog = _write_tlog(tmp_path / "gcs.tlog", imu_hz=1.0)
    res = replay(str(tlog))
    assert res.imu_check["stream"] == "RAW_IMU" and res.imu_check["rate_hz"] == pytest.approx(1.0)
    assert res.refusal and not res.solutions
    js = tmp_path / "gcs.json"
    p = subprocess.run([sys.executable, "-m", "companion.run_cli", "replay", str(tlog), "--no-progress",
                        "--json", str(js)], capture_output=True, text=True, timeout=60)
    assert p.returncode == EXIT_NO_SOLUTION, p.stdout + p.stderr
    assert "RAW_IMU at 1.00 Hz" in p.stderr and f"at least {IMU_RATE_NEEDED_HZ:.0f} Hz" in p.stderr
    assert "DataFlash" in p.stderr                                 # and what to do instead
    assert json.loads(js.read_text())["refusal"]


def test_tlog_that_gives_no_solution_says_why(tmp_path):
    """Enough IMU, but no SYSTEM_TIME (so no GPS time): no solution, a reason, a non-zero exit."""
    from companion.replay import EXIT_NO_SOLUTION
    tlog = _write_tlog(tmp_path / "notime.tlog", imu_hz=50.0, duration_s=10.0, system_time=False)
    p = subprocess.run([sys.executable, "-m", "companion.run_cli", "replay", str(tlog), "--no-progress"],
                       capture_output=True, text=True, timeout=60)
    assert p.returncode == EXIT_NO_SOLUTION, p.stdout + p.stderr
    assert "RAW_IMU at 50.0 Hz" in p.stdout and "no solution" in p.stderr and "SYSTEM_TIME" in p.stderr
