"""A PX4 ULog with its receiver's bytes (gps_dump, GPS_DUMP_COMM 1 and 2) replayed tightly coupled
(companion.replay_raw): the simulated survey flight written as PX4 logs it."""
from __future__ import annotations

import math

import numpy as np
import pytest

from tests._ulog_writer import ULogWriter

LEAP_S = 18                   # what companion.io.ulog takes between UTC and GPS time
GPS_EPOCH_UNIX_S = 315964800.0
DUMP_BYTES = 79               # gps_dump.data


def _flight_ulog(sim, path, receiver_chunks, *, gps_east_bias_m: float):
    """sensor_combined at the IMU rate, vehicle_gps_position per epoch (the truth moved
    ``gps_east_bias_m`` east), vehicle_attitude and the SIH-style ground truth at 10 Hz, and
    ``receiver_chunks`` ((GPS time, bytes)) as gps_dump messages of 79 bytes from the receiver."""
    from scipy.spatial.transform import Rotation

    from companion.nav.earth import C_n_e, ecef_to_geodetic
    w = ULogWriter()
    w.topic("sensor_combined", [("uint64_t", "timestamp"), ("float[3]", "gyro_rad"), ("uint32_t", "gyro_integral_dt"),
                                ("int32_t", "accelerometer_timestamp_relative"), ("float[3]", "accelerometer_m_s2")])
    w.topic("vehicle_gps_position", [
        ("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"), ("uint64_t", "time_utc_usec"),
        ("double", "latitude_deg"), ("double", "longitude_deg"), ("double", "altitude_msl_m"),
        ("double", "altitude_ellipsoid_m"), ("float", "eph"), ("float", "epv"), ("float", "hdop"), ("float", "vdop"),
        ("float", "s_variance_m_s"), ("float", "vel_n_m_s"), ("float", "vel_e_m_s"), ("float", "vel_d_m_s"),
        ("bool", "vel_ned_valid"), ("uint8_t", "fix_type"), ("uint8_t", "satellites_used")])
    w.topic("vehicle_attitude", [("uint64_t", "timestamp"), ("float[4]", "q")])
    w.topic("vehicle_global_position_groundtruth", [("uint64_t", "timestamp"), ("double", "lat"), ("double", "lon"),
                                                    ("float", "alt")])
    w.topic("gps_dump", [("uint64_t", "timestamp"), ("uint8_t", "instance"), ("uint8_t", "len"),
                         ("uint8_t[79]", "data")])
    tr = sim.truth
    boot0 = math.floor(float(tr.t_gps[0])) - 20.0
    def us(t_gps):
        return int(round((t_gps - boot0) * 1e6))
    for s in sim.imu:
        w.write("sensor_combined", us(s.t_gps), list(np.asarray(s.dtheta_b) / s.dt_s), int(s.dt_s * 1e6), 0,
                list(np.asarray(s.dv_b) / s.dt_s))
    step = max(1, int(round(0.1 / float(tr.t_gps[1] - tr.t_gps[0]))))
    for k in range(0, len(tr.t_gps), step):
        lat, lon, h = ecef_to_geodetic(tr.r_e[k])
        C_b_n = C_n_e(lat, lon).T @ tr.C_b_e[k]
        x, y, z, qw = Rotation.from_matrix(C_b_n).as_quat()
        w.write("vehicle_attitude", us(tr.t_gps[k]), [qw, x, y, z])
        w.write("vehicle_global_position_groundtruth", us(tr.t_gps[k]), math.degrees(lat), math.degrees(lon), h)
    for ep in sim.rover_epochs:
        k = int(np.argmin(np.abs(tr.t_gps - ep.t_gps)))
        lat, lon, h = ecef_to_geodetic(tr.r_e[k])
        v_n = C_n_e(lat, lon).T @ tr.v_e[k]
        lon_deg = math.degrees(lon) + gps_east_bias_m / (111_320.0 * math.cos(lat))
        utc_us = int(round((ep.t_gps - LEAP_S + GPS_EPOCH_UNIX_S) * 1e6))
        w.write("vehicle_gps_position", us(ep.t_gps) + 60_000, us(ep.t_gps), utc_us, math.degrees(lat), lon_deg, h, h,
                1.0, 1.5, 0.9, 1.2, 0.3, *v_n, True, 3, 10)
    for t_gps, data in receiver_chunks:
        for j in range(0, len(data), DUMP_BYTES):
            chunk = data[j:j + DUMP_BYTES]
            w.write("gps_dump", us(t_gps) + 70_000 + j // DUMP_BYTES, 0, len(chunk),
                    chunk + bytes(DUMP_BYTES - len(chunk)))
            if j == 0:        # the configuration PX4 sends the receiver is logged too (len's top bit)
                w.write("gps_dump", us(t_gps) + 69_000, 0, 0x80 | 8, b"\xb5\x62\x06\x8a\x00\x00\x90\x6c" + bytes(71))
    return w.save(path)


@pytest.fixture(scope="module")
def uav():
    from sitl.fly import load_sim
    from sitl.scenario import build_scenario
    return load_sim("uav", 0, 70.0), build_scenario("uav")


def test_a_px4_log_with_its_receivers_ubx_stream_is_tightly_coupled(uav, tmp_path):
    """GPS_DUMP_COMM 1: the receiver's whole UBX stream (RXM-RAWX, RXM-SFRBX) in gps_dump; the
    ephemerides come with it, so no --nav: loose on the fixes (6 m off) until the subframes have
    brought them, tightly coupled from then on, the 6 m gone."""
    from companion.replay import replay
    from tests._sim_streams import ubx_epochs
    sim, scenario = uav
    chunks = ubx_epochs(sim, scenario, math.inf, LEAP_S)
    log = _flight_ulog(sim, tmp_path / "flight.ulg", chunks, gps_east_bias_m=6.0)
    res = replay(log)
    rms_tight = _horizontal_rms(sim, [s for s in res.solutions if s.extras.get("mode") == "tight"])
    rms_loose = _horizontal_rms(sim, [s for s in res.solutions if s.extras.get("mode") == "loose"])
    print(f"loose until the ephemerides came (RMS {rms_loose:.2f} m), then tight (RMS {rms_tight:.2f} m)")
    assert any("ephemerides from its RXM-SFRBX" in n for n in res.notes)
    assert res.pipeline_health["filter"]["mode"] == "tight"
    assert res.pipeline_health["pipeline"]["rover epochs"] == len(sim.rover_epochs)
    assert rms_loose > 4.0 and rms_tight < 0.5 * rms_loose     # (from a 6-m-off loose state to tight)


def _horizontal_rms(sim, solutions) -> float:
    from companion.nav.earth import C_n_e, ecef_to_geodetic
    tr = sim.truth
    err = []
    for s in solutions:
        k = int(np.argmin(np.abs(tr.t_gps - s.t_gps)))
        lat, lon, _ = ecef_to_geodetic(tr.r_e[k])
        d = C_n_e(lat, lon).T @ (s.r_e - tr.r_e[k])
        err.append(math.hypot(d[0], d[1]))
    return float(np.sqrt(np.mean(np.square(err)))) if err else math.nan


def test_a_px4_log_with_its_receivers_rtcm_output_needs_nav_and_then_is_tight(uav, tmp_path):
    """GPS_DUMP_COMM 2: the receiver set to output RTCM 3 for PPK (its own MSM7 and 1005):
    without --nav it is said and the replay stays loose; with it, the epochs are the rover's."""
    from companion.replay import replay
    from sitl.caster import encode_1005
    from sitl.rtcm_msm import MultiMsm7Encoder
    from sitl.sky import GEONET_NAV
    sim, _ = uav
    msm = MultiMsm7Encoder(0)
    chunks = [(ep.t_gps, (encode_1005(0, sim.truth.r_e[0]) if k % 10 == 0 else b"") + msm.encode(ep))
              for k, ep in enumerate(sim.rover_epochs)]
    log = _flight_ulog(sim, tmp_path / "ppk.ulg", chunks, gps_east_bias_m=6.0)
    loose = replay(log)
    assert loose.pipeline_health["filter"]["mode"] == "loose"
    assert any("GPS_DUMP_COMM 2" in n and "--nav" in n for n in loose.notes)
    tight = replay(log, nav_path=str(GEONET_NAV))
    h = tight.truth_score["ours"]["horizontal"]
    print(f"loose RMS {loose.truth_score['ours']['horizontal']['rms_m']:.2f} m, tight RMS {h['rms_m']:.2f} m; "
          f"{tight.log_stats.get('raw_gnss')}")
    assert tight.pipeline_health["filter"]["mode"] == "tight"
    assert tight.log_stats["raw_gnss"]["rover epochs"] == len(sim.rover_epochs)
    assert h["rms_m"] < 0.5 * loose.truth_score["ours"]["horizontal"]["rms_m"]
