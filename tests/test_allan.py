"""Allan deviation and noise-term fits (companion.nav.allan), and `companion allan` end to end."""
import argparse
import json
import math

import numpy as np
import pytest

from companion.nav.allan import (BI_FACTOR, analyse_imu, fit_allan, overlapping_adev, simulate_static_imu)

FS = 100.0
N_SAMPLES = int(3 * 3600 * FS)       # 3 h at 100 Hz


def _params(n_white, tau_n, tau_k):
    """(N, B, K) with the white/flat crossing at tau_n and the flat/RRW crossing at tau_k."""
    b = n_white / math.sqrt(tau_n) / BI_FACTOR
    return n_white, b, BI_FACTOR * b * math.sqrt(3.0 / tau_k)


def test_white_noise_allan_deviation_is_exact():
    rng = np.random.default_rng(3)
    y = rng.standard_normal(200_000) * 0.01 * math.sqrt(FS)     # N = 0.01 /sqrt(s)
    tau, adev, ncl = overlapping_adev(y, FS)
    sel = tau <= 10
    assert np.max(np.abs(adev[sel] * np.sqrt(tau[sel]) / 0.01 - 1)) < 0.05
    assert np.all(np.diff(tau) > 0) and tau[0] == 1 / FS


@pytest.mark.parametrize("sensor,n_white", [("gyro", 2.9e-5), ("accel", 1e-3)])
def test_fitted_noise_terms_match_generator(sensor, n_white):
    """3 h static recording: white (N), flicker bias instability (B), rate random walk (K).
    N and B per axis within 10 %; K (whose estimate from one 3-h record scatters ~5 % 1-sigma per
    axis: few independent long clusters) as the three-axis mean within 10 %."""
    N, B, K = _params(n_white, 0.3, 30.0)
    rng = np.random.default_rng(11 if sensor == "gyro" else 12)
    y = simulate_static_imu(rng, N_SAMPLES, FS, N, B, K, bias=0.01)
    tau, adev, ncl = overlapping_adev(y - y.mean(axis=0), FS)
    fits = [fit_allan(tau, adev[:, j], ncl) for j in range(3)]
    for f in fits:
        print(f"{sensor}: N {f.N / N:.3f} B {f.B / B:.3f} K {f.K / K:.3f} (ratios to generator)")
        assert abs(f.N / N - 1) < 0.10
        assert abs(f.B / B - 1) < 0.10
    assert abs(np.mean([f.K for f in fits]) / K - 1) < 0.10


def _write_tlog(path, n, fs, N_g, N_a, rng, raw_n=0):
    import struct

    from companion.allan_cli import mavlink2_mavutil
    mavutil = mavlink2_mavutil()
    path.touch()     # mavutil opens an existing file as a log (else it tries a serial port)
    out = mavutil.mavlink_connection(str(path), write=True, source_system=1)

    def put(t_us, msg):   # .tlog record: 8-byte big-endian receive time in us, then the packet
        out.write(struct.pack(">Q", t_us) + msg.pack(out.mav))
    g = rng.standard_normal((n, 3)) * N_g * math.sqrt(fs) + np.array([1e-3, -2e-3, 5e-4])
    a = rng.standard_normal((n, 3)) * N_a * math.sqrt(fs) + np.array([0.0, 0.0, -9.80665])
    for k in range(n):
        t_us = int(1_000_000 + k * 1e6 / fs)
        put(t_us, out.mav.highres_imu_encode(t_us, a[k, 0], a[k, 1], a[k, 2], g[k, 0], g[k, 1], g[k, 2],
                                             0, 0, 0, 0, 0, 0, 0, 0))
        if k < raw_n:   # a second IMU as ArduPilot RAW_IMU id 1: mG and mrad/s
            put(t_us, out.mav.raw_imu_encode(t_us, 0, 0, -1000, 10, -20, 5, 0, 0, 0, id=1, temperature=25))
    out.close()


def _cli(argv):
    from companion.allan_cli import register
    p = argparse.ArgumentParser()
    register(p.add_subparsers())
    a = p.parse_args(argv)
    return a.func(a)


def test_cli_on_a_real_tlog(tmp_path, capsys):
    N_g, N_a = 2e-4, 3e-3
    path = tmp_path / "static.tlog"
    _write_tlog(path, 30_000, 50.0, N_g, N_a, np.random.default_rng(5), raw_n=500)
    js, png = tmp_path / "a.json", tmp_path / "a.png"
    assert _cli(["allan", str(path), "--json", str(js), "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "[filter]" in text and "gyro_arw_rad_per_sqrt_s" in text
    res = json.loads(js.read_text())
    assert res["imu_id"] == 0 and res["samples"] == 30_000 and abs(res["fs_hz"] - 50.0) < 1e-6
    # white noise only: the reported densities are the generating ones (largest axis)
    assert abs(res["noise"]["gyro_arw_rad_per_sqrt_s"] / N_g - 1) < 0.10
    assert abs(res["noise"]["accel_vrw_mps_per_sqrt_s"] / N_a - 1) < 0.10
    assert png.stat().st_size > 10_000
    # the RAW_IMU unit (id 1) is selectable and its ArduPilot units are converted
    from companion.allan_cli import load_imu_log
    imu_id, t, g, a = load_imu_log(str(path), 1)
    assert imu_id == 1 and len(t) == 500
    assert np.allclose(a[0], [0, 0, -9.80665]) and np.allclose(g[0], [0.010, -0.020, 0.005])


def test_cli_on_field_log_and_npz(tmp_path):
    from pymavlink.dialects.v20 import ardupilotmega as mav

    from companion.allan_cli import load_imu_log
    from companion.io.fieldlog import FieldLogWriter
    m = mav.MAVLink(None, srcSystem=1)
    rng = np.random.default_rng(2)
    with FieldLogWriter(tmp_path / "fl") as w:
        for k in range(2000):
            msg = mav.MAVLink_highres_imu_message(1000 + k * 10_000, 0.1, 0.2, -9.8, *(rng.standard_normal(3) * 0.01),
                                                  0, 0, 0, 0, 0, 0, 0, 0, 2)
            w.write("mavlink", msg.pack(m))
    imu_id, t, g, a = load_imu_log(str(tmp_path / "fl"), None)
    assert imu_id == 2 and len(t) == 2000 and abs(np.median(np.diff(t)) - 0.01) < 1e-9
    d = np.column_stack([t, g, a])
    np.savez(tmp_path / "x.npz", data=d)
    assert np.array_equal(load_imu_log(str(tmp_path / "x.npz"))[2], g)


def test_analyse_imu_noise_block_keys():
    from companion.nav.filter import ProcessNoise
    rng = np.random.default_rng(0)
    n = 60_000
    res = analyse_imu(np.arange(n) / FS, rng.standard_normal((n, 3)) * 1e-3, rng.standard_normal((n, 3)) * 1e-2)
    ProcessNoise(**res["noise"])     # the block's keys are exactly ProcessNoise's fields
