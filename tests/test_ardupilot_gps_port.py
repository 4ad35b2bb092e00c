"""The shipped GNSS source against the real ArduCopter SITL (../shared/ardupilot): its simulated
u-blox sends no raw observations, so the companion's probe must give the GPS port back, ArduPilot
must get its 3-D fix, and the companion must initialise loosely on GPS_RAW_INT; and the EKF
origin our outputs use must be the one ArduPilot reports (GPS_GLOBAL_ORIGIN).  About 60 s."""
from __future__ import annotations

import json
import re
import time

import pytest

from sitl import ardupilot_score as S
from sitl.ardupilot import DEPLOY
from sitl.ardupilot_gcs import Gcs
from sitl.ardupilot_procs import ArduCopterSitl, CompanionProcess, binary_problem, companion_config, find_binary
from tests._flyhelp import final_health


@pytest.mark.slow
def test_shipped_gnss_source_leaves_arducopter_its_gps_and_the_origin_is_read_back(tmp_path):
    binary = find_binary()
    problem = binary_problem(binary)
    if problem:
        pytest.skip(problem)
    toml = (DEPLOY / "companion.toml").read_text()
    assert 'source = "mavlink_serial_control"' in toml           # the shipped default, unchanged below
    sitl = ArduCopterSitl(binary, [DEPLOY / "ardupilot-vision.parm"], tmp_path / "sitl")
    gcs = companion = None
    try:
        sitl.start()
        gcs = Gcs(sitl.port(0))
        gcs.wait_heartbeat()
        gcs.request_streams({"GPS_RAW_INT": 5.0, "EKF_STATUS_REPORT": 1.0})
        cfg = tmp_path / "companion.toml"
        cfg.write_text(companion_config(toml, connection=f"tcp:127.0.0.1:{sitl.port(2)}",
                                        log_dir=str(tmp_path / "fieldlog"), gnss_source="mavlink_serial_control",
                                        output_mode="vision"))
        companion = CompanionProcess(cfg, tmp_path / "companion.log")
        companion.start()
        t0 = time.monotonic()

        def texts():
            return [t for _, t in gcs.statustext]

        def wait(cond, timeout_s):
            end = time.monotonic() + timeout_s
            while not cond() and time.monotonic() < end:
                gcs.pump(0.5)
                assert companion.alive(), companion.tail()
            return cond()

        # the probe found no RXM-RAWX and gave the port back: ArduPilot detects its u-blox, 3-D fix
        assert wait(lambda: any(m.fix_type >= 3 for _, m in gcs.records["GPS_RAW_INT"]), 40.0), texts()
        t_fix = next(t for t, m in gcs.records["GPS_RAW_INT"] if m.fix_type >= 3) - t0
        assert "CC: GPS1: no RXM-RAWX, port left to autopilot" in texts()
        # the companion initialises loosely on GPS_RAW_INT and EKF3 takes its estimates
        assert wait(lambda: any("is using external nav data" in t for t in texts()), 60.0), texts()
        assert any("CC: nav init #1: GPS_RAW_INT fix (loose)" in t for t in texts()), texts()
        # the origin: confirmed by the autopilot (ours) or adopted (EKF3's own from its GPS)
        assert wait(lambda: any(t.startswith(("CC: origin confirmed", "CC: AP origin")) for t in texts()), 10.0)
        gcs.request_message("GPS_GLOBAL_ORIGIN")
        assert wait(lambda: gcs.records["GPS_GLOBAL_ORIGIN"], 5.0)
        ap = gcs.records["GPS_GLOBAL_ORIGIN"][-1][1]
        used = companion.origin()                                 # what the outputs use (its log)
        assert (round(used[0] * 1e7), round(used[1] * 1e7)) == (ap.latitude, ap.longitude)
        assert abs(round(used[2] * 1000) - ap.altitude) <= 1
        gcs.pump(6.0)                                           # one health record more
        assert companion.stop() == 0
        h = final_health(tmp_path / "fieldlog")["health"]
        sc, org = h["serial_control"], h["origin"]
        assert sc["probes"] >= 1 and sc["claims"] == 0 and sc["raw epochs"] == 0 and sc["state"] == "released"
        assert org["confirmed"] and org["used"] == {"lat_e7": ap.latitude, "lon_e7": ap.longitude,
                                                    "alt_mm": ap.altitude}
        assert h["filter"]["mode"] == "loose"
        print(json.dumps({"gps_3d_fix_after_companion_start_s": round(t_fix, 1),
                          "probes": sc["probes"], "autopilot_gps_back_s": sc["autopilot_gps_back_s"],
                          "origin_mismatch_m": org["mismatch_m"], "origin_source": org["source"],
                          "origin_adopted": org.get("origin adopted from autopilot", 0)}))
    finally:
        if companion is not None:
            companion.stop()
        if gcs is not None:
            gcs.close()
        sitl.stop()


@pytest.mark.slow
def test_an_origin_a_ground_station_set_first_is_adopted_by_the_companion(tmp_path):
    """A GCS sets ArduPilot's EKF origin 5 m north of the vehicle before the companion starts:
    ArduPilot then ignores ours, so our NED outputs must be about its origin -- and they land
    on SITL's truth in its frame."""
    binary = find_binary()
    problem = binary_problem(binary)
    if problem:
        pytest.skip(problem)
    sitl = ArduCopterSitl(binary, [DEPLOY / "ardupilot-vision.parm"], tmp_path / "sitl")
    gcs = companion = None
    gcs_origin = (-353632610 + round(5.0 / S.LOCATION_SCALING_FACTOR_M), 1491652300, 584000)
    try:
        sitl.start()
        gcs = Gcs(sitl.port(0))
        gcs.wait_heartbeat()
        gcs.request_streams({"SIMSTATE": 10.0, "GPS_RAW_INT": 2.0})
        end = time.monotonic() + 30.0            # EKF3 takes an origin once its states are initialised
        while not gcs.records["GPS_GLOBAL_ORIGIN"] and time.monotonic() < end:
            gcs.conn.mav.set_gps_global_origin_send(1, *gcs_origin, 0)
            gcs.pump(1.0)
        org = gcs.records["GPS_GLOBAL_ORIGIN"][-1][1]
        assert (org.latitude, org.longitude) == gcs_origin[:2]
        cfg = tmp_path / "companion.toml"
        cfg.write_text(companion_config((DEPLOY / "companion.toml").read_text(),
                                        connection=f"tcp:127.0.0.1:{sitl.port(2)}",
                                        log_dir=str(tmp_path / "fieldlog"), gnss_source="mavlink_serial_control",
                                        output_mode="vision"))
        companion = CompanionProcess(cfg, tmp_path / "companion.log")
        companion.start()
        end = time.monotonic() + 60.0
        while len(gcs.records["VISION_POSITION_ESTIMATE"]) < 50 and time.monotonic() < end:
            gcs.pump(0.5)
            assert companion.alive(), companion.tail()
        texts = [t for _, t in gcs.statustext]
        assert any(re.fullmatch(r"CC: AP origin [45]\.\d\d m from ours: adopted", t) for t in texts), texts
        used = companion.origin()
        assert (round(used[0] * 1e7), round(used[1] * 1e7)) == (org.latitude, org.longitude)
        # the last estimates at rest against the truth, both about the autopilot's origin
        sim = gcs.records["SIMSTATE"][-1][1]
        truth_ne = S.ned_from_latlon_e7([sim.lat], [sim.lng], org.latitude, org.longitude)[0]
        for _, v in gcs.records["VISION_POSITION_ESTIMATE"][-10:]:
            assert abs(v.x - truth_ne[0]) < 0.3 and abs(v.y - truth_ne[1]) < 0.3, (v.x, v.y, truth_ne)
        assert abs(truth_ne[0] + 5.0) < 0.5          # the vehicle sits 5 m south of that origin
        assert companion.stop() == 0
        h = final_health(tmp_path / "fieldlog")["health"]["origin"]
        assert h["confirmed"] and h["source"] == "autopilot" and 4.5 < h["mismatch_m"] < 5.6
        assert h["origin adopted from autopilot"] == 1
        print(json.dumps({"origin_mismatch_m": h["mismatch_m"], "vision_minus_truth_m": [
            round(v.x - truth_ne[0], 3), round(v.y - truth_ne[1], 3)]}))
    finally:
        if companion is not None:
            companion.stop()
        if gcs is not None:
            gcs.close()
        sitl.stop()
