"""sitl.bench.export_kf_gins: the benchmark's workload in KF-GINS's input formats -- files that parse,
one IMU row per sample with the increments in rad and m/s (FRD: the z specific force of a level
flight reads -g), one GNSS row per solved rover epoch in degrees and metres near the true antenna,
and a configuration with KF-GINS's keys and the engine's initial state."""
import dataclasses
import math

import numpy as np
import pytest

from companion.nav.earth import C_n_e, ecef_to_geodetic, geodetic_to_ecef
from sitl.bench import export_kf_gins
from sitl.scenario import build_scenario
from sitl.simulate import simulate
from sitl.tuning import tuning_for

#: every key of KF-GINS's dataset/kf-gins.yaml (its reader needs them), imunoise's included
KF_GINS_KEYS = {"imupath", "gnsspath", "outputpath", "imudatalen", "imudatarate", "starttime", "endtime",
                "initpos", "initvel", "initatt", "initgyrbias", "initaccbias", "initgyrscale", "initaccscale",
                "initposstd", "initvelstd", "initattstd", "imunoise", "arw", "vrw", "gbstd", "abstd", "gsstd",
                "asstd", "corrtime", "antlever"}
#: its optional keys (commented out in that file: the bias and scale-factor sigmas at the start)
KF_GINS_OPTIONAL = {"initbgstd", "initbastd", "initsgstd", "initsastd"}


def parse_flat_yaml(text: str) -> dict:
    """The exported file's YAML subset: 'key: scalar' and 'key: [ a, b, c ]', comments, one nesting."""
    out = {}
    for line in text.splitlines():
        line = line.split("#", 1)[0].rstrip()
        if not line.strip():
            continue
        key, _, val = line.strip().partition(":")
        val = val.strip()
        if val.startswith("["):
            out[key] = [float(x) for x in val.strip("[] ").split(",")]
        elif val.startswith('"'):
            out[key] = val.strip('"')
        else:
            out[key] = float(val) if val else None
    return out


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    scn = dataclasses.replace(build_scenario("uav"), mask_deg=0.0, duration_s=30.0)
    sim = simulate(scn, 0)
    out = tmp_path_factory.mktemp("kfgins")
    return sim, export_kf_gins(sim, tuning_for(scn), out), out


def test_imu_file_counts_units_and_frame(exported):
    sim, summary, out = exported
    imu = np.loadtxt(out / "imu.txt")
    assert imu.shape == (len(sim.imu), 7) == (summary["imu_records"], 7)
    rate = sim.scenario.imu.rate_hz
    assert np.allclose(np.diff(imu[:, 0]), 1.0 / rate, atol=1e-6)           # seconds, one row per sample
    t0 = summary["start_tow_s"]
    assert imu[0, 0] == pytest.approx(t0 + 1.0 / rate, abs=1e-6) and 0 <= t0 < 604800
    assert np.allclose(imu[:, 1:4], [s.dtheta_b for s in sim.imu], rtol=1e-10, atol=1e-15)
    assert np.allclose(imu[:, 4:7], [s.dv_b for s in sim.imu], rtol=1e-10, atol=1e-15)
    f_b = imu[:, 4:7] * rate                                # specific force, m/s^2
    assert np.median(f_b[:, 2]) == pytest.approx(-9.8, abs=0.3)              # FRD: z down reads -g
    assert np.max(np.abs(imu[:, 1:4] * rate)) < 3.0                          # rad/s, not deg/s


def test_gnss_file_counts_units_and_accuracy(exported):
    sim, summary, out = exported
    g = np.loadtxt(out / "gnss.txt", ndmin=2)
    assert g.shape[1] == 7 and len(g) == summary["gnss_records"]
    t_end = sim.imu[-1].t_gps
    n_epochs = sum(1 for e in sim.rover_epochs if sim.truth.t_gps[0] <= e.t_gps <= t_end)
    assert len(g) >= 0.9 * n_epochs and len(g) <= n_epochs                  # one per solved rover epoch
    week = summary["gps_week"]
    err_h = []
    for row in g:
        t_gps = week * 604800.0 + row[0]
        r_fix = geodetic_to_ecef(math.radians(row[1]), math.radians(row[2]), row[3])
        r_true = sim.antenna_at(t_gps)
        lat, lon, _ = ecef_to_geodetic(r_true)
        d_n = C_n_e(lat, lon).T @ (r_fix - r_true)
        err_h.append(math.hypot(d_n[0], d_n[1]))
        assert abs(d_n[2]) < 10.0
        assert np.all(row[4:7] > 0.0) and np.all(row[4:7] < 10.0)            # sigmas in metres
    assert float(np.sqrt(np.mean(np.square(err_h)))) < 3.0                    # DGPS, degrees not radians


def test_config_has_kf_gins_keys_and_the_initial_state(exported):
    sim, summary, out = exported
    cfg = parse_flat_yaml((out / "kf-gins.yaml").read_text())
    assert set(cfg) == KF_GINS_KEYS | KF_GINS_OPTIONAL
    assert cfg["imudatarate"] == sim.scenario.imu.rate_hz and cfg["imudatalen"] == 7
    assert cfg["imupath"] == "imu.txt" and cfg["gnsspath"] == "gnss.txt"
    assert cfg["starttime"] == pytest.approx(summary["start_tow_s"], abs=1e-6)
    lat, lon, h = cfg["initpos"]
    r0 = geodetic_to_ecef(math.radians(lat), math.radians(lon), h)
    assert np.linalg.norm(r0 - sim.truth.r_e[0]) < 5 * 0.5 * math.sqrt(3)   # truth + a P0 draw (0.5 m)
    assert cfg["antlever"] == pytest.approx(list(sim.lever_arm_b))
    assert 0.0 <= cfg["initatt"][2] < 360.0
    assert all(v > 0 for k in ("arw", "vrw", "gbstd", "abstd") for v in cfg[k])
