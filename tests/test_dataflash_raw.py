"""ArduPilot's GRXH/GRXS records (GPS_RAW_DATA = 1) back into RXM-RAWX (companion.io.dataflash_raw):
a real ZED-F9P capture logged as ArduPilot logs it, and the band recovered without its sigId."""
from __future__ import annotations

import math
import shutil
import subprocess

import numpy as np
import pytest

from companion.io.dataflash import read_dataflash
from companion.io.dataflash_raw import MAX_FREQUENCY_ERROR, band_of, rawx_frames
from companion.io.serial_control import UbxFrameScanner
from companion.io.ubx import RAWX_HEAD, RAWX_MEAS, UbxDecoder
from companion.messages import GnssEpoch, SPEED_OF_LIGHT_MPS
from tests._data import data_path
from tests.test_dataflash import DataFlashWriter

F9P = data_path("qzsl6tool-hiroshima-rtcm3-ubx/20230919-114418.ubx")


def log_as_ardupilot(rawx_payloads, path, *, drop_every: int = 0):
    """A DataFlash log of RXM-RAWX payloads as AP_GPS_UBLOX::log_rxm_rawx writes them: a GRXH,
    then one GRXS per measurement (every field but sigId), all with the TimeUS of the logging;
    ``drop_every``: every n-th GRXS lost (a full log buffer)."""
    w = DataFlashWriter.with_formats("GRXH", "GRXS")
    k = 0
    for i, p in enumerate(rawx_payloads):
        t_us = 10_000_000 + i * 1_000_000 + 80_000
        tow, week, leap, n, stat, _ver = RAWX_HEAD.unpack_from(p, 0)
        w.write("GRXH", t_us, tow, week, leap, n, stat)
        for j in range(n):
            pr, cp, do, gnss, sv, _sig, freq, lock, cno, prd, cpd, dod, trk = RAWX_MEAS.unpack_from(p, 16 + 32 * j)
            k += 1
            if drop_every and k % drop_every == 0:
                continue
            w.write("GRXS", t_us, pr, cp, do, gnss, sv, freq, lock, cno, prd, cpd, dod, trk)
    return w.save(path)


def _rawx_payloads(data: bytes) -> list[bytes]:
    return [payload for cls, mid, payload in UbxFrameScanner().feed(data) if (cls, mid) == (0x02, 0x15)]


def _epochs(frames) -> list[GnssEpoch]:
    dec = UbxDecoder()
    out = []
    for frame in frames:
        out += [m for m in dec.feed(frame) if isinstance(m, GnssEpoch)]
    return out


def _key(o):
    return (o.sat, o.signal)


def test_a_real_f9p_logged_by_ardupilot_decodes_as_its_own_frames(tmp_path):
    """36 epochs of a ZED-F9P (GPS L1/L2, Galileo E1/E5b, BeiDou B1I/B2I, QZSS L1/L2, GLONASS
    L1/L2, SBAS): every measurement comes back on its own signal, value for value, from the
    GRXH/GRXS records alone."""
    data = F9P.read_bytes()
    payloads = _rawx_payloads(data)
    assert len(payloads) == 36
    log = read_dataflash(log_as_ardupilot(payloads, tmp_path / "f9p.BIN"))
    assert len(log.raw_epochs) == 36 and log.raw_orphans == 0
    frames, counters = rawx_frames(log.raw_epochs)
    theirs = _epochs([f for _, f in frames])
    ours = _epochs([data])                   # the receiver's own frames
    assert len(ours) == len(theirs) == 36
    n_meas = n_same = 0
    for a, b in zip(ours, theirs):
        assert a.t_gps == b.t_gps
        by_key = {_key(o): o for o in b.observations}
        for o in a.observations:
            n_meas += 1
            p = by_key.get(_key(o))
            n_same += p is not None and _values(p) == _values(o)
    lost = sum(v for k, v in counters.items() if k.startswith("raw measurements dropped"))
    print(f"{n_meas} measurements, {n_same} back on their own signal, counters {dict(counters)}")
    assert n_same + lost == n_meas and n_same >= 0.98 * n_meas
    assert {o.signal for e in theirs for o in e.observations} >= {"L1C", "L2L", "L7Q", "L2I", "L7I", "L2C"}


def _values(o) -> tuple:
    """The measurement's values, NaN written as None (so that two missing carriers compare equal)."""
    return tuple(None if isinstance(v, float) and math.isnan(v) else v
                 for v in (o.pseudorange_m, o.carrier_cycles, o.doppler_hz, o.lock_time_s, o.cn0_dbhz,
                           o.half_cycle_ambiguous, o.wavelength_m))


def test_records_lost_from_the_log_are_counted_not_guessed(tmp_path):
    payloads = _rawx_payloads(F9P.read_bytes())[:5]
    log = read_dataflash(log_as_ardupilot(payloads, tmp_path / "lossy.BIN", drop_every=7))
    frames, counters = rawx_frames(log.raw_epochs)
    assert len(frames) == 5 and counters["raw epochs with records missing (numMeas)"] == 5


def test_records_that_no_u_blox_writes_are_counted(tmp_path):
    """A GRXS before any GRXH, an unknown system, a pseudorange that is not a number, a carrier
    that fits no band, a header promising 255 measurements: counted, nothing raised, the one
    good measurement kept."""
    w = DataFlashWriter.with_formats("GRXH", "GRXS")
    pr = 22_000_000.0
    l1 = pr * 1575.42e6 / SPEED_OF_LIGHT_MPS
    w.write("GRXS", 1_000, pr, l1, 0.0, 0, 5, 0, 1000, 40, 0, 0, 0, 7)              # no header yet
    w.write("GRXH", 2_000, 100.0, 2300, 18, 255, 1)
    w.write("GRXS", 2_000, pr, l1, 0.0, 4, 1, 0, 1000, 40, 0, 0, 0, 7)              # gnssId 4 (IMES)
    w.write("GRXS", 2_000, float("nan"), l1, 0.0, 0, 6, 0, 1000, 40, 0, 0, 0, 7)
    w.write("GRXS", 2_000, pr, 3.0 * l1, 0.0, 0, 7, 0, 1000, 40, 0, 0, 0, 7)
    w.write("GRXS", 2_000, pr, l1, 0.0, 0, 8, 0, 1000, 40, 0, 0, 0, 7)               # the good one
    log = read_dataflash(w.save(tmp_path / "odd.BIN"))
    assert log.raw_orphans == 1 and len(log.raw_epochs) == 1
    frames, counters = rawx_frames(log.raw_epochs)
    assert len(frames) == 1 and counters["raw measurements dropped: unknown system"] == 1
    assert counters["raw measurements dropped: carrier fits no band"] == 2
    assert counters["raw epochs with records missing (numMeas)"] == 1
    epochs = _epochs([f for _, f in frames])
    assert [(o.sat, o.signal) for o in epochs[0].observations] == [("G08", "L1C")]


def test_the_band_from_carrier_and_pseudorange():
    pr = 23_000_000.0
    def cp(f_hz, rel=0.0):
        return pr * f_hz / SPEED_OF_LIGHT_MPS * (1.0 + rel)
    assert band_of(0, 5, 0, pr, cp(1575.42e6)) == "1"
    assert band_of(0, 5, 0, pr, cp(1227.60e6, 3e-3)) == "2"
    assert band_of(0, 5, 0, pr, cp(1176.45e6)) == "5"
    # Galileo E5a and E5b, 2.6 % apart: each its own up to half way, nothing beyond
    assert band_of(2, 11, 0, pr, cp(1176.45e6, 0.012)) == "5"
    assert band_of(2, 11, 0, pr, cp(1207.14e6, -0.012)) == "7"
    assert band_of(2, 11, 0, pr, cp(1191.795e6)) is None                   # half way: not told
    # GLONASS: the slot's own carriers (k = freqId - 7)
    assert band_of(6, 3, 7 + 4, pr, cp(1602.0e6 + 4 * 0.5625e6)) == "1"
    assert band_of(6, 3, 7 + 4, pr, cp(1246.0e6 + 4 * 0.4375e6)) == "2"
    # a carrier count not started near the pseudorange, no carrier, no pseudorange
    assert band_of(0, 5, 0, pr, cp(1575.42e6, 2 * MAX_FREQUENCY_ERROR)) is None
    assert band_of(0, 5, 0, pr, 0.0) is None and band_of(0, 5, 0, 0.0, 1e8) is None


# ------------------------------------------------------------------ a flight's log, end to end
def _sim_flight_bin(sim, path, *, gps_east_bias_m: float, leap_s: int = 13):
    """An ArduPilot-like DataFlash log of a simulated flight: IMU at the simulated rate, GPS/GPA at
    each epoch (its position from the truth moved ``gps_east_bias_m`` east: a fix we can tell from
    the raw solution), ATT and SIM (truth) at 10 Hz, the lever arm as GPS_POS1, and the receiver's
    RXM-RAWX as GRXH/GRXS records 80 ms after each epoch."""
    from companion.nav.earth import C_n_e, dcm_to_euler, ecef_to_geodetic
    from sitl.autopilot import rawx_frame
    w = DataFlashWriter.with_formats("PARM", "IMU", "GPS", "GPA", "ATT", "SIM", "GRXH", "GRXS")
    tr = sim.truth
    boot0 = math.floor(float(tr.t_gps[0])) - 20.0          # boot time 20 s at the flight's start
    def us(t_gps):
        return int(round((t_gps - boot0) * 1e6))
    for name, value in zip(("GPS_POS1_X", "GPS_POS1_Y", "GPS_POS1_Z"), sim.lever_arm_b):
        w.write("PARM", us(tr.t_gps[0]), name, float(value))
    events = [(us(s.t_gps), 0, s) for s in sim.imu]
    for k in range(0, len(tr.t_gps), max(1, int(round(0.1 / float(tr.t_gps[1] - tr.t_gps[0]))))):
        events.append((us(tr.t_gps[k]), 1, k))
    for ep in sim.rover_epochs:
        events.append((us(ep.t_gps) + 60_000, 2, ep))
        events.append((us(ep.t_gps) + 80_000, 3, ep))
    def llh_deg(r_e):
        lat, lon, h = ecef_to_geodetic(r_e)
        return math.degrees(lat), math.degrees(lon), h
    for t_us, kind, item in sorted(events, key=lambda e: (e[0], e[1])):
        if kind == 0:
            s = item
            w.write("IMU", t_us, 0, *(np.asarray(s.dtheta_b) / s.dt_s), *(np.asarray(s.dv_b) / s.dt_s), 1, 1)
        elif kind == 1:
            lat, lon, h = llh_deg(tr.r_e[item])
            C_b_n = C_n_e(math.radians(lat), math.radians(lon)).T @ tr.C_b_e[item]
            roll, pitch, yaw = (math.degrees(a) for a in dcm_to_euler(C_b_n))
            w.write("ATT", t_us, roll, pitch, yaw % 360.0)
            w.write("SIM", t_us, lat, lon, h)
        elif kind == 2:
            k = int(np.argmin(np.abs(tr.t_gps - item.t_gps)))
            lat, lon, h = llh_deg(tr.r_e[k])
            lon += gps_east_bias_m / (111_320.0 * math.cos(math.radians(lat)))
            v_n = C_n_e(math.radians(lat), math.radians(lon)).T @ tr.v_e[k]
            week = int(item.t_gps // 604800)
            gms = int(round((item.t_gps - week * 604800) * 1000))
            w.write("GPS", t_us, 0, 3, gms, week, 10, 0.9, lat, lon, h, math.hypot(v_n[0], v_n[1]),
                    math.degrees(math.atan2(v_n[1], v_n[0])) % 360.0, float(v_n[2]), 0.0)
            w.write("GPA", t_us, 0, 1.2, 1.0, 1.5, 0.3, h)
        else:
            p = rawx_frame(item, leap_s)[6:-2]
            tow, week, leap, n, stat, _ver = RAWX_HEAD.unpack_from(p, 0)
            w.write("GRXH", t_us, tow, week, leap, n, stat)
            for j in range(n):
                pr, cp, do, gnss, sv, _sig, freq, lock, cno, prd, cpd, dod, trk = RAWX_MEAS.unpack_from(p, 16 + 32 * j)
                w.write("GRXS", t_us, pr, cp, do, gnss, sv, freq, lock, cno, prd, cpd, dod, trk)
    return w.save(path)


def test_a_flight_log_with_raw_observations_is_tightly_coupled(tmp_path):
    """The simulated survey flight as a DataFlash log whose GPS fixes are 6 m east of the truth:
    without a navigation file the replay can only follow them (loosely coupled, metres off and
    says what --nav would add); with the RINEX navigation file the GRXH/GRXS observations drive
    it (tightly coupled, every epoch decoded, the header's Klobuchar model) and the 6 m are gone
    (standalone: no base; measured 1.6 m RMS against 5.9 m)."""
    from companion.replay import replay
    from sitl.fly import load_sim
    from sitl.sky import GEONET_NAV
    sim = load_sim("uav", 0, 70.0)
    log = _sim_flight_bin(sim, tmp_path / "flight.BIN", gps_east_bias_m=6.0)
    loose = replay(log)
    tight = replay(log, nav_path=str(GEONET_NAV))
    h_loose = loose.truth_score["ours"]["horizontal"]
    h_tight = tight.truth_score["ours"]["horizontal"]
    print(f"loose RMS {h_loose['rms_m']:.2f} m, tight RMS {h_tight['rms_m']:.2f} m (p95 {h_tight['p95_m']:.2f}); "
          f"{tight.log_stats['raw_gnss']}; notes {tight.notes}")
    assert any("give --nav" in n for n in loose.notes)
    assert loose.pipeline_health["filter"]["mode"] == "loose" and h_loose["rms_m"] > 4.0
    assert tight.pipeline_health["filter"]["mode"] == "tight"
    assert tight.pipeline_health["pipeline"]["rover epochs"] == len(sim.rover_epochs)
    assert tight.log_stats["raw_gnss"] == {"raw epochs rebuilt as RXM-RAWX": len(sim.rover_epochs)}
    assert tight.pipeline_health["pipeline"]["klobuchar from the RINEX navigation header"] == 1
    assert h_tight["rms_m"] < min(2.5, 0.5 * h_loose["rms_m"]) and h_tight["n"] >= 0.8 * h_loose["n"]


@pytest.mark.skipif(shutil.which("convbin") is None, reason="RTKLIB's convbin (Debian rtklib) is not installed")
def test_a_flight_log_with_raw_observations_and_a_base_file_is_dgps(tmp_path):
    """The same log with the base station's RINEX observations (its capture converted by RTKLIB's
    convbin, the position in the header): the corrections reach the filter and the track comes
    to DGPS grade."""
    from companion.replay import replay
    from sitl.autopilot import rawx_frame
    from sitl.fly import load_sim
    from sitl.sky import GEONET_NAV
    sim = load_sim("uav", 0, 70.0)
    log = _sim_flight_bin(sim, tmp_path / "flight.BIN", gps_east_bias_m=6.0)
    (tmp_path / "base.ubx").write_bytes(b"".join(rawx_frame(ep, 13) for ep in sim.base_epochs))
    subprocess.run(["convbin", "-r", "ubx", "-od", "-os", "-o", str(tmp_path / "base.obs"),
                    "-hp", "/".join(f"{x:.4f}" for x in sim.base.r_e), str(tmp_path / "base.ubx")],
                   check=True, capture_output=True)
    alone = replay(log, nav_path=str(GEONET_NAV))
    dgps = replay(log, nav_path=str(GEONET_NAV), base_path=str(tmp_path / "base.obs"))
    h_alone, h_dgps = (r.truth_score["ours"]["horizontal"] for r in (alone, dgps))
    print(f"standalone RMS {h_alone['rms_m']:.2f} m, with the base {h_dgps['rms_m']:.2f} m; {dgps.notes[-1]}")
    assert dgps.pipeline_health["filter"]["mode"] == "tight"
    assert dgps.pipeline_health["engine"].get("base epochs", 0) >= 0.9 * len(sim.rover_epochs)
    assert h_dgps["rms_m"] < 0.5 * h_alone["rms_m"]


def test_nav_file_problems_are_said(tmp_path):
    """--nav for a log without raw observations is said, not silently ignored; a navigation file
    that cannot be read refuses the replay (exit 3) instead of falling back to loose coupling."""
    from companion.replay import replay
    from tests.test_dataflash import synthetic_bin
    plain = synthetic_bin(tmp_path / "plain.BIN", imu_hz=50.0, duration_s=10.0)
    res = replay(plain, nav_path=str(tmp_path / "any.nav"))
    assert any("--nav given, but the log has no raw observations" in n for n in res.notes)
    from sitl.fly import load_sim
    flight = _sim_flight_bin(load_sim("uav", 0, 70.0), tmp_path / "flight.BIN", gps_east_bias_m=0.0)
    res = replay(flight, nav_path=str(tmp_path / "missing.nav"))
    assert res.refusal.startswith("cannot read the RINEX input") and not res.solutions


def test_a_flight_log_with_a_base_stations_rtcm_capture_is_dgps(tmp_path):
    """The base station as an RTCM 3 capture (1005 + MSM4, as a caster sends it) in place of RINEX."""
    from companion.replay import replay
    from sitl.caster import encode_1005
    from sitl.fly import load_sim
    from sitl.rtcm_msm import Msm4Encoder
    from sitl.sky import GEONET_NAV
    sim = load_sim("uav", 0, 70.0)
    log = _sim_flight_bin(sim, tmp_path / "flight.BIN", gps_east_bias_m=6.0)
    msm = Msm4Encoder(station_id=7)
    rtcm = tmp_path / "base.rtcm3"
    rtcm.write_bytes(b"".join((encode_1005(7, sim.base.r_e) if k % 10 == 0 else b"") + msm.encode(ep)
                              for k, ep in enumerate(sim.base_epochs)))
    dgps = replay(log, nav_path=str(GEONET_NAV), base_path=str(rtcm))
    h = dgps.truth_score["ours"]["horizontal"]
    print(f"with the RTCM base {h['rms_m']:.2f} m")
    assert dgps.pipeline_health["engine"].get("base epochs", 0) >= 0.9 * len(sim.rover_epochs)
    assert h["rms_m"] < 0.8


def test_rtk_post_processing_of_a_flight_log(tmp_path):
    """`companion gnss --rover LOG.BIN --mode rtk`: the carrier-phase track of a drone from its own
    DataFlash log (GRXH/GRXS, L1 + L2) and a base station's RTCM capture (1005 + MSM7), on the
    simulated rtk flight, against the antenna's true track; the same fixes as from the receiver's
    own RXM-RAWX capture.  (RTKLIB 2.4.3's convbin is no base maker here: it writes a dual-frequency
    RXM-RAWX's L2 carrier as L1C.)"""
    import json

    from companion.cli import main
    from sitl.autopilot import rawx_frame
    from sitl.caster import encode_1005
    from sitl.fly import load_sim
    from sitl.rtcm_msm import MultiMsm7Encoder
    from sitl.sky import GEONET_NAV
    sim = load_sim("rtk", 0, 60.0)
    log = _sim_flight_bin(sim, tmp_path / "flight.BIN", gps_east_bias_m=0.0)
    (tmp_path / "rover.ubx").write_bytes(b"".join(rawx_frame(ep, 13) for ep in sim.rover_epochs))
    msm = MultiMsm7Encoder(7)
    base = tmp_path / "base.rtcm3"
    base.write_bytes(b"".join((encode_1005(7, sim.base.r_e) if k % 10 == 0 else b"") + msm.encode(ep)
                              for k, ep in enumerate(sim.base_epochs)))
    runs = {}
    for name, rover in (("log", log), ("capture", tmp_path / "rover.ubx")):
        out = tmp_path / f"{name}.json"
        assert main(["gnss", "--rover", str(rover), "--nav", str(GEONET_NAV), "--base", str(base),
                     "--mode", "rtk", "--json", str(out)]) == 0
        runs[name] = json.loads(out.read_text())["solutions"]
    rows = runs["log"]
    fixed = [r for r in rows if r["q"] == 1]
    err = [float(np.linalg.norm(np.asarray(r["r_e"]) - sim.antenna_at(r["t_gps"]))) for r in fixed]
    print(f"{len(fixed)} of {len(rows)} epochs fixed, 3-D error median {np.median(err):.3f} m, max {max(err):.3f} m")
    assert rows == runs["capture"]
    assert len(rows) == len(sim.rover_epochs) and len(fixed) >= 0.5 * len(rows)
    assert max(err) < 0.1
