"""`python -m sitl bench` produces its figures (how fast is the benchmark's question, not the
suite's: a loaded machine must not fail a test)."""
import math

from sitl.bench import format_bench, run_bench


def test_bench_reports_cpu_time_rates_latency_rtk_and_startup():
    r = run_bench(duration_s=5.0)
    for k in ("imu_samples_per_s", "imu_samples_per_s_with_gnss", "imu_samples_per_cpu_s",
              "imu_samples_per_cpu_s_with_gnss", "latency_us_p50", "latency_us_p99", "rtk_epoch_cpu_ms",
              "startup_import_service_s", "peak_rss_mb",
              "propagation_58_states_dense_us", "propagation_58_states_blocks_us"):
        assert math.isfinite(r[k]) and r[k] > 0, (k, r[k])
    assert r["imu_samples"] == 1000 and r["rtk_epochs"] >= 115
    assert r["latency_us_p50"] <= r["latency_us_p99"]
    assert "samples/CPU-s" in format_bench(r)
