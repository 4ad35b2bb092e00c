"""Engine throughput benchmark: IMU samples per second through mechanization + covariance
propagation, without and with GNSS updates, per-sample latency percentiles and peak memory.

Workload: the 'uav' scenario (200 Hz MEMS IMU, real 2005 ephemeris) with the elevation mask at 0 deg
so that ~11 satellites are tracked (the issue's 10-satellite load), simulated once; the engine then
consumes the same samples twice in one process:
* IMU only;
* IMU plus 1 Hz rover epochs with DGPS-corrected pseudoranges and base-corrected TDCP (the
  production configuration), base epochs included.
Throughput comes from untimed passes, as wall-clock *and* CPU-time rates (process_time: what the
process itself used, which is what means something on a shared, loaded machine); latency from
separate passes that time every IMU sample (including any GNSS epoch it releases) with
perf_counter_ns.  The same for carrier-phase RTK inside the filter (:mod:`companion.nav.rtk_update`):
the 'rtk-gec' scenario (dual-frequency GPS + Galileo + BeiDou rover, short baseline) with the mask
at 0 deg, ~19 satellites and ~38 signals per epoch (the issue's "20 satellites, two frequencies";
``rtk_workload(systems="G")`` is the older GPS-only load of ~10 satellites).  Also: the cost of one carrier-phase RTK epoch (companion.gnss.rtk, GEONET
0759/3040, L1+L2) in CPU time, the start-up time of ``import companion.service`` in a fresh
interpreter, and one covariance propagation step with 40 identity states (float ambiguities) beside
the standard 18, dense against by blocks (companion.nav.filter).
"""
from __future__ import annotations

import dataclasses
import gc
import math
import os
import resource
import subprocess
import sys
import time

import numpy as np

from companion.nav.engine import NavEngine
from companion.nav.earth import rotation_from_rotvec

from .paper import initial_errors, mode_config
from .scenario import build_scenario
from .simulate import simulate
from .tuning import tuning_for

#: the RTK load's elevation mask: as low as the simulator's sky allows, for the most satellites
RTK_MASK_DEG = 0.0


def _run(sim, tuning, with_gnss: bool, seed: int = 0, timed: bool = False, cfg=None, gnss_latency_s: float = 0.0,
         epoch_mask: np.ndarray | None = None, batched: bool = False):
    """One pass of the engine over the flight.  ``timed``: also time every sample (that timing
    costs a few microseconds itself, so throughput comes from an untimed pass).  ``cfg``: the
    engine's configuration (default: tdcp_dgps with the mask at 0 deg); ``gnss_latency_s``: GNSS
    epochs are handed over this long after their time (as :mod:`sitl.rtk_score` does);
    ``epoch_mask`` (bool, one per IMU sample): set where a rover epoch was handed over.
    ``batched``: the IMU samples as arrays through NavEngine.process_imu_batch (as a replay), the
    GNSS messages between the runs in the same order as the per-sample loop."""
    if cfg is None:
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
    lat_s = gnss_latency_s
    gc.disable()
    cpu_start = time.process_time_ns()
    t_start = clock()
    if batched:
        # the replay's form: the samples as arrays (converted inside the timing), each run of them
        # between two GNSS messages in one call (NavEngine.process_imu_batch)
        imu = sim.imu
        t = np.fromiter((s.t_gps for s in imu), float, len(imu))
        tau = np.fromiter((s.dt_s for s in imu), float, len(imu))
        th = np.array([s.dtheta_b for s in imu])
        dv = np.array([s.dv_b for s in imu])
        # before sample k: every base message due by its time, then every rover one (as the loop below)
        events = sorted([(int(np.searchsorted(t, e.t_gps + lat_s, side="left")), 0, j) for j, e in enumerate(base)]
                        + [(int(np.searchsorted(t, e.t_gps + lat_s, side="left")), 1, j)
                           for j, e in enumerate(rover)]) if with_gnss else []
        k = 0
        for k1, kind, j in events:
            if k1 >= len(t):
                break
            if k1 > k:
                eng.process_imu_batch(t[k:k1], tau[k:k1], th[k:k1], dv[k:k1])
                k = k1
            eng.process((base if kind == 0 else rover)[j])
        if k < len(t):
            eng.process_imu_batch(t[k:], tau[k:], th[k:], dv[k:])
    # the time at which the next GNSS message is due (one comparison per sample in the loop below:
    # the harness's own cost is counted with the engine's)
    inf = math.inf

    def next_due() -> float:
        return min(base[i_b].t_gps + lat_s if i_b < n_b else inf,
                   rover[i_r].t_gps + lat_s if i_r < n_r else inf) if with_gnss else inf
    t_due = next_due()
    process_imu = eng.process_imu
    for k, s in enumerate(sim.imu if not batched else ()):
        t0 = clock() if timed else 0
        if s.t_gps >= t_due:
            while i_b < n_b and base[i_b].t_gps + lat_s <= s.t_gps:
                eng.process(base[i_b])
                i_b += 1
            while i_r < n_r and rover[i_r].t_gps + lat_s <= s.t_gps:
                eng.process(rover[i_r])
                i_r += 1
                if epoch_mask is not None:
                    epoch_mask[k] = True
            t_due = next_due()
        process_imu(s)
        if timed:
            lat_ns[k] = clock() - t0
    elapsed = (clock() - t_start) * 1e-9
    cpu = (time.process_time_ns() - cpu_start) * 1e-9
    gc.enable()
    return (len(sim.imu) / elapsed, len(sim.imu) / max(cpu, 1e-9)), lat_ns, dict(eng.counters)


def rtk_workload(duration_s: float | None = None, mask_deg: float = RTK_MASK_DEG, systems: str = "GE"):
    """The issue's RTK load, "20 satellites, two frequencies": the 'rtk-gec' flight (dual-frequency
    rover, base 0.1-0.5 km away) under GPS + Galileo (L1 C/A + L2 P(Y), E1 + E5b: 19.8 satellites,
    39.6 signals above 0 deg), the elevation mask at ``mask_deg`` for simulator and engine,
    simulated once: (sim, tuning, engine configuration).  ``systems`` 'G': the former load, the
    'rtk' flight's GPS-only 2005 sky (10.2 satellites, 20.4 signals); 'GEC' adds BeiDou (38.8
    satellites).  Every system double-differenced within itself."""
    from .rtk_score import rtk_config
    scn = build_scenario("rtk" if systems == "G" else "rtk-gec")
    if systems != "G":
        scn = dataclasses.replace(scn, systems=systems,
                                  ephemerides=tuple(e for e in scn.ephemerides if e.sat[0] in systems))
    scn = dataclasses.replace(scn, mask_deg=mask_deg)
    if duration_s is not None:
        scn = dataclasses.replace(scn, duration_s=float(duration_s))
    sim = simulate(scn, 0)
    tuning = tuning_for(scn)
    return sim, tuning, rtk_config(scn, tuning)


def _rtk_epoch_cpu_s() -> tuple[float, int, float]:
    """(CPU s per RTK epoch, epochs, mean satellites) of companion.gnss.rtk on GEONET 0759/3040."""
    from pathlib import Path
    from companion.gnss.rtk_post import solve_rtk_rinex
    d = Path(__file__).resolve().parents[1] / "tests" / "data" / "rtklib-testdata-geonet-2005" / "rinex"
    if not d.is_dir():
        return float("nan"), 0, float("nan")
    args = (d / "07590920.05o", d / "30400920.05o", [d / "07590920.05n"])
    solve_rtk_rinex(*args)                 # warm-up: RINEX parsing caches, imports
    c0 = time.process_time()
    sols, _ = solve_rtk_rinex(*args)
    cpu = time.process_time() - c0
    return cpu / max(len(sols), 1), len(sols), float(np.mean([s.n_sats for s in sols])) if sols else float("nan")


def propagation_us(extra_states: int = 40, steps: int = 2000, repeats: int = 5) -> tuple[float, float]:
    """CPU microseconds of one covariance propagation step with ``extra_states`` identity states
    (e.g. float ambiguities) beside the standard 18: (dense Phi P Phi^T + Q, by blocks as the
    filter does it).  Interleaved, best of ``repeats``: a shared machine's load hits both alike."""
    from companion.nav.earth import geodetic_to_ecef, gravity_gradient_ecef
    from companion.nav.filter import ErrorStateKalmanFilter, ProcessNoise
    noise = ProcessNoise(3e-4, 3e-3, 1e-5, 1e-4, imu_time_offset_rw_s_per_sqrt_s=1e-4)
    rng = np.random.default_rng(0)
    A = rng.normal(size=(18, 18)) * 0.1
    kf = ErrorStateKalmanFilter(A @ A.T + np.eye(18), noise)
    for i in range(extra_states):
        kf.add_block(f"amb {i}", 1, 1.0, 1e-6)
    C, dv = np.eye(3), np.array([0.01, -0.02, -0.049])
    G = gravity_gradient_ecef(geodetic_to_ecef(0.6, 2.4, 100.0))
    kf.propagate(C, dv, G, 0.005)
    phi, Q = kf.transition_matrix(), kf.process_noise_matrix()
    phi_T, out = phi.T, np.empty_like(kf.P)
    P_dense = kf.P.copy()

    def dense():
        nonlocal P_dense
        np.matmul(phi, P_dense, out=out)
        P_dense = out @ phi_T
        P_dense += Q

    best = [math.inf, math.inf]
    for _ in range(repeats):
        for j, step in enumerate((dense, lambda: kf.propagate(C, dv, G, 0.005))):
            c0 = time.process_time()
            for _ in range(steps):
                step()
            best[j] = min(best[j], (time.process_time() - c0) / steps * 1e6)
    return best[0], best[1]


def _startup_s() -> float:
    """Wall time of a fresh interpreter importing the service (what a restart costs)."""
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-c", "import companion.service"], check=True)
    return time.perf_counter() - t0


def bench_workload(duration_s: float | None = None):
    """The benchmark's flight: the 'uav' scenario with the mask at 0 deg, seed 0, the IMU cut to
    ``duration_s``: (scenario, sim, tuning)."""
    scenario = dataclasses.replace(build_scenario("uav"), mask_deg=0.0)
    sim = simulate(scenario, 0)
    if duration_s is not None:
        n = int(duration_s * scenario.imu.rate_hz)
        sim.imu = sim.imu[:n]
    return scenario, sim, tuning_for(scenario)


def run_bench(duration_s: float | None = None, kf_gins_dir=None) -> dict:
    """The figures; ``kf_gins_dir``: also write the workload there in KF-GINS's formats
    (:func:`export_kf_gins`, its summary under ``kf_gins_export``)."""
    scenario, sim, tuning = bench_workload(duration_s)
    export = export_kf_gins(sim, tuning, kf_gins_dir) if kf_gins_dir is not None else None
    _run(sim, tuning, True)  # warm-up (imports, caches, compilation on a cold numba cache) ...
    _run(sim, tuning, True, batched=True)  # ... of the batch kernel too (cold: 4.7k samples/CPU-s)
    (rate_imu, cpu_rate_imu), _, _ = _run(sim, tuning, False)
    (rate_gnss, cpu_rate_gnss), _, counters = _run(sim, tuning, True)
    (_, cpu_rate_imu_batch), _, _ = _run(sim, tuning, False, batched=True)
    (_, cpu_rate_gnss_batch), _, _ = _run(sim, tuning, True, batched=True)
    rtk_cpu_s, rtk_epochs, rtk_sats = _rtk_epoch_cpu_s()
    prop_dense_us, prop_blocks_us = propagation_us()
    _, lat_imu, _ = _run(sim, tuning, False, timed=True)
    _, lat_gnss, _ = _run(sim, tuning, True, timed=True)
    rtk = _rtk_load(duration_s)
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
        "imu_samples_per_cpu_s": round(cpu_rate_imu, 1),
        "imu_samples_per_cpu_s_with_gnss": round(cpu_rate_gnss, 1),
        # the replay's form: runs of samples between GNSS messages in one call (process_imu_batch)
        "imu_samples_per_cpu_s_batched": round(cpu_rate_imu_batch, 1),
        "imu_samples_per_cpu_s_with_gnss_batched": round(cpu_rate_gnss_batch, 1),
        "rtk_epoch_cpu_ms": round(rtk_cpu_s * 1e3, 3),
        "rtk_epochs": rtk_epochs,
        "rtk_mean_satellites": round(rtk_sats, 2),
        "startup_import_service_s": round(_startup_s(), 3),
        "latency_us_p50": round(float(np.percentile(lat_gnss, 50)) / 1e3, 2),
        "latency_us_p99": round(float(np.percentile(lat_gnss, 99)) / 1e3, 2),
        "latency_us_max": round(float(lat_gnss.max()) / 1e3, 2),
        "latency_us_p50_imu_only": round(float(np.percentile(lat_imu, 50)) / 1e3, 2),
        "gnss_cost_ratio": round(rate_imu / rate_gnss, 3),
        "propagation_58_states_dense_us": round(prop_dense_us, 2),
        "propagation_58_states_blocks_us": round(prop_blocks_us, 2),
        **rtk,
        "compiled_kernels": _kernels_on(),
        "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS", "default"),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
        **({"kf_gins_export": export} if export is not None else {}),
    }


def _kernels_on() -> bool:
    """Whether the engine ran the compiled kernels (numba) or the pure-Python references."""
    from companion.nav import imu_kernel
    return imu_kernel.compiled() is not None


def _rtk_load(duration_s: float | None) -> dict:
    """RTK inside the filter at IMU rate (the 'rtk-gec' scenario, :func:`rtk_workload`): throughput
    from an untimed pass after a warm-up, latency from a timed one."""
    sim, tuning, cfg = rtk_workload(duration_s)
    lat = tuning.gnss_latency_s
    _run(sim, tuning, True, cfg=cfg, gnss_latency_s=lat)  # warm-up
    (rate, cpu_rate), _, counters = _run(sim, tuning, True, cfg=cfg, gnss_latency_s=lat)
    at_epoch = np.zeros(len(sim.imu), bool)
    _, lat_ns, _ = _run(sim, tuning, True, timed=True, cfg=cfg, gnss_latency_s=lat, epoch_mask=at_epoch)
    lat_epoch = lat_ns[at_epoch] if at_epoch.any() else np.full(1, np.nan)
    sats = [len({o.sat for o in e.observations}) for e in sim.rover_epochs]
    signals = [len({(o.sat, o.signal) for o in e.observations}) for e in sim.rover_epochs]
    return {
        "rtk_imu_samples": len(sim.imu),
        "rtk_mask_deg": cfg.elevation_mask_deg,
        "rtk_mean_rover_satellites": round(float(np.mean(sats)), 2) if sats else 0.0,
        "rtk_mean_rover_signals": round(float(np.mean(signals)), 2) if signals else 0.0,
        "rtk_phase_rows": counters.get("rtk_phase used", 0),
        "rtk_code_rows": counters.get("rtk_code used", 0),
        "rtk_fixed_epochs": counters.get("rtk fixed epochs", 0),
        "imu_samples_per_s_with_rtk": round(rate, 1),
        "imu_samples_per_cpu_s_with_rtk": round(cpu_rate, 1),
        "latency_us_p50_with_rtk": round(float(np.percentile(lat_ns, 50)) / 1e3, 2),
        "latency_us_p99_with_rtk": round(float(np.percentile(lat_ns, 99)) / 1e3, 2),
        "latency_us_max_with_rtk": round(float(lat_ns.max()) / 1e3, 2),
        # the samples that carry a rover epoch (1 in 200: invisible in the p99 of all samples)
        "rtk_epoch_latency_ms_p50": round(float(np.percentile(lat_epoch, 50)) / 1e6, 3),
        "rtk_epoch_latency_ms_p99": round(float(np.percentile(lat_epoch, 99)) / 1e6, 3),
    }


def format_bench(r: dict) -> str:
    return "\n".join([
        f"engine benchmark: {r['imu_samples']} IMU samples at {r['imu_rate_hz']:.0f} Hz, "
        f"{r['mean_rover_satellites']} satellites/epoch",
        f"  IMU only            : {r['imu_samples_per_cpu_s']:>10,.0f} samples/CPU-s ({r['imu_samples_per_s']:,.0f}/s wall;"
        f" p50 {r['latency_us_p50_imu_only']} us); batched {r['imu_samples_per_cpu_s_batched']:,.0f}",
        f"  IMU + GNSS (PR+TDCP): {r['imu_samples_per_cpu_s_with_gnss']:>10,.0f} samples/CPU-s "
        f"({r['imu_samples_per_s_with_gnss']:,.0f}/s wall; p50 {r['latency_us_p50']} us, p99 {r['latency_us_p99']} us, "
        f"max {r['latency_us_max']} us); batched {r['imu_samples_per_cpu_s_with_gnss_batched']:,.0f}",
        f"  IMU + RTK (L1+L2)   : {r['imu_samples_per_cpu_s_with_rtk']:>10,.0f} samples/CPU-s "
        f"({r['imu_samples_per_s_with_rtk']:,.0f}/s wall; p50 {r['latency_us_p50_with_rtk']} us, "
        f"p99 {r['latency_us_p99_with_rtk']} us, max {r['latency_us_max_with_rtk']} us)",
        f"    'rtk-gec' scenario, mask {r['rtk_mask_deg']:g} deg: {r['rtk_mean_rover_satellites']} satellites, "
        f"{r['rtk_mean_rover_signals']} signals/epoch; {r['rtk_phase_rows']} DD phase + {r['rtk_code_rows']} DD code rows, "
        f"{r['rtk_fixed_epochs']} fixed epochs; a sample with an RTK epoch: p50 {r['rtk_epoch_latency_ms_p50']} ms, "
        f"p99 {r['rtk_epoch_latency_ms_p99']} ms",
        f"  RTK epoch (GEONET, L1+L2, {r['rtk_mean_satellites']} satellites): {r['rtk_epoch_cpu_ms']} ms CPU "
        f"over {r['rtk_epochs']} epochs",
        f"  start-up (import companion.service): {r['startup_import_service_s']} s",
        f"  GNSS updates: {r['pseudorange_updates']} pseudoranges, {r['tdcp_updates']} TDCP; "
        f"cost ratio with/without GNSS {r['gnss_cost_ratio']}",
        f"  covariance propagation with 40 identity states (n = 58): dense {r['propagation_58_states_dense_us']} us, "
        f"by blocks {r['propagation_58_states_blocks_us']} us of CPU per IMU sample",
        f"  peak RSS {r['peak_rss_mb']} MB; compiled kernels {'on' if r['compiled_kernels'] else 'off (pure Python)'}, "
        f"OPENBLAS_NUM_THREADS {r['openblas_num_threads']}",
    ])


# ------------------------------------------------------------------------------------------
# the workload in KF-GINS's input formats (github.com/i2Nav-WHU/KF-GINS: dataset/ and
# config/kf-gins.yaml): the same IMU increments and initial state as the engine gets, and the
# DGPS position fixes of the same rover and base epochs, so its loosely coupled result can be
# set beside ours
KF_GINS_IMU_FILE = "imu.txt"
KF_GINS_GNSS_FILE = "gnss.txt"
KF_GINS_CONFIG_FILE = "kf-gins.yaml"
KF_GINS_CORRTIME_H = 1.0        # one correlation time for every bias in KF-GINS (hours)
_DEG_H = math.degrees(1.0) * 3600.0          # rad/s -> deg/h
_SQRT_H = 60.0                               # 1/sqrt(s) -> 1/sqrt(h)
_MGAL = 1e-5                                 # m/s^2 per mGal


def kf_gins_fixes(sim, elevation_mask_deg: float = 10.0):
    """(t_gps, lat rad, lon rad, h m, sigma N E D m) of every rover epoch's DGPS fix (antenna),
    carrier-smoothed code with the base's corrections (:mod:`companion.gnss.postprocess`); sigmas
    from the fix's own covariance."""
    from companion.gnss.ephemeris_store import EphemerisStore
    from companion.gnss.postprocess import ProcessOptions, process
    from companion.nav.earth import C_n_e, ecef_to_geodetic
    opts = ProcessOptions(mode="dgps", elevation_mask_rad=math.radians(elevation_mask_deg))
    sols = process(sim.rover_epochs, EphemerisStore(sim.ephemerides), opts, base_epochs=sim.base_epochs,
                   base=sim.base)
    out = []
    for s in sols:
        if s is None or not np.all(np.isfinite(s.cov_r_e)):
            continue
        lat, lon, h = ecef_to_geodetic(s.r_e)
        C = C_n_e(lat, lon)
        sig = np.sqrt(np.clip(np.diag(C.T @ s.cov_r_e @ C), 0.0, None))
        out.append((float(s.t_gps), lat, lon, h, sig))
    return out


def export_kf_gins(sim, tuning, out_dir, seed: int = 0) -> dict:
    """Write ``imu.txt`` (time of week s, dtheta x y z rad, dv x y z m/s: FRD body increments, time
    = end of the interval), ``gnss.txt`` (time of week s, lat deg, lon deg, h m, sigma N E D m) and
    ``kf-gins.yaml`` (paths, rate, initial state = the engine's in :func:`_run` (truth + the
    errors drawn from P0 with ``seed``), its sigmas, the filter's IMU noise, the lever arm).
    The bias random walks of our filter become KF-GINS's first-order Gauss-Markov biases with
    correlation time :data:`KF_GINS_CORRTIME_H` and the same driving noise (sigma = q sqrt(T/2));
    the simulated IMU has no scale-factor error (1 ppm keeps those states all but fixed).
    Returns counts, span and paths."""
    from pathlib import Path
    from companion.messages import gps_week_tow
    from companion.nav.earth import C_n_e, dcm_to_euler, ecef_to_geodetic
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    week0, _ = gps_week_tow(float(sim.truth.t_gps[0]))

    def tow(t_gps: float) -> float:     # seconds of the first sample's week (may run past 604800)
        return float(t_gps) - week0 * 604800.0

    with open(out / KF_GINS_IMU_FILE, "w") as fh:
        for smp in sim.imu:
            th, dv = smp.dtheta_b, smp.dv_b
            fh.write(f"{tow(smp.t_gps):.6f} {th[0]:.12e} {th[1]:.12e} {th[2]:.12e} "
                     f"{dv[0]:.12e} {dv[1]:.12e} {dv[2]:.12e}\n")
    t_end = sim.imu[-1].t_gps if sim.imu else sim.truth.t_gps[0]
    fixes = [f for f in kf_gins_fixes(sim) if sim.truth.t_gps[0] <= f[0] <= t_end]
    with open(out / KF_GINS_GNSS_FILE, "w") as fh:
        for t, lat, lon, h, sig in fixes:
            fh.write(f"{tow(t):.6f} {math.degrees(lat):.11f} {math.degrees(lon):.11f} {h:.4f} "
                     f"{sig[0]:.4f} {sig[1]:.4f} {sig[2]:.4f}\n")
    # the engine's initial state (the same draw as _run)
    truth, p0, n = sim.truth, tuning.p0, tuning.noise
    d_att, d_pos, d_vel = initial_errors(np.random.default_rng(seed), p0, truth.r_e[0])
    r0 = truth.r_e[0] + d_pos
    lat, lon, h = ecef_to_geodetic(r0)
    Cne = C_n_e(lat, lon)
    v_n = Cne.T @ (truth.v_e[0] + d_vel)
    roll, pitch, yaw = dcm_to_euler(Cne.T @ rotation_from_rotvec(d_att) @ truth.C_b_e[0])
    T_s = KF_GINS_CORRTIME_H * 3600.0
    gb = n.gyro_bias_rw_radps_per_sqrt_s * math.sqrt(T_s / 2.0) * _DEG_H
    ab = n.accel_bias_rw_mps2_per_sqrt_s * math.sqrt(T_s / 2.0) / _MGAL

    def v3(x) -> str:
        return "[ " + ", ".join(f"{float(v)!r}" for v in x) + " ]"

    rate = sim.scenario.imu.rate_hz
    yaml = "\n".join([
        "# KF-GINS configuration: the companion benchmark's workload (python -m sitl bench --kf-gins-format)",
        f'imupath: "{KF_GINS_IMU_FILE}"', f'gnsspath: "{KF_GINS_GNSS_FILE}"', 'outputpath: "."',
        "imudatalen: 7", f"imudatarate: {rate:g}",
        f"starttime: {tow(truth.t_gps[0])!r}", "endtime: -1",
        "# IMU position at the start [deg, deg, m], NED velocity [m/s], roll pitch yaw (ZYX) [deg]",
        f"initpos: {v3([math.degrees(lat), math.degrees(lon), h])}", f"initvel: {v3(v_n)}",
        f"initatt: {v3([math.degrees(roll), math.degrees(pitch), math.degrees(yaw) % 360.0])}",
        "initgyrbias: [ 0, 0, 0 ]    # [deg/h]", "initaccbias: [ 0, 0, 0 ]    # [mGal]",
        "initgyrscale: [ 0, 0, 0 ]   # [ppm]", "initaccscale: [ 0, 0, 0 ]   # [ppm]",
        f"initposstd: {v3([p0['pos_m']] * 3)}", f"initvelstd: {v3([p0['vel_mps']] * 3)}",
        f"initattstd: {v3(np.degrees([p0['tilt_rad'], p0['tilt_rad'], p0['heading_rad']]))}",
        f"initbgstd: {v3([p0['bg_radps'] * _DEG_H] * 3)}    # [deg/h]",
        f"initbastd: {v3([p0['ba_mps2'] / _MGAL] * 3)}    # [mGal]",
        "initsgstd: [ 1.0, 1.0, 1.0 ]    # [ppm]", "initsastd: [ 1.0, 1.0, 1.0 ]    # [ppm]",
        "imunoise:",
        f"  arw: {v3([n.gyro_arw_rad_per_sqrt_s * math.degrees(1.0) * _SQRT_H] * 3)}    # [deg/sqrt(hr)]",
        f"  vrw: {v3([n.accel_vrw_mps_per_sqrt_s * _SQRT_H] * 3)}    # [m/s/sqrt(hr)]",
        f"  gbstd: {v3([gb] * 3)}    # [deg/hr]", f"  abstd: {v3([ab] * 3)}    # [mGal]",
        "  gsstd: [ 1.0, 1.0, 1.0 ]    # [ppm]", "  asstd: [ 1.0, 1.0, 1.0 ]    # [ppm]",
        f"  corrtime: {KF_GINS_CORRTIME_H!r}    # [hr]",
        "# antenna lever arm, forward right down in the IMU frame [m]",
        f"antlever: {v3(sim.lever_arm_b)}", ""])
    (out / KF_GINS_CONFIG_FILE).write_text(yaml)
    return {"dir": str(out), "imu_records": len(sim.imu), "gnss_records": len(fixes),
            "start_tow_s": round(tow(truth.t_gps[0]), 6), "gps_week": week0,
            "files": [KF_GINS_IMU_FILE, KF_GINS_GNSS_FILE, KF_GINS_CONFIG_FILE]}
