"""`companion export`: a field log's receiver and correction streams come back out byte for byte
(RTKLIB's convbin reads them), its solutions as KML, GPX and CSV (issue 15)."""
from __future__ import annotations

import csv
import os
import shutil
import subprocess
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from companion.cli import main
from companion.io.fieldlog import FieldLogWriter
from companion.messages import NavSolution
from companion.nav.earth import geodetic_to_ecef
from companion.log_records import encode_solution
from tests._data import data_path

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as m  # noqa: E402

UBX = data_path("qzsl6tool-hiroshima-rtcm3-ubx/20230919-114418.ubx")
RTCM = data_path("qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm")
pytestmark = pytest.mark.real_data


def _solution(k: int, inject: bool) -> NavSolution:
    r = geodetic_to_ecef(np.radians(34.4 + 1e-5 * k), np.radians(132.5), 50.0 + 0.1 * k)
    return NavSolution(t_gps=1.379e9 + 0.04 * k, r_e=r, v_e=np.array([1.0, 0.0, 0.0]), C_b_e=np.eye(3),
                       sigma_r_n_m=np.array([0.3, 0.3, 0.6]), sigma_v_n_mps=np.full(3, 0.05),
                       sigma_att_rad=np.full(3, 0.01), status="nav", reset_counter=1,
                       extras={"inject": inject, "mode": "tight", "imu_count": k, "t_boot_us": 1000 * k})


def _field_log(tmp_path):
    """A field log with the F9P's UBX through SERIAL_CONTROL replies (as the tunnel receives them),
    the base's RTCM in chunks, a HEARTBEAT, and 50 solutions (every other one injected)."""
    ubx, rtcm = UBX.read_bytes()[:60000], RTCM.read_bytes()[:40000]
    mav = m.MAVLink(None, srcSystem=1, srcComponent=1)
    w = FieldLogWriter(tmp_path / "log", background_flush=False)
    t = 0
    w.write("mavlink", bytes(mav.heartbeat_encode(2, 3, 0, 0, 4).pack(mav)), t, t)
    for i in range(0, len(ubx), 70):
        part = ubx[i:i + 70]
        msg = mav.serial_control_encode(m.SERIAL_CONTROL_DEV_GPS1, m.SERIAL_CONTROL_FLAG_REPLY, 0, 0, len(part),
                                        list(part) + [0] * (70 - len(part)))
        t += 1000
        w.write("mavlink", bytes(msg.pack(mav)), t, t)
    for i in range(0, len(rtcm), 1000):
        t += 1000
        w.write("rtcm", rtcm[i:i + 1000], t, t)
    for k in range(50):
        t += 1000
        w.write("solution", encode_solution(_solution(k, inject=k % 2 == 0)), t, t)
    w.close()
    return tmp_path / "log", ubx, rtcm


def test_raw_streams_come_back_byte_for_byte_and_convbin_reads_them(tmp_path):
    log, ubx, rtcm = _field_log(tmp_path)
    out_ubx, out_rtcm = tmp_path / "rover.ubx", tmp_path / "base.rtcm3"
    assert main(["export", str(log), "--ubx", str(out_ubx), "--rtcm", str(out_rtcm)]) == 0
    assert out_ubx.read_bytes() == ubx and out_rtcm.read_bytes() == rtcm
    if shutil.which("convbin") is None:      # RTKLIB not installed: the byte-for-byte check is the test
        return
    obs = tmp_path / "rover.obs"
    subprocess.run(["convbin", "-r", "ubx", "-o", str(obs), str(out_ubx)], check=True, capture_output=True, timeout=60)
    assert sum(1 for ln in obs.read_text().splitlines() if ln.startswith(">")) >= 5     # RINEX 3 epochs


def test_solutions_as_kml_gpx_csv(tmp_path):
    log, _, _ = _field_log(tmp_path)
    kml, gpx, csv_p = tmp_path / "t.kml", tmp_path / "t.gpx", tmp_path / "t.csv"
    assert main(["export", str(log), "--kml", str(kml), "--gpx", str(gpx), "--csv", str(csv_p)]) == 0
    ns = {"k": "http://www.opengis.net/kml/2.2", "g": "http://www.topografix.com/GPX/1/1"}
    coords = ET.parse(kml).getroot().find(".//k:coordinates", ns).text.split()
    assert len(coords) == 50
    lon, lat, h = (float(v) for v in coords[3].split(","))
    assert lat == pytest.approx(34.4 + 3e-5, abs=1e-8) and lon == pytest.approx(132.5, abs=1e-8)
    assert h == pytest.approx(50.3, abs=1e-3)
    pts = ET.parse(gpx).getroot().findall(".//g:trkpt", ns)
    assert len(pts) == 50 and pts[0].find("g:time", ns).text.endswith("Z")
    rows = list(csv.DictReader(csv_p.open()))
    assert len(rows) == 50 and rows[1]["injected"] == "0" and rows[2]["injected"] == "1"
    assert main(["export", str(log), "--csv", str(csv_p), "--injected-only"]) == 0
    assert len(list(csv.DictReader(csv_p.open()))) == 25


def test_clear_errors(tmp_path):
    assert main(["export", str(tmp_path / "nothing-here"), "--kml", str(tmp_path / "x.kml")]) == 2
    log, _, _ = _field_log(tmp_path)
    assert main(["export", str(log)]) == 2                       # no output asked for
