"""`companion replay`: a short run's field log replays bit for bit; a .tlog replays (loose)."""
import json
import struct
import subprocess
import sys

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

    # the CLI says so too, and writes JSON and a plot
    js, png = tmp_path / "replay.json", tmp_path / "replay.png"
    p = subprocess.run([sys.executable, "-m", "companion.run_cli", "replay", logdir, "--json", str(js),
                        "--plot", str(png), "--no-progress"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stdout + p.stderr
    assert "BIT FOR BIT" in p.stdout
    obj = json.loads(js.read_text())
    assert obj["comparison"]["bit_for_bit"] and obj["solutions"][0]["status"] in ("nav", "coasting")
    assert png.stat().st_size > 1000

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
    from companion.pipeline import config_event
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
