"""Seeds 002 and 003: constraint and attitude aiding, each compared with and without on the same
simulated data (Monte Carlo over seeds, worker processes as in :mod:`sitl.paper`).

``run_nhc``  (scenario 'nhc', seed 002 Table 1): loosely coupled INS/GNSS (standalone L1 SPP
position + Doppler velocity per rover epoch) *without* vs *with* the non-holonomic constraint.
ZUPT/ZARU at the stops and the in-motion heading alignment from the GNSS course over ground
(companion.nav.course_alignment) are on in **both** modes: the comparison isolates the NHC.  The
car rests 15 s at the start with a compass-class heading (tuning: 0.05 rad), unobservable at rest
to both filters; the paper reports a navigation run, so the headline RMSE is taken over the
**navigation phase**: from the heading alignment epoch (the later of the two modes, in each run)
to the end, outages included; the whole-run figures are reported beside it.  Errors sampled at
1 Hz (the IMU sample nearest each second), pooled over all runs.  Position: IMU position error in
the local ENU frame of the start point; attitude: differences of the ZYX Euler angles (roll,
pitch, heading) of truth and estimate in the local NED frame.  3-D = root sum of squares of the
component RMSEs.

``run_attitude`` (scenario 'attitude', seed 003 Table 2): PV (PPK position + velocity fixes at
1 Hz) vs PVA (plus three-antenna GNSS attitude at 1 Hz).  RMS and STD of the N/E/U position
(cm), velocity (cm/s) and yaw/pitch/roll (deg) errors over the whole flight, pooled over runs.

Filter tuning: :func:`sitl.tuning.tuning_for` (IMU densities, P0 from the scenario's sensor
models); the initial attitude uncertainty is the scenario's alignment figure where it gives one
(seed 003 Table 1: 0.01/0.01/0.03 deg); initial errors are drawn from P0 with the same seed in both
modes, so every comparison is paired.  Nothing is tuned against the truth.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from companion.nav.earth import C_n_e, ecef_to_geodetic, rotation_from_rotvec
from companion.nav.engine import EngineConfig, NavEngine

# seed 002 Table 1 (RMSE, without -> with NHC)
PAPER_TABLE1 = {
    "without": {"e_m": 1.08, "n_m": 0.76, "u_m": 1.35, "pos_3d_m": 1.89,
                "roll_deg": 0.16, "pitch_deg": 0.47, "heading_deg": 1.31, "att_3d_deg": 1.34},
    "with": {"e_m": 1.02, "n_m": 0.28, "u_m": 0.49, "pos_3d_m": 1.17,
             "roll_deg": 0.06, "pitch_deg": 0.43, "heading_deg": 0.27, "att_3d_deg": 0.51},
    "improvement_position_pct": 38.0, "improvement_attitude_pct": 62.0,
}
# seed 003 Table 2 (RMS, PV -> PVA)
PAPER_TABLE2 = {
    "PV": {"n_cm": 5.93, "e_cm": 12.98, "u_cm": 8.69, "vn_cmps": 3.2, "ve_cmps": 4.37, "vu_cmps": 3.78,
           "yaw_deg": 0.1883, "pitch_deg": 0.0127, "roll_deg": 0.0461},
    "PVA": {"n_cm": 5.39, "e_cm": 11.59, "u_cm": 8.04, "vn_cmps": 2.08, "ve_cmps": 3.28, "vu_cmps": 2.81,
            "yaw_deg": 0.1625, "pitch_deg": 0.0071, "roll_deg": 0.0238},
    "improvement_roll_pct": 48.37, "improvement_pitch_pct": 44.09,
}
NHC_MODES = ("without", "with")
ATT_MODES = ("PV", "PVA")


# ------------------------------------------------------------------------------------------
# configuration (from the scenario's own sensor models)
# ------------------------------------------------------------------------------------------
def _p0(scenario, tuning) -> dict:
    p0 = dict(tuning.p0)
    if scenario.initial_attitude_sigma_rad is not None:
        p0["tilt_rad"], p0["heading_rad"] = scenario.initial_attitude_sigma_rad
    return p0


def nhc_config(scenario, tuning, nhc: bool) -> EngineConfig:
    """Loose coupling as sitl.paper's 'loose' mode, ZUPT on, NHC on or off.  The stillness
    thresholds are twice the IMU's own per-sample white noise (never below the engine defaults),
    so a still vehicle is recognised whatever the IMU grade."""
    from .paper import mode_config
    imu = scenario.imu
    per_sample = math.sqrt(imu.rate_hz)
    cfg = mode_config("loose", tuning, scenario.lever_arm_b)
    return dataclasses.replace(
        cfg, elevation_mask_deg=scenario.mask_deg, zupt_enabled=True,
        zupt_gyro_std_radps=max(cfg.zupt_gyro_std_radps, 2.0 * imu.gyro_arw_radps_per_sqrthz * per_sample),
        zupt_accel_std_mps2=max(cfg.zupt_accel_std_mps2, 2.0 * imu.accel_vrw_mps2_per_sqrthz * per_sample),
        nhc_enabled=nhc, course_alignment_enabled=True)


def attitude_config(scenario, tuning) -> EngineConfig:
    """Position/velocity (and attitude) fixes only: no raw GNSS measurements, no ZUPT (airborne)."""
    return EngineConfig(noise=tuning.noise, lever_arm_b_m=tuple(scenario.lever_arm_b),
                        use_pseudorange=False, use_dgps=False, use_tdcp=False, use_doppler=False,
                        use_loose=False, zupt_enabled=False, nhc_enabled=False)


# ------------------------------------------------------------------------------------------
# one engine run
# ------------------------------------------------------------------------------------------
def _euler(Cbn: np.ndarray) -> np.ndarray:
    return np.array([math.atan2(Cbn[2, 1], Cbn[2, 2]), -math.asin(max(-1.0, min(1.0, Cbn[2, 0]))),
                     math.atan2(Cbn[1, 0], Cbn[0, 0])])


def _wrap(a):
    return (np.asarray(a) + math.pi) % (2.0 * math.pi) - math.pi


def run_engine(sim, cfg: EngineConfig, p0: dict, seed: int, *, epochs=True, fixes=False, attitudes=False,
               latency_s: float = 0.0, keep_engine: bool = False, extra_messages=()) -> dict:
    """Run the engine over a simulated trajectory; at 1 Hz record the IMU position error (local ENU
    of the start, m), velocity error (ENU, m/s) and Euler-angle errors (roll, pitch, heading; rad)."""
    from .paper import initial_errors

    truth = sim.truth
    eng = NavEngine(cfg)
    for eph in sim.ephemerides:
        eng.process(eph)
    rng = np.random.default_rng(10_000 + seed)
    d_att, d_pos, d_vel = initial_errors(rng, p0, truth.r_e[0])
    eng.initialize(truth.t_gps[0], truth.r_e[0] + d_pos, truth.v_e[0] + d_vel,
                   rotation_from_rotvec(d_att) @ truth.C_b_e[0], p0)
    msgs = []
    if epochs:
        msgs += list(sim.rover_epochs)
    if fixes:
        msgs += list(sim.gnss_fixes)
    if attitudes:
        msgs += list(sim.attitude_measurements)
    msgs += list(extra_messages)
    msgs.sort(key=lambda m: m.t_gps)
    lat0, lon0, _ = ecef_to_geodetic(truth.r_e[0])
    C_e_enu = C_n_e(lat0, lon0).T[[1, 0, 2]] * np.array([[1.0], [1.0], [-1.0]])   # ECEF -> ENU
    step = max(1, int(round(1.0 / (truth.t_gps[1] - truth.t_gps[0]))))
    t0 = truth.t_gps[0]
    ts, dpos, dvel, datt = [], [], [], []
    i = 0
    for k, s in enumerate(sim.imu, start=1):
        while i < len(msgs) and msgs[i].t_gps + latency_s <= s.t_gps:
            eng.process(msgs[i])
            i += 1
        eng.process_imu(s)
        if k % step == 0:
            lat, lon, _ = ecef_to_geodetic(truth.r_e[k])
            C_e_n = C_n_e(lat, lon).T
            ts.append(s.t_gps - t0)
            dpos.append(C_e_enu @ (eng.r_e - truth.r_e[k]))
            dvel.append(C_e_enu @ (eng.v_e - truth.v_e[k]))
            datt.append(_wrap(_euler(C_e_n @ eng.C_b_e) - _euler(C_e_n @ truth.C_b_e[k])))
    out = {"t_s": np.array(ts), "pos_enu_m": np.array(dpos), "vel_enu_mps": np.array(dvel),
           "att_rph_rad": np.array(datt), "counters": dict(eng.counters),
           "course_alignment_t_s": eng.course_alignment_t_gps - t0}
    if keep_engine:
        out["engine"] = eng
    return out


def _pool(fn, args_list, jobs: int):
    from .montecarlo import run_all
    return run_all(fn, args_list, jobs)


def _rms(x) -> float:
    x = np.asarray(x, float)
    return float(np.sqrt(np.mean(x * x)))


def _pct(before: float, after: float) -> float:
    return 100.0 * (before - after) / before if before > 0 else float("nan")


# ------------------------------------------------------------------------------------------
# seed 002: NHC
# ------------------------------------------------------------------------------------------
def _nhc_one(seed: int, scenario_name: str = "nhc") -> dict:
    from .scenario import build_scenario
    from .simulate import simulate
    from .tuning import tuning_for

    scn = build_scenario(scenario_name)
    tuning = tuning_for(scn)
    sim = simulate(scn, seed)
    p0 = _p0(scn, tuning)
    out = {}
    for mode in NHC_MODES:
        r = run_engine(sim, nhc_config(scn, tuning, mode == "with"), p0, seed, epochs=True,
                       latency_s=tuning.gnss_latency_s)
        out[mode] = r
    out["outages_s"] = [(a - scn.t0_gps, b - scn.t0_gps) for a, b in scn.rover_outages]
    return out


def _nhc_stats(curves: list[dict], outages) -> dict:
    pos = np.concatenate([c["pos_enu_m"] for c in curves])
    att = np.degrees(np.concatenate([c["att_rph_rad"] for c in curves]))
    e, n, u = (_rms(pos[:, j]) for j in range(3))
    r, p, h = (_rms(att[:, j]) for j in range(3))
    st = {"e_m": e, "n_m": n, "u_m": u, "pos_3d_m": math.sqrt(e * e + n * n + u * u),
          "roll_deg": r, "pitch_deg": p, "heading_deg": h, "att_3d_deg": math.sqrt(r * r + p * p + h * h)}
    t = curves[0]["t_s"]
    in_out = np.zeros(len(t), bool)
    for a, b in outages:
        in_out |= (t >= a) & (t < b)
    pos3 = np.concatenate([np.linalg.norm(c["pos_enu_m"], axis=1) for c in curves])
    mask = np.tile(in_out, len(curves))
    st["pos_3d_in_outages_m"] = _rms(pos3[mask])
    st["pos_3d_outside_outages_m"] = _rms(pos3[~mask])
    ends = []
    for a, b in outages:
        j = int(np.searchsorted(t, b)) - 1
        ends.append(float(np.mean([np.linalg.norm(c["pos_enu_m"][j]) for c in curves])))
    st["pos_3d_at_outage_end_m"] = ends
    return st


def _from(c: dict, t_start_s: float) -> dict:
    k = c["t_s"] >= t_start_s
    return {"t_s": c["t_s"][k], "pos_enu_m": c["pos_enu_m"][k], "att_rph_rad": c["att_rph_rad"][k]}


def run_nhc(runs: int = 4, seed: int = 1, jobs: int = 0, scenario_name: str = "nhc") -> dict:
    """Seed 002 Table 1 on scenario 'nhc': loose INS/GNSS without vs with NHC (ZUPT and in-motion
    course alignment in both).  Headline: the navigation phase, from the later of the two modes'
    heading alignment epochs in each run; the whole run (with the unaligned stationary start) beside it."""
    t_start = time.perf_counter()
    results = _pool(_nhc_one, [(seed + r, scenario_name) for r in range(runs)], jobs)
    outages = results[0]["outages_s"]
    keys = ("e_m", "n_m", "u_m", "pos_3d_m", "roll_deg", "pitch_deg", "heading_deg", "att_3d_deg")
    t_aligned = [float(max(r[m]["course_alignment_t_s"] for m in NHC_MODES)) for r in results]
    if not all(math.isfinite(t) for t in t_aligned):
        raise RuntimeError(f"a run never aligned its heading from the course (alignment epochs {t_aligned} s)")
    nav = {m: _nhc_stats([_from(r[m], t) for r, t in zip(results, t_aligned)], outages) for m in NHC_MODES}
    whole = {m: _nhc_stats([r[m] for r in results], outages) for m in NHC_MODES}
    improvement = {k: _pct(nav["without"][k], nav["with"][k]) for k in keys}
    improvement_whole = {k: _pct(whole["without"][k], whole["with"][k]) for k in keys}
    from .scenario import build_scenario
    t_move = next(b for name, a, b in build_scenario(scenario_name).trajectory.events if name == "rest")
    return {"scenario": scenario_name, "runs": runs, "seed": seed,
            "interval": "navigation phase: from the in-motion heading alignment (the later of the two modes) "
                        "to the end, outages included (1 Hz samples, pooled over runs)",
            "course_alignment_t_s": t_aligned, "first_motion_t_s": float(t_move),
            "outages_s": outages, "modes": nav, "improvement_pct": improvement,
            "improvement_position_pct": improvement["pos_3d_m"],
            "improvement_attitude_pct": improvement["att_3d_deg"],
            "paper": PAPER_TABLE1,
            "whole_run": {"modes": whole, "improvement_pct": improvement_whole,
                          "note": "includes the stationary start, where heading is the compass-class "
                                  "initial value in both modes (unobservable at rest)"},
            "counters": {m: results[0][m]["counters"] for m in NHC_MODES},
            "elapsed_s": time.perf_counter() - t_start}


def format_nhc(res: dict) -> str:
    rows = [("E [m]", "e_m"), ("N [m]", "n_m"), ("U [m]", "u_m"), ("3-D position [m]", "pos_3d_m"),
            ("roll [deg]", "roll_deg"), ("pitch [deg]", "pitch_deg"), ("heading [deg]", "heading_deg"),
            ("3-D attitude [deg]", "att_3d_deg")]
    P = res["paper"]
    ta = res["course_alignment_t_s"]
    lines = [f"Seed 002 Table 1: RMSE from the in-motion heading alignment to the end (outages included), "
             f"loosely coupled INS/GNSS without -> with NHC, {res['runs']} run(s), scenario '{res['scenario']}'",
             "heading aligned from the course over ground at t = " + ", ".join(f"{t:.0f}" for t in ta)
             + f" s (first motion at {res['first_motion_t_s']:.0f} s)",
             f"{'':20s} | {'without':>8} {'with':>8} {'impr.':>7} | {'paper without':>13} {'with':>6} {'impr.':>7}",
             "-" * 84]
    for label, k in rows:
        w, n = res["modes"]["without"][k], res["modes"]["with"][k]
        pw, pn = P["without"][k], P["with"][k]
        lines.append(f"{label:20s} | {w:8.3f} {n:8.3f} {res['improvement_pct'][k]:6.1f}% | "
                     f"{pw:13.2f} {pn:6.2f} {_pct(pw, pn):6.1f}%")
    lines.append("-" * 84)
    for m in NHC_MODES:
        s = res["modes"][m]
        lines.append(f"{m:>7} NHC: 3-D position RMS {s['pos_3d_outside_outages_m']:.2f} m outside the outages, "
                     f"{s['pos_3d_in_outages_m']:.2f} m inside; error at the outage ends "
                     + ", ".join(f"{x:.2f}" for x in s["pos_3d_at_outage_end_m"]) + " m")
    c = res["counters"]["with"]
    lines.append(f"first run, with NHC: {c.get('nhc used', 0)} NHC rows used, "
                 f"{c.get('nhc rejected: innovation gate', 0)} rejected, {c.get('nhc suspended', 0)} suspensions; "
                 f"{c.get('zupt used', 0)} ZUPT rows; course alignment {c.get('course alignment: heading fused', 0)} "
                 f"fused, {c.get('course alignment: heading reset', 0)} reset")
    wr = res["whole_run"]
    lines.append(f"whole run (incl. the {res['first_motion_t_s']:.0f}-s stationary start with the compass-class "
                 f"heading, the same in both modes): "
                 f"3-D position {wr['modes']['without']['pos_3d_m']:.2f} -> {wr['modes']['with']['pos_3d_m']:.2f} m "
                 f"({wr['improvement_pct']['pos_3d_m']:.1f} %), 3-D attitude {wr['modes']['without']['att_3d_deg']:.3f} -> "
                 f"{wr['modes']['with']['att_3d_deg']:.3f} deg ({wr['improvement_pct']['att_3d_deg']:.1f} %)")
    lines.append(f"improvement: 3-D position {res['improvement_position_pct']:.1f} % (paper 38 %), "
                 f"3-D attitude {res['improvement_attitude_pct']:.1f} % (paper 62 %)")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------
# seed 003: GNSS attitude
# ------------------------------------------------------------------------------------------
def _attitude_one(seed: int, scenario_name: str = "attitude") -> dict:
    from .scenario import build_scenario
    from .simulate import simulate
    from .tuning import tuning_for

    scn = build_scenario(scenario_name)
    tuning = tuning_for(scn)
    sim = simulate(scn, seed)
    p0 = _p0(scn, tuning)
    cfg = attitude_config(scn, tuning)
    out = {}
    for mode in ATT_MODES:
        out[mode] = run_engine(sim, cfg, p0, seed, epochs=False, fixes=True, attitudes=(mode == "PVA"),
                               latency_s=tuning.gnss_latency_s)
    return out


def _att_stats(curves: list[dict]) -> dict:
    pos = 100.0 * np.concatenate([c["pos_enu_m"] for c in curves])
    vel = 100.0 * np.concatenate([c["vel_enu_mps"] for c in curves])
    att = np.degrees(np.concatenate([c["att_rph_rad"] for c in curves]))
    cols = {"n_cm": pos[:, 1], "e_cm": pos[:, 0], "u_cm": pos[:, 2],
            "vn_cmps": vel[:, 1], "ve_cmps": vel[:, 0], "vu_cmps": vel[:, 2],
            "yaw_deg": att[:, 2], "pitch_deg": att[:, 1], "roll_deg": att[:, 0]}
    return {"rms": {k: _rms(v) for k, v in cols.items()}, "std": {k: float(np.std(v)) for k, v in cols.items()}}


def run_attitude(runs: int = 2, seed: int = 1, jobs: int = 0, scenario_name: str = "attitude") -> dict:
    """Seed 003 Table 2 on scenario 'attitude': PV vs PVA."""
    t_start = time.perf_counter()
    results = _pool(_attitude_one, [(seed + r, scenario_name) for r in range(runs)], jobs)
    modes = {m: _att_stats([r[m] for r in results]) for m in ATT_MODES}
    impr = {k: _pct(modes["PV"]["rms"][k], modes["PVA"]["rms"][k]) for k in modes["PV"]["rms"]}
    impr_std = {k: _pct(modes["PV"]["std"][k], modes["PVA"]["std"][k]) for k in modes["PV"]["std"]}
    return {"scenario": scenario_name, "runs": runs, "seed": seed,
            "interval": "whole flight (1 Hz samples, pooled over runs)",
            "modes": modes, "improvement_rms_pct": impr, "improvement_std_pct": impr_std,
            "improvement_roll_pct": impr["roll_deg"], "improvement_pitch_pct": impr["pitch_deg"],
            "improvement_yaw_pct": impr["yaw_deg"], "paper": PAPER_TABLE2,
            "counters": {m: results[0][m]["counters"] for m in ATT_MODES},
            "elapsed_s": time.perf_counter() - t_start}


def format_attitude(res: dict) -> str:
    keys = [("N cm", "n_cm"), ("E cm", "e_cm"), ("U cm", "u_cm"), ("VN cm/s", "vn_cmps"),
            ("VE cm/s", "ve_cmps"), ("VU cm/s", "vu_cmps"), ("Y deg", "yaw_deg"), ("P deg", "pitch_deg"),
            ("R deg", "roll_deg")]
    head = f"{'':12s}" + "".join(f"{lab:>10}" for lab, _ in keys)
    lines = [f"Seed 003 Table 2: RMS over the whole flight, PV vs PVA (GNSS attitude), {res['runs']} run(s), "
             f"scenario '{res['scenario']}'  [paper's figures in the (paper) rows]", head, "-" * len(head)]
    P = res["paper"]
    for m in ATT_MODES:
        lines.append(f"{m + ' RMS':12s}" + "".join(f"{res['modes'][m]['rms'][k]:10.4f}" for _, k in keys))
        lines.append(f"{m + ' STD':12s}" + "".join(f"{res['modes'][m]['std'][k]:10.4f}" for _, k in keys))
        lines.append(f"{'(paper) ' + m:12s}" + "".join(f"{P[m][k]:10.4f}" for _, k in keys))
    lines.append(f"{'impr. RMS':12s}" + "".join(f"{res['improvement_rms_pct'][k]:9.1f}%" for _, k in keys))
    lines.append(f"{'(paper)':12s}" + "".join(f"{_pct(P['PV'][k], P['PVA'][k]):9.1f}%" for _, k in keys))
    c = res["counters"]["PVA"]
    lines.append(f"first run, PVA: {c.get('attitude used', 0)} attitude rows used, "
                 f"{sum(v for k, v in c.items() if k.startswith('attitude rejected'))} rejected")
    lines.append(f"improvement: roll {res['improvement_roll_pct']:.1f} % (paper 48 %), "
                 f"pitch {res['improvement_pitch_pct']:.1f} % (paper 44 %)")
    return "\n".join(lines)
