"""The seed-000 experiment: five navigation modes on the same simulated data, Monte Carlo.

Modes (all share one simulated flight per run):

* ``ins``        free inertial from the initial state;
* ``gps``        standalone single point positioning, epoch by epoch (no INS);
* ``loose``      INS + SPP position/velocity fixes (loosely coupled);
* ``tight``      INS + standalone pseudoranges + Doppler range rates (conventional tight coupling);
* ``tdcp_dgps``  the proposal: INS + DGPS-corrected pseudoranges + TDCP range rates.

The error of a mode at time t is the 3-D distance between its position (the IMU for the INS
modes, the antenna for ``gps``) and the truth, sampled at 1 Hz and averaged over the runs.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections import Counter
from dataclasses import dataclass

import numpy as np

from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.spp import spp_epoch
from companion.nav.base_check import BASE_POSITION_MAX_SPP_DIFF_M
from companion.nav.engine import EngineConfig, NavEngine
from companion.nav.earth import C_n_e, ecef_to_geodetic, rotation_from_rotvec
from companion.nav.chi2 import chi2_ppf
from companion.nav.filter import ProcessNoise
from .simulate import feed_engine

MODES = ("ins", "gps", "loose", "tight", "tdcp_dgps")
#: after a rover outage, the first epoch is fused within this (one 1-Hz epoch interval plus latency)
OUTAGE_FIRST_EPOCH_S = 1.5
# extra modes (not in the paper's table): the proposal with between-satellite single differences
# (seed 004: no receiver clock states needed) instead of undifferenced measurements
EXTRA_MODES = ("tdcp_dgps_sd",)

# Table 4 of seed 000, 3-D position error (m)
PAPER_TABLE4 = {
    "t_s": [0, 10, 20, 30, 40, 50, 100, 200, 300, 400, 500],
    "ins": [0, 2.05, 7.155, 15.79, 21.72, 43.03, 61.37, 659, 1540, 2690, 3718],
    "gps": [115, 12, 193, 187, 50, 3, 187, 181, 56, 15, 20],
    "loose": [0, 10, 113, 47, 99, 37, 241, 9, 2, 34, 30],
    "tight": [0, 21, 20.2, 17.9, 25.9, 17.8, 41.4, 85, 44.9, 21.1, 12.3],
    "tdcp_dgps": [0, 1.80, 7.74, 1.04, 5.96, 9.55, 6.88, 8.13, 4.26, 2.12, 8.03],
}
PAPER_MEAN = {"ins": None, "gps": 99.52, "loose": 65.66, "tight": 34.52, "tdcp_dgps": 6.568}


@dataclass
class FilterTuning:
    """Filter noise model and initial uncertainty for one scenario (derived from its IMU model)."""

    noise: ProcessNoise
    p0: dict
    sigma_doppler_mps: float = 0.1
    sigma_phase_m: float = 0.005
    sigma_tdcp_floor_mps: float = 0.01
    gnss_latency_s: float = 0.0
    # standalone pseudoranges: error floor the per-satellite model does not know about (e.g. SA)
    sigma_pseudorange_standalone_floor_m: float = 0.0
    # the base position check's reach (companion.nav.base_check): SA moves the base's single-point
    # solution by hundreds of metres (paper scenario, seeds 0-5: 137-443 m at the median, 549 m at
    # most); sitl.tuning gives it twenty times the standalone range floor (1158 m there)
    base_max_spp_diff_m: float = BASE_POSITION_MAX_SPP_DIFF_M
    klobuchar: tuple | None = None       # broadcast (alpha, beta) for the standalone modes
    pseudorange_correlation_time_s: float = 0.0
    zupt_enabled: bool = False
    sigma_phase_elevation_scaling: bool = False


def _engine_has_systems() -> bool:
    """EngineConfig grows ``systems`` with multi-GNSS fusion; older engines fuse GPS only."""
    return "systems" in {f.name for f in dataclasses.fields(EngineConfig)}


def mode_config(mode: str, tuning: FilterTuning, lever_arm_b, systems: str = "G") -> EngineConfig:
    """The engine configuration of ``mode``; ``systems`` (the scenario's, e.g. 'GEC') is passed on
    only when it is not GPS alone and the engine knows the field (GPS-only runs stay as they were)."""
    common = dict(noise=tuning.noise, lever_arm_b_m=tuple(lever_arm_b), sigma_doppler_mps=tuning.sigma_doppler_mps,
                  sigma_phase_m=tuning.sigma_phase_m, sigma_tdcp_floor_mps=tuning.sigma_tdcp_floor_mps,
                  elevation_mask_deg=5.0, klobuchar=tuning.klobuchar,
                  pseudorange_correlation_time_s=tuning.pseudorange_correlation_time_s,
                  zupt_enabled=tuning.zupt_enabled,
                  sigma_phase_elevation_scaling=tuning.sigma_phase_elevation_scaling,
                  base_max_spp_diff_m=tuning.base_max_spp_diff_m)
    if systems != "G" and _engine_has_systems():
        common["systems"] = systems
    standalone = dict(use_dgps=False, sigma_pseudorange_floor_m=tuning.sigma_pseudorange_standalone_floor_m)
    if mode == "loose":
        return EngineConfig(use_loose=True, use_tdcp=False, **standalone, **common)
    if mode == "tight":
        return EngineConfig(use_pseudorange=True, use_doppler=True, use_tdcp=False, **standalone, **common)
    if mode == "tdcp_dgps":
        return EngineConfig(use_pseudorange=True, use_dgps=True, use_doppler=False, use_tdcp=True, **common)
    if mode == "tdcp_dgps_sd":
        return EngineConfig(use_pseudorange=True, use_dgps=True, use_doppler=False, use_tdcp=True,
                            measurement_form="single_difference", **common)
    if mode == "ins":
        return EngineConfig(use_pseudorange=False, use_dgps=False, use_tdcp=False, **common)
    raise ValueError(f"unknown mode {mode!r}")


def initial_errors(rng: np.random.Generator, p0: dict, r_e):
    """Initial attitude/position/velocity errors drawn from the filter's own P0 (honest NEES).
    Attitude: tilt and heading sigmas in local NED, returned as an ECEF rotation vector."""
    lat, lon, _ = ecef_to_geodetic(r_e)
    att_n = rng.normal(0.0, 1.0, 3) * np.array([p0["tilt_rad"], p0["tilt_rad"], p0["heading_rad"]])
    return C_n_e(lat, lon) @ att_n, rng.normal(0.0, p0["pos_m"], 3), rng.normal(0.0, p0["vel_mps"], 3)


def run_ins_mode(mode: str, sim, tuning: FilterTuning, seed: int, record_every_s: float = 1.0,
                 on_epoch=None, keep_engine: bool = False):
    """Run one INS mode over a simulated flight.  Returns dict with 't_s', 'err_3d_m' (1 Hz) and
    'nees' samples (error-state NEES of attitude/position/velocity at the same instants)."""
    truth = sim.truth
    cfg = mode_config(mode, tuning, sim.lever_arm_b, getattr(sim.scenario, "systems", "G"))
    eng = NavEngine(cfg)
    eng.on_epoch = on_epoch
    for eph in sim.ephemerides:
        eng.process(eph)
    eng.process(sim.base)
    rng = np.random.default_rng(10_000 + seed)
    d_att, d_pos, d_vel = initial_errors(rng, tuning.p0, truth.r_e[0])
    eng.initialize(truth.t_gps[0], truth.r_e[0] + d_pos, truth.v_e[0] + d_vel,
                   rotation_from_rotvec(d_att) @ truth.C_b_e[0], tuning.p0)
    use_gnss = mode != "ins"
    lat = tuning.gnss_latency_s
    t0 = truth.t_gps[0]
    step = max(1, int(round(record_every_s / (truth.t_gps[1] - truth.t_gps[0]))))
    lat0, lon0, _ = ecef_to_geodetic(truth.r_e[0])
    up_e = -C_n_e(lat0, lon0)[:, 2]   # local vertical (the flights span a few km: one is enough)
    d0 = eng.r_e - truth.r_e[0]
    ts, errs, nees = [0.0], [float(np.linalg.norm(d0))], []
    errs_h = [float(np.linalg.norm(d0 - up_e * (d0 @ up_e)))]
    for k, s in feed_engine(eng, sim, lat, use_gnss=use_gnss):
        if k % step == 0:
            d = eng.r_e - truth.r_e[k]
            ts.append(s.t_gps - t0)
            errs.append(float(np.linalg.norm(d)))
            errs_h.append(float(np.linalg.norm(d - up_e * (d @ up_e))))
            nees.append(_nees(eng, truth, k))
    out = {"t_s": np.array(ts), "err_3d_m": np.array(errs), "err_h_m": np.array(errs_h),
           "nees": np.array(nees), "counters": dict(eng.counters)}
    if keep_engine:
        out["engine"] = eng
    return out


def _nees(eng: NavEngine, truth, k: int) -> float:
    """NEES of the 9 navigation error states (attitude, position, velocity) at truth sample k."""
    L = eng.layout
    # correction-convention errors: truth = estimate + error
    dC = truth.C_b_e[k] @ eng.C_b_e.T
    err = np.concatenate([0.5 * np.array([dC[2, 1] - dC[1, 2], dC[0, 2] - dC[2, 0], dC[1, 0] - dC[0, 1]]),
                          truth.r_e[k] - eng.r_e, truth.v_e[k] - eng.v_e])
    idx = np.r_[L.att, L.pos, L.vel]
    P = eng.kf.P[np.ix_(idx, idx)]
    return float(err @ np.linalg.solve(P, err))


def run_gps_mode(sim, klobuchar=None):
    """Standalone SPP at every rover epoch (the scenario's systems); error of the antenna position
    against truth."""
    store = EphemerisStore(sim.ephemerides)
    systems = getattr(sim.scenario, "systems", "G")
    truth = sim.truth
    t0 = truth.t_gps[0]
    ts, errs, errs_h = [], [], []
    r_prev = None
    lat0, lon0, _ = ecef_to_geodetic(truth.r_e[0])
    up_e = -C_n_e(lat0, lon0)[:, 2]
    for ep in sim.rover_epochs:
        sol = spp_epoch(ep, store, klobuchar=klobuchar, r_init_e=r_prev, systems=systems)
        if sol is None:
            continue
        r_prev = sol.r_e
        r_ant_true = _truth_antenna_at(sim, ep.t_gps)
        d = sol.r_e - r_ant_true
        ts.append(ep.t_gps - t0)
        errs.append(float(np.linalg.norm(d)))
        errs_h.append(float(np.linalg.norm(d - up_e * (d @ up_e))))
    return {"t_s": np.array(ts), "err_3d_m": np.array(errs), "err_h_m": np.array(errs_h)}


def _truth_antenna_at(sim, t_gps: float) -> np.ndarray:
    truth = sim.truth
    k = int(np.searchsorted(truth.t_gps, t_gps))
    k = min(max(k, 1), len(truth.t_gps) - 1)
    a = (t_gps - truth.t_gps[k - 1]) / (truth.t_gps[k] - truth.t_gps[k - 1])
    r = truth.r_e[k - 1] * (1 - a) + truth.r_e[k] * a
    return r + truth.C_b_e[k] @ np.asarray(sim.lever_arm_b, float)


def summarize(curves: list[dict], duration_s: float) -> dict:
    """Average the runs' 1 Hz error curves; statistics over the flight."""
    grid = np.arange(0.0, math.floor(duration_s) + 1e-9, 1.0)
    stack = []
    for c in curves:
        # nearest sample within 1 s; gaps (outages, no solution) stay NaN instead of being bridged
        j = np.clip(np.searchsorted(c["t_s"], grid), 1, len(c["t_s"]) - 1)
        j = np.where(np.abs(c["t_s"][j - 1] - grid) < np.abs(c["t_s"][j] - grid), j - 1, j)
        v = c["err_3d_m"][j].astype(float)
        v[np.abs(c["t_s"][j] - grid) > 1.0] = np.nan
        stack.append(v)
    arr = np.array(stack)
    counts = np.sum(np.isfinite(arr), axis=0)
    mean_curve = np.where(counts > 0, np.nansum(arr, axis=0) / np.maximum(counts, 1), np.nan)
    at = {str(int(t)): round(float(mean_curve[int(t)]), 3) for t in PAPER_TABLE4["t_s"] if t < len(grid)}
    valid = np.isfinite(mean_curve)
    all_h = np.concatenate([c["err_h_m"] for c in curves])
    return {"mean_3d_m": float(np.mean(mean_curve[valid])),
            "rms_3d_m": float(np.sqrt(np.mean(np.concatenate([s[np.isfinite(s)] for s in stack]) ** 2))),
            "rms_h_m": float(np.sqrt(np.mean(all_h ** 2))),
            "max_3d_m": float(np.nanmax(mean_curve)),
            "at_s": at, "curve_t_s": grid.tolist(), "curve_3d_m": [round(float(x), 4) for x in mean_curve]}


def _one_run(scenario_name: str, seed: int, modes) -> dict:
    """Simulate one flight and run every mode on it (a unit of work for a worker process)."""
    from .scenario import build_scenario
    from .simulate import simulate
    from .tuning import tuning_for

    scenario = build_scenario(scenario_name)
    tuning = tuning_for(scenario)
    sim = simulate(scenario, seed)
    out = {"duration_s": float(sim.truth.t_gps[-1] - sim.truth.t_gps[0]),
           "outages_s": [(a - sim.truth.t_gps[0], b - sim.truth.t_gps[0]) for a, b in scenario.rover_outages],
           "curves": {}, "counters": {}, "sats_per_epoch": sats_per_epoch(sim.rover_epochs)}
    for m in modes:
        res = run_gps_mode(sim, tuning.klobuchar) if m == "gps" else run_ins_mode(m, sim, tuning, seed)
        out["counters"][m] = res.pop("counters", {})
        out["curves"][m] = res
    return out


def sats_per_epoch(epochs) -> dict[str, float]:
    """Mean number of satellites observed per epoch, by system (RINEX letter)."""
    n = Counter()
    for ep in epochs:
        n.update(s[0] for s in {o.sat for o in ep.observations})
    return {s: n[s] / max(len(epochs), 1) for s in sorted(n)}


def run_experiment(scenario_name: str, runs: int, seed: int, modes=MODES, progress=None, jobs: int = 0) -> dict:
    """Monte Carlo over ``runs`` simulated flights (seeds seed..seed+runs-1), in parallel worker
    processes.  Each run is deterministic in its seed, so the result does not depend on ``jobs``."""
    from .montecarlo import run_all
    from .scenario import build_scenario

    t_start = time.perf_counter()
    results = run_all(_one_run, [(scenario_name, seed + r, modes) for r in range(runs)], jobs, progress)
    duration = results[0]["duration_s"]
    out = {"scenario": scenario_name, "runs": runs, "seed": seed, "modes": {}}
    for m in modes:
        out["modes"][m] = summarize([r["curves"][m] for r in results], duration)
    # run-averaged NEES of the 9 navigation states per INS mode, and its two-sided 95 % band
    # (runs x NEES ~ chi-square with 9 runs dof when the filter is consistent)
    lo, hi = chi2_ppf(0.025, 9 * runs) / runs, chi2_ppf(0.975, 9 * runs) / runs
    for m in modes:
        if m in ("gps",):
            continue
        avg = np.mean(np.array([r["curves"][m]["nees"] for r in results]), axis=0)
        out["modes"][m]["avg_nees_9dof"] = {
            "mean": float(np.mean(avg)), "median": float(np.median(avg)), "band_95": [lo, hi],
            "fraction_inside": float(np.mean((avg >= lo) & (avg <= hi)))}
    if "tdcp_dgps" in modes:
        out["tdcp_dgps_avg_nees_9dof"] = out["modes"]["tdcp_dgps"]["avg_nees_9dof"]
        outages = results[0]["outages_s"]
        if outages:
            a, b = outages[0]
            # outside: before it, and after the first epoch that follows it has been fused (the
            # receiver's epoch at its end is fused up to one epoch interval plus the latency later;
            # the seconds before that are still the outage's drift)
            b_fused = b + OUTAGE_FIRST_EPOCH_S
            outside = np.concatenate([c["err_h_m"][(c["t_s"] < a) | (c["t_s"] > b_fused)]
                                      for c in (r["curves"]["tdcp_dgps"] for r in results)])
            out["modes"]["tdcp_dgps"]["rms_h_m_outside_outage"] = float(np.sqrt(np.mean(outside ** 2)))
            curve = np.array(out["modes"]["tdcp_dgps"]["curve_3d_m"])
            ia, ib = int(math.floor(a)), min(int(math.ceil(b)), len(curve) - 1)
            out["outage"] = {"start_s": a, "end_s": b, "duration_s": b - a,
                             "err_start_m": float(curve[ia]), "err_end_m": float(curve[ib]),
                             "err_max_m": float(np.max(curve[ia:ib + 1]))}
    out["counters"] = {m: results[0]["counters"][m] for m in modes}
    out["systems"] = getattr(build_scenario(scenario_name), "systems", "G")
    per = [r["sats_per_epoch"] for r in results]
    out["sats_per_epoch"] = {s: float(np.mean([p.get(s, 0.0) for p in per])) for s in sorted({k for p in per for k in p})}
    out["elapsed_s"] = time.perf_counter() - t_start
    return out


def format_table(result: dict) -> str:
    modes = [m for m in MODES + EXTRA_MODES if m in result["modes"]]
    paper = result["scenario"] == "paper"
    head = f"{'t [s]':>6} | " + " | ".join(f"{m:>17}" for m in modes)
    lines = [f"3-D position error (m), mean of {result['runs']} run(s), scenario '{result['scenario']}'"
             + ("  [ours (paper Table 4)]" if paper else ""), head, "-" * len(head)]
    for i, t in enumerate(PAPER_TABLE4["t_s"]):
        cells = []
        for m in modes:
            ours = result["modes"][m]["at_s"].get(str(t))
            if ours is None:
                cells.append(f"{'-':>17}")
                continue
            txt = f"{ours:8.2f}"
            if paper and m in PAPER_TABLE4:
                txt += f" ({PAPER_TABLE4[m][i]:6g})"
            cells.append(f"{txt:>17}")
        lines.append(f"{t:>6} | " + " | ".join(cells))
    lines.append("-" * len(head))
    cells = []
    for m in modes:
        txt = f"{result['modes'][m]['mean_3d_m']:8.2f}"
        if paper and m in PAPER_MEAN:
            pm = PAPER_MEAN[m]
            txt += f" ({pm:6g})" if pm is not None else " (     -)"
        cells.append(f"{txt:>17}")
    lines.append(f"{'mean':>6} | " + " | ".join(cells))
    rms = " | ".join(f"{m} {result['modes'][m]['rms_h_m']:.3f} / {result['modes'][m]['rms_3d_m']:.3f}" for m in modes)
    lines.append(f"RMS horizontal / 3-D (m): {rms}")
    if "sats_per_epoch" in result:
        per = ", ".join(f"{s} {n:.1f}" for s, n in result["sats_per_epoch"].items())
        lines.append(f"rover satellites per epoch (systems '{result.get('systems', 'G')}'): {per}")
    return "\n".join(lines)


def plot(result: dict, path: str) -> None:
    from companion.extras import pyplot
    plt = pyplot("python -m sitl paper --plot")

    fig, ax = plt.subplots(figsize=(9, 5))
    for m in MODES + EXTRA_MODES:
        if m in result["modes"]:
            s = result["modes"][m]
            ax.semilogy(s["curve_t_s"], np.maximum(s["curve_3d_m"], 1e-3), label=f"{m} (mean {s['mean_3d_m']:.2f} m)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("3-D position error [m]")
    ax.set_title(f"scenario '{result['scenario']}', {result['runs']} run(s)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
