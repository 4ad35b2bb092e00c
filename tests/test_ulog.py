"""PX4 ULog replay (companion.io.ulog + companion.replay.replay_ulog) on a real PX4 log: the SIH
box flight in tests/data/px4-sih-ulog (80 s, sensor_combined at 250 Hz, GPS at 8 Hz, SIH truth)."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from companion.io.ulog import is_sih, is_ulog, read_ulog
from companion.replay import imu_noise_at_rest, replay
from tests._data import data_path

pytestmark = pytest.mark.real_data
ULG = data_path("px4-sih-ulog/box-flight.ulg.xz")


@pytest.fixture(scope="module")
def log():
    return read_ulog(ULG)


def test_records(log):
    dlog, notes = log
    assert is_ulog(ULG) and is_sih(dlog) and dlog.firmware.startswith("PX4 99c40407")
    imu = dlog.imu[0]
    assert len(imu) > 19000 and 1e6 / np.median(np.diff(imu[:, 0])) == pytest.approx(250.0, rel=0.01)
    g = dlog.gps[0]
    assert len(g) > 600 and np.all(np.diff(g[:, 0]) > 0)
    # no UTC in a SIH log: GPS time is boot time on a fixed week, and said so
    t_gps = g[:, 3] * 604800 + g[:, 2] * 1e-3
    assert np.allclose(t_gps - g[:, 0] * 1e-6, t_gps[0] - g[0, 0] * 1e-6, atol=1e-6)
    assert any("no UTC" in n for n in notes)
    # at rest the accelerometer measures -g on z (body FRD), as EKF2 gets it
    rest = imu[(imu[:, 0] > imu[0, 0] + 1e6) & (imu[:, 0] < dlog.arm[1][0] - 1e6)]
    assert np.mean(rest[:, 6]) == pytest.approx(-9.8, abs=0.1)
    assert [a for _, a in dlog.arm] == [False, True, False]
    assert len(dlog.sim) > 3000 and len(dlog.pos) > 800
    # EKF2's attitude, level at rest to within its few degrees of tilt error on SIH's noisy IMU
    att_rest = dlog.att[dlog.att[:, 0] < dlog.arm[1][0]]
    assert len(att_rest) > 50 and np.all(np.abs(att_rest[:, 1:3]) < 5.0)


def test_euler_from_quaternion():
    """ZYX Euler angles of a body-FRD-to-NED quaternion built from known angles."""
    from companion.io.ulog import _euler_deg_from_q
    r, p, y = np.radians([10.0, -20.0, 150.0])
    cr, sr, cp, sp, cy, sy = (f(a / 2) for a in (r, p, y) for f in (np.cos, np.sin))
    q = np.array([[cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                   cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]])
    assert _euler_deg_from_q(q)[0] == pytest.approx([10.0, -20.0, 150.0], abs=1e-9)


def test_imu_noise_at_rest_is_the_allan_white_noise(log):
    dlog, _ = log
    arw, vrw, span = imu_noise_at_rest(dlog)
    assert span > 30
    # SIH's sample deviation at rest is 0.099 rad/s and 1.19 m/s^2 on its worst axes, filtered
    # before logging: the white-noise density lies below deviation x sqrt(interval) (0.0063, 0.075)
    assert 0.003 < arw < 0.0063 and 0.03 < vrw < 0.075


def test_replay_is_scored_against_sih_truth():
    res = replay(ULG)
    assert res.kind == "ulog" and not res.refusal
    assert any("IMU white noise measured at rest" in n for n in res.notes)
    assert any("Earth's rotation" in n for n in res.notes)
    sc = res.truth_score
    ours = sc["ours"]["horizontal"]["rms_m"]
    assert sc["ours"]["horizontal"]["n"] > 400
    # from the in-flight start to the end; EKF2 of this flight (GPS + the live companion's vision)
    assert ours < 0.15 and sc["ours_at_or_below_reference"]
    assert math.isfinite(sc["reference"]["horizontal"]["rms_m"])


def test_cli_replays_a_ulog(tmp_path):
    pos, kml = tmp_path / "flight.pos", tmp_path / "flight.kml"
    out = subprocess.run([sys.executable, "-m", "companion", "replay", str(ULG), "--no-progress",
                          "--pos", str(pos), "--kml", str(kml)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "against SIH truth" in out.stdout and "EKF2 vehicle_global_position" in out.stdout
    epochs = [line.split() for line in pos.read_text().splitlines() if not line.startswith("%")]
    assert len(epochs) > 400 and all(len(e) >= 14 for e in epochs)
    lat = np.array([float(e[2]) for e in epochs])
    assert np.all(np.abs(lat - 45.467) < 0.01)            # SIH's home (SIH_LOC_LAT0)
    import xml.etree.ElementTree as ET
    assert ET.parse(kml).getroot().tag.endswith("kml")
