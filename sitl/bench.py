"""Engine throughput benchmark: IMU samples per second through mechanization + covariance
propagation, without and with GNSS updates, per-sample latency percentiles and peak memory.

Workload: the 'uav' scenario (200 Hz MEMS IMU, real 2005 ephemeris) with the elevation mask at 0 deg
so that ~11 satellites are tracked (the issue's 10-satellite load), simulated once; the engine then
consumes the same samples twice in one process:
* IMU only;
* IMU plus 1 Hz rover epochs with DGPS-corrected pseudoranges and base-corrected TDCP (the
  production configuration), base epochs included.
Throughput comes from untimed passes; latency from separate passes that time every IMU sample
(including any GNSS epoch it releases) with perf_counter_ns.
"""
from __future__ import annotations

import dataclasses
import gc
import resource
import time

import numpy as np

from companion.nav.engine import NavEngine
from companion.nav.earth import rotation_from_rotvec

from .paper import initial_errors, mode_config
from .scenario import build_scenario
from .simulate import simulate
from .tuning import tuning_for


def _run(sim, tuning, with_gnss: bool, seed: int = 0, timed: bool = False):
    """One pass of the engine over the flight.  ``timed``: also time every sample (that timing
    costs a few microseconds itself, so throughput comes from an untimed pass)."""
    cfg = mode_config("tdcp_dgps", tuning, sim.lever_arm_b)
    cfg.elevation_mask_deg = 0.0
    eng = NavEngine(cfg)
    for eph in sim.ephemerides:
        eng.process(eph)
    eng.process(sim.base)
    truth = sim.truth
    d_att, d_pos, d_vel = initial_errors(np.random.default_rng(seed), tuning.p0, sim.truth.r_e[0])
    eng.initialize(truth.t_gps[0], truth.r_e[0] + d_pos, truth.v_e[0] + d_vel,
                   rotation_from_rotvec(d_att) @ truth.C_b_e[0], tuning.p0)
    rover, base = sim.rover_epochs, sim.base_epochs
    i_r = i_b = 0
    lat_ns = np.zeros(len(sim.imu), dtype=np.int64)
    clock = time.perf_counter_ns
    n_b, n_r = len(base), len(rover)
    gc.disable()
    t_start = clock()
    for k, s in enumerate(sim.imu):
        t0 = clock() if timed else 0
        if with_gnss:
            while i_b < n_b and base[i_b].t_gps <= s.t_gps:
                eng.process(base[i_b])
                i_b += 1
            while i_r < n_r and rover[i_r].t_gps <= s.t_gps:
                eng.process(rover[i_r])
                i_r += 1
        eng.process_imu(s)
        if timed:
            lat_ns[k] = clock() - t0
    elapsed = (clock() - t_start) * 1e-9
    gc.enable()
    return len(sim.imu) / elapsed, lat_ns, dict(eng.counters)


def run_bench(duration_s: float | None = None) -> dict:
    scenario = dataclasses.replace(build_scenario("uav"), mask_deg=0.0)
    sim = simulate(scenario, 0)
    if duration_s is not None:
        n = int(duration_s * scenario.imu.rate_hz)
        sim.imu = sim.imu[:n]
    tuning = tuning_for(scenario)
    _run(sim, tuning, True)  # warm-up (imports, caches)
    rate_imu, _, _ = _run(sim, tuning, False)
    rate_gnss, _, counters = _run(sim, tuning, True)
    _, lat_imu, _ = _run(sim, tuning, False, timed=True)
    _, lat_gnss, _ = _run(sim, tuning, True, timed=True)
    n_sats = np.mean([len({o.sat for o in e.observations}) for e in sim.rover_epochs])
    return {
        "imu_rate_hz": scenario.imu.rate_hz,
        "imu_samples": len(sim.imu),
        "mean_rover_satellites": round(float(n_sats), 2),
        "gnss_epochs": counters.get("gnss epochs", 0),
        "pseudorange_updates": counters.get("pseudorange used", 0),
        "tdcp_updates": counters.get("tdcp used", 0),
        "imu_samples_per_s": round(rate_imu, 1),
        "imu_samples_per_s_with_gnss": round(rate_gnss, 1),
        "latency_us_p50": round(float(np.percentile(lat_gnss, 50)) / 1e3, 2),
        "latency_us_p99": round(float(np.percentile(lat_gnss, 99)) / 1e3, 2),
        "latency_us_max": round(float(lat_gnss.max()) / 1e3, 2),
        "latency_us_p50_imu_only": round(float(np.percentile(lat_imu, 50)) / 1e3, 2),
        "gnss_cost_ratio": round(rate_imu / rate_gnss, 3),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
    }


def format_bench(r: dict) -> str:
    return "\n".join([
        f"engine benchmark: {r['imu_samples']} IMU samples at {r['imu_rate_hz']:.0f} Hz, "
        f"{r['mean_rover_satellites']} satellites/epoch",
        f"  IMU only            : {r['imu_samples_per_s']:>10,.0f} samples/s  (p50 {r['latency_us_p50_imu_only']} us)",
        f"  IMU + GNSS (PR+TDCP): {r['imu_samples_per_s_with_gnss']:>10,.0f} samples/s  "
        f"(p50 {r['latency_us_p50']} us, p99 {r['latency_us_p99']} us, max {r['latency_us_max']} us)",
        f"  GNSS updates: {r['pseudorange_updates']} pseudoranges, {r['tdcp_updates']} TDCP; "
        f"cost ratio with/without GNSS {r['gnss_cost_ratio']}",
        f"  peak RSS {r['peak_rss_mb']} MB",
    ])
