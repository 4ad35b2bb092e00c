"""`python -m sitl bench` produces its figures (how fast is the benchmark's question, not the
suite's: a loaded machine must not fail a test)."""
import math

import pytest

from sitl.bench import format_bench, run_bench


def test_bench_reports_cpu_time_rates_latency_rtk_and_startup():
    r = run_bench(duration_s=5.0)
    for k in ("imu_samples_per_s", "imu_samples_per_s_with_gnss", "imu_samples_per_cpu_s",
              "imu_samples_per_cpu_s_with_gnss", "latency_us_p50", "latency_us_p99", "rtk_epoch_cpu_ms",
              "startup_import_service_s", "peak_rss_mb",
              "propagation_58_states_dense_us", "propagation_58_states_blocks_us",
              "imu_samples_per_cpu_s_with_rtk", "imu_samples_per_s_with_rtk", "latency_us_p50_with_rtk",
              "latency_us_p99_with_rtk", "rtk_mean_rover_satellites", "rtk_epoch_latency_ms_p50"):
        assert math.isfinite(r[k]) and r[k] > 0, (k, r[k])
    assert r["imu_samples"] == 1000 and r["rtk_epochs"] >= 115
    assert r["latency_us_p50"] <= r["latency_us_p99"]
    # the RTK load really runs RTK: DD phase rows on two frequencies from the 0-deg sky
    assert r["rtk_imu_samples"] == 1000 and r["rtk_phase_rows"] > 0 and r["rtk_code_rows"] > 0
    assert r["rtk_mean_rover_signals"] > 1.5 * r["rtk_mean_rover_satellites"]
    assert r["latency_us_p50_with_rtk"] <= r["latency_us_p99_with_rtk"]
    assert r["rtk_epoch_latency_ms_p50"] * 1e3 >= r["latency_us_p50_with_rtk"]   # an epoch costs more than a sample
    text = format_bench(r)
    assert "samples/CPU-s" in text and "IMU + RTK" in text


def test_the_harness_runs_numpy_with_one_blas_thread():
    """``python -m sitl`` imports numpy through its modules: companion must set
    OPENBLAS_NUM_THREADS=1 first, or a second BLAS thread spins through every RTK epoch (the bench's
    RTK load read 24.8k samples per CPU-second at 35.8k per wall-second)."""
    import os
    import subprocess
    import sys
    if not os.path.isdir("/proc/self/task"):
        pytest.skip("counts the process's threads in /proc")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    code = ("import sitl.faults, numpy as np, os; np.ones((300, 300)) @ np.ones((300, 300)); "
            "print(len(os.listdir('/proc/self/task')))")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120,
                         cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    assert out.returncode == 0, out.stderr
    assert int(out.stdout.split()[-1]) == 1
