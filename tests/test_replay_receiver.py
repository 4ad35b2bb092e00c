"""`companion replay ROVER.ubx --imu-csv IMU.csv`: a u-blox capture and an IMU recorded beside it,
post-processed through the pipeline.  The capture and the CSV are written from the simulated 'uav'
flight (real UBX bytes: RXM-RAWX from sitl.autopilot, RXM-SFRBX subframes from sitl.lnav_encode),
the CSV in another sensor frame (FLU), other units (deg/s, g) and UNIX time, so that every
conversion is exercised; the solutions are scored against the simulator's truth."""
from __future__ import annotations

import csv
import math
import shutil
import subprocess
import sys

import numpy as np
import pytest

from companion.io.imu_csv import parse_columns, parse_rotation, read_imu_csv
from companion.replay_receiver import replay_receiver, ubx_segments

DURATION_S = 90.0
LEAP_S = 18


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from sitl.autopilot import rawx_frame
    from sitl.scenario import build_scenario
    from sitl.simulate import simulate
    from tests._sim_streams import ubx_epochs
    sc = build_scenario("uav")
    sim = simulate(sc, 3)
    t0 = sim.truth.t_gps[0]
    d = tmp_path_factory.mktemp("ubx_imu")
    epochs = ubx_epochs(sim, sc, t0 + DURATION_S, LEAP_S)
    n_epochs = len(epochs)
    (d / "rover.ubx").write_bytes(b"".join(data for _, data in epochs))
    # the base station's epochs as a second capture, for a RINEX base file (convbin -hp)
    (d / "base.ubx").write_bytes(b"".join(rawx_frame(ep, LEAP_S) for ep in sim.base_epochs
                                          if ep.t_gps <= t0 + DURATION_S))
    (d / "base_xyz").write_text("/".join(f"{x:.4f}" for x in sim.base.r_e))
    # ... and as an RTCM 3 capture (1005 every 10 s, MSM4 1074 per epoch), as a caster sends it
    from sitl.caster import encode_1005
    from sitl.rtcm_msm import Msm4Encoder
    msm = Msm4Encoder(station_id=7)
    (d / "base.rtcm3").write_bytes(b"".join((encode_1005(7, sim.base.r_e) if k % 10 == 0 else b"") + msm.encode(ep)
                                            for k, ep in enumerate(e for e in sim.base_epochs
                                                                   if e.t_gps <= t0 + DURATION_S)))
    with open(d / "imu.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["unix_s", "wx_dps", "wy_dps", "wz_dps", "fx_g", "fy_g", "fz_g"])
        for s in sim.imu:
            if s.t_gps > t0 + DURATION_S + 2:
                break
            wr, f = np.degrees(s.dtheta_b / s.dt_s), s.dv_b / s.dt_s / 9.80665
            # FRD -> FLU (y and z flipped), GPS -> UNIX time
            w.writerow([f"{s.t_gps + 315964800.0 - LEAP_S:.6f}", f"{wr[0]:.9g}", f"{-wr[1]:.9g}", f"{-wr[2]:.9g}",
                        f"{f[0]:.9g}", f"{-f[1]:.9g}", f"{-f[2]:.9g}"])
        w.writerow(["not a number", "", "", "", "", "", ""])       # dropped and counted
    (d / "epochs").write_text(str(n_epochs))
    return sim, d


CSV_OPTIONS = {"columns": "t=unix_s,gx=wx_dps,gy=wy_dps,gz=wz_dps,ax=fx_g,ay=fy_g,az=fz_g", "time": "unix",
               "gyro_unit": "deg/s", "accel_unit": "g", "rotation": "x,-y,-z"}


def test_imu_csv_conversions_give_back_the_simulated_samples(flight):
    sim, d = flight
    a, counters = read_imu_csv(d / "imu.csv", **CSV_OPTIONS, leap_seconds=LEAP_S)
    assert counters["dropped: not a number"] == 1
    s = sim.imu[100]
    k = int(np.argmin(np.abs(a[:, 0] - s.t_gps)))
    assert a[k, 0] == pytest.approx(s.t_gps, abs=1e-5)
    assert a[k, 1:4] == pytest.approx(s.dtheta_b / s.dt_s, rel=1e-6, abs=1e-9)
    assert a[k, 4:7] == pytest.approx(s.dv_b / s.dt_s, rel=1e-6, abs=1e-7)


def test_column_and_rotation_errors_are_clear(flight):
    _, d = flight
    with pytest.raises(ValueError, match="no column"):
        read_imu_csv(d / "imu.csv")
    with pytest.raises(ValueError, match="QUANTITY=COLUMN"):
        parse_columns("time=unix_s")
    with pytest.raises(ValueError, match="each of x, y, z once"):
        parse_rotation("x,x,-z")
    assert (parse_rotation("x,-y,-z") @ np.array([1.0, 2.0, 3.0])).tolist() == [1.0, -2.0, -3.0]


def test_capture_and_imu_give_a_tightly_coupled_solution_on_truth(flight):
    sim, d = flight
    seg = ubx_segments((d / "rover.ubx").read_bytes())
    assert len(seg) == int((d / "epochs").read_text()) and all(b[:4] == b"\xb5\x62\x02\x15" for _, b in seg[1:])
    res = replay_receiver(d / "rover.ubx", d / "imu.csv", csv_options=CSV_OPTIONS)
    assert not res.refusal, res.refusal
    # standalone: sigma_h of metres and an HPL above output.max_hpl_m, so nothing would be injected
    # live; post-processing keeps every solution in navigation
    sols = [s for s in res.solutions if s.status == "nav"]
    assert len(sols) > 400
    assert {s.extras.get("mode") for s in sols} == {"tight"}
    tr = sim.truth
    err_h = []
    for s in sols:
        k = int(np.argmin(np.abs(tr.t_gps - s.t_gps)))
        assert abs(tr.t_gps[k] - s.t_gps) < 0.01
        from companion.nav.earth import C_n_e, ecef_to_geodetic
        lat, lon, _ = ecef_to_geodetic(tr.r_e[k])
        dn = C_n_e(lat, lon).T @ (s.r_e - tr.r_e[k])
        err_h.append(math.hypot(dn[0], dn[1]))
    rms = float(np.sqrt(np.mean(np.square(err_h))))
    sig_h = float(np.median([math.hypot(*s.sigma_r_n_m[:2]) for s in sols]))
    print(f"\nubx + IMU CSV, standalone: {len(sols)} solutions in nav, horizontal RMS {rms:.2f} m, median sigma_h {sig_h:.2f} m")
    assert rms < 5.0                       # standalone GPS L1 with broadcast orbits: metres, not tens


def test_a_capture_with_a_base_stations_rtcm_file_gives_dgps(flight):
    """The .ubx capture with the base station's RTCM 3 capture (`--base BASE.rtcm3`): its epochs
    reach the filter beside the receiver's frames and the track comes to DGPS grade."""
    sim, d = flight
    alone = replay_receiver(d / "rover.ubx", d / "imu.csv", csv_options=CSV_OPTIONS)
    dgps = replay_receiver(d / "rover.ubx", d / "imu.csv", base_path=d / "base.rtcm3", csv_options=CSV_OPTIONS)
    assert not dgps.refusal, dgps.refusal
    nav_a = [s for s in alone.solutions if s.status == "nav"]
    nav_d = [s for s in dgps.solutions if s.status == "nav"]
    rms_a, rms_d = _horizontal_rms(sim, nav_a), _horizontal_rms(sim, nav_d)
    print(f"\nubx + IMU CSV + RTCM base: standalone RMS_h {rms_a:.2f} m, with the base {rms_d:.2f} m")
    assert dgps.pipeline_health["engine"].get("base epochs", 0) > 60 and len(nav_d) > 400
    assert rms_d < 0.5 * rms_a
    bad = replay_receiver(d / "rover.ubx", d / "imu.csv", base_path=d / "imu.csv", csv_options=CSV_OPTIONS)
    assert bad.refusal.startswith("cannot read the base station's file")


def test_a_capture_that_starts_mid_frame_is_still_a_capture(flight, tmp_path):
    """A logger started mid-stream leaves a frame's tail first: it was taken for RINEX by its first
    two bytes and refused."""
    _, d = flight
    cut = tmp_path / "cut.ubx"
    cut.write_bytes((d / "rover.ubx").read_bytes()[10:])
    res = replay_receiver(cut, d / "imu.csv", csv_options=CSV_OPTIONS)
    assert not res.refusal, res.refusal
    assert sum(1 for s in res.solutions if s.status == "nav") > 400


def _horizontal_rms(sim, sols) -> float:
    from companion.nav.earth import C_n_e, ecef_to_geodetic
    tr, err = sim.truth, []
    for s in sols:
        k = int(np.argmin(np.abs(tr.t_gps - s.t_gps)))
        lat, lon, _ = ecef_to_geodetic(tr.r_e[k])
        dn = C_n_e(lat, lon).T @ (s.r_e - tr.r_e[k])
        err.append(math.hypot(dn[0], dn[1]))
    return float(np.sqrt(np.mean(np.square(err))))


@pytest.mark.skipif(shutil.which("convbin") is None, reason="RTKLIB's convbin (Debian rtklib) is not installed")
def test_rinex_observations_with_a_base_give_dgps(flight):
    """The same capture converted to RINEX by RTKLIB's convbin (rover obs + nav; the base capture
    with its position in the header): standalone as from the .ubx, and with the base DGPS-grade."""
    sim, d = flight
    for name, extra in (("rover", []), ("base", ["-hp", (d / "base_xyz").read_text()])):
        subprocess.run(["convbin", "-r", "ubx", "-od", "-os", "-o", str(d / f"{name}.obs"), "-n", str(d / f"{name}.nav"), *extra,
                        str(d / f"{name}.ubx")], check=True, capture_output=True)
    alone = replay_receiver(d / "rover.obs", d / "imu.csv", nav_path=d / "rover.nav", csv_options=CSV_OPTIONS)
    dgps = replay_receiver(d / "rover.obs", d / "imu.csv", nav_path=d / "rover.nav", base_path=d / "base.obs",
                           csv_options=CSV_OPTIONS)
    assert not alone.refusal and not dgps.refusal, (alone.refusal, dgps.refusal)
    nav_a = [s for s in alone.solutions if s.status == "nav"]
    nav_d = [s for s in dgps.solutions if s.status == "nav"]
    rms_a, rms_d = _horizontal_rms(sim, nav_a), _horizontal_rms(sim, nav_d)
    sig_d = float(np.median([math.hypot(*s.sigma_r_n_m[:2]) for s in nav_d]))
    print(f"\nRINEX + IMU CSV: standalone RMS_h {rms_a:.2f} m ({len(nav_a)}), with the base {rms_d:.2f} m "
          f"({len(nav_d)}, median sigma_h {sig_d:.2f} m)")
    assert len(nav_a) > 400 and len(nav_d) > 400 and rms_a < 5.0
    assert dgps.pipeline_health["engine"].get("base epochs", 0) > 60
    assert rms_d < rms_a and sig_d < 1.0                   # the base's corrections reached the filter
    assert any(s.extras.get("inject") for s in nav_d)      # DGPS-grade: injectable live


def test_epochs_and_imu_that_do_not_overlap_are_refused(flight, tmp_path):
    _, d = flight
    res = replay_receiver(d / "rover.ubx", d / "imu.csv", csv_options={**CSV_OPTIONS, "time": "gps"})
    assert "do not overlap" in res.refusal and "--imu-time" in res.refusal
    out = subprocess.run([sys.executable, "-m", "companion", "replay", str(d / "rover.ubx"), "--imu-csv",
                          str(d / "imu.csv"), "--imu-columns", CSV_OPTIONS["columns"], "--no-progress"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode != 0 and "do not overlap" in out.stderr
