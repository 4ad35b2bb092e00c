"""``python -m sitl smooth``: forward-only against RTS-smoothed (companion.nav.smoother) on a simulated flight.

One simulated flight (default 'uav', with its 30-s rover outage), one navigation mode of
:mod:`sitl.paper` (default tdcp_dgps), solutions at ``--rate`` Hz; prints the horizontal RMS against
truth over each rover outage and over the whole flight, forward and smoothed, and the mean NEES of
the position (3 dof) of both.
"""
from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

from companion.nav.earth import C_n_e, ecef_to_geodetic, rotation_from_rotvec
from companion.nav.engine import NavEngine
from companion.nav.smoother import SmootherRecorder
from .simulate import feed_engine


def run_smoothing(scenario_name: str = "uav", seed: int = 1, mode: str = "tdcp_dgps", rate_hz: float = 10.0) -> dict:
    from .paper import initial_errors, mode_config
    from .scenario import build_scenario
    from .simulate import simulate
    from .tuning import tuning_for

    scenario = build_scenario(scenario_name)
    tuning = tuning_for(scenario)
    sim = simulate(scenario, seed)
    truth = sim.truth
    if mode == "rtk":             # carrier-phase RTK: float ambiguity blocks come and go (layout changes)
        from .rtk_score import rtk_config
        cfg = rtk_config(scenario, tuning)
    else:
        cfg = mode_config(mode, tuning, sim.lever_arm_b)
    eng = NavEngine(cfg)
    rec = SmootherRecorder()
    rec.attach(eng)
    for eph in sim.ephemerides:
        eng.process(eph)
    eng.process(sim.base)
    rng = np.random.default_rng(10_000 + seed)          # the same initial errors as sitl.paper's run
    d_att, d_pos, d_vel = initial_errors(rng, tuning.p0, truth.r_e[0])
    eng.initialize(truth.t_gps[0], truth.r_e[0] + d_pos, truth.v_e[0] + d_vel,
                   rotation_from_rotvec(d_att) @ truth.C_b_e[0], tuning.p0)
    use_gnss = mode != "ins"
    step = max(1, int(round(1.0 / (rate_hz * (truth.t_gps[1] - truth.t_gps[0])))))
    k_truth, P_fwd = [], []
    forward = []
    for k, s in feed_engine(eng, sim, tuning.gnss_latency_s, use_gnss=use_gnss):
        if k % step == 0:
            forward.append(eng.solution())
            k_truth.append(k)
            P_fwd.append(eng.kf.P[eng.layout.pos, eng.layout.pos].copy())
    smoothed = rec.smoothed_solutions()
    t0 = truth.t_gps[0]
    t = np.array([s.t_gps for s in forward]) - t0
    r_true = truth.r_e[k_truth]
    err_f = r_true - np.array([s.r_e for s in forward])
    err_s = r_true - np.array([s.r_e for s in smoothed])
    P_smo = [s.extras["smoothed_cov_nav_e"][3:6, 3:6] for s in smoothed]
    lat0, lon0, _ = ecef_to_geodetic(truth.r_e[0])
    up = -C_n_e(lat0, lon0)[:, 2]
    h_f = np.linalg.norm(err_f - np.outer(err_f @ up, up), axis=1)
    h_s = np.linalg.norm(err_s - np.outer(err_s @ up, up), axis=1)
    sig_h_f = np.array([math.hypot(*s.sigma_r_n_m[:2]) for s in forward])
    sig_h_s = np.array([math.hypot(*s.sigma_r_n_m[:2]) for s in smoothed])

    def rms(x, m):
        return float(np.sqrt(np.mean(x[m] ** 2))) if np.any(m) else math.nan

    def nees(err, Ps, m):
        return float(np.mean([e @ np.linalg.solve(P, e) for e, P, ok in zip(err, Ps, m) if ok]))

    everything = np.ones(len(t), bool)
    out = {"scenario": scenario_name, "seed": seed, "mode": mode, "rate_hz": rate_hz,
           "checkpoints": rec.n_checkpoints, "solutions": len(t),
           "whole": {"rms_h_forward_m": rms(h_f, everything), "rms_h_smoothed_m": rms(h_s, everything),
                     "nees_pos_forward": nees(err_f, P_fwd, everything),
                     "nees_pos_smoothed": nees(err_s, P_smo, everything)},
           "outages": [], "curves": {"t_s": t.tolist(), "err_h_forward_m": h_f.tolist(),
                                     "err_h_smoothed_m": h_s.tolist(), "sigma_h_forward_m": sig_h_f.tolist(),
                                     "sigma_h_smoothed_m": sig_h_s.tolist()}}
    for a, b in scenario.rover_outages:
        m = (t >= a - t0) & (t <= b - t0)
        f, sm = rms(h_f, m), rms(h_s, m)
        out["outages"].append({"start_s": a - t0, "end_s": b - t0, "rms_h_forward_m": f, "rms_h_smoothed_m": sm,
                               "reduction": 1.0 - sm / f, "max_h_forward_m": float(h_f[m].max()),
                               "max_h_smoothed_m": float(h_s[m].max()),
                               "nees_pos_forward": nees(err_f, P_fwd, m), "nees_pos_smoothed": nees(err_s, P_smo, m)})
    return out


def format_smoothing(r: dict) -> str:
    w = r["whole"]
    lines = [f"{r['scenario']} seed {r['seed']}, {r['mode']}, {r['solutions']} solutions at {r['rate_hz']:g} Hz, "
             f"{r['checkpoints']} checkpoints",
             f"whole flight: horizontal RMS forward {w['rms_h_forward_m']:.3f} m, "
             f"smoothed {w['rms_h_smoothed_m']:.3f} m; "
             f"position NEES (3 dof) forward {w['nees_pos_forward']:.2f}, smoothed {w['nees_pos_smoothed']:.2f}"]
    for o in r["outages"]:
        lines.append(f"outage {o['start_s']:.0f}-{o['end_s']:.0f} s: "
                     f"horizontal RMS forward {o['rms_h_forward_m']:.3f} m, "
                     f"smoothed {o['rms_h_smoothed_m']:.3f} m ({100 * o['reduction']:.0f} % lower); max "
                     f"{o['max_h_forward_m']:.2f} / {o['max_h_smoothed_m']:.2f} m; position NEES "
                     f"{o['nees_pos_forward']:.2f} / {o['nees_pos_smoothed']:.2f}")
    return "\n".join(lines)


def plot_smoothing(r: dict, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    c = r["curves"]
    fig, ax = plt.subplots(figsize=(10, 4.5))
    for o in r["outages"]:
        ax.axvspan(o["start_s"], o["end_s"], color="0.9", label="rover outage")
    ax.plot(c["t_s"], c["err_h_forward_m"], color="tab:red", lw=1, label="forward: horizontal error")
    ax.plot(c["t_s"], c["err_h_smoothed_m"], color="tab:blue", lw=1, label="smoothed (RTS): horizontal error")
    ax.plot(c["t_s"], c["sigma_h_forward_m"], color="tab:red", lw=0.8, ls="--", label="forward sigma_h")
    ax.plot(c["t_s"], c["sigma_h_smoothed_m"], color="tab:blue", lw=0.8, ls="--", label="smoothed sigma_h")
    ax.set_yscale("log")
    ax.set_xlabel("time since start, s")
    ax.set_ylabel("m")
    ax.set_title(f"{r['scenario']} seed {r['seed']} ({r['mode']}): forward-only vs smoothed")
    ax.legend(fontsize=8, loc="upper left")
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def cmd_smooth(args) -> int:
    result = run_smoothing(args.scenario, args.seed, args.mode, args.rate)
    print(format_smoothing(result))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")
    if args.plot:
        plot_smoothing(result, args.plot)
        print(f"wrote {args.plot}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("smooth", help="forward-only vs RTS-smoothed trajectory on a simulated flight "
                                      "(horizontal RMS over the rover outages and overall)")
    p.add_argument("--scenario", default="uav", help="simulated flight (default uav: 30-s rover outage)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--mode", default="tdcp_dgps", help="navigation mode of sitl.paper (default tdcp_dgps), or rtk "
                   "(with --scenario rtk)")
    p.add_argument("--rate", type=float, default=10.0, help="solution rate, Hz")
    p.add_argument("--json", help="write the figures and curves as JSON here")
    p.add_argument("--plot", help="write a PNG of the errors and sigmas against time here")
    p.set_defaults(func=cmd_smooth)


if __name__ == "__main__":
    import argparse
    ap = argparse.ArgumentParser(prog="python -m sitl.smooth")
    register(ap.add_subparsers(dest="cmd", required=True))
    a = ap.parse_args(["smooth"] + sys.argv[1:])
    sys.exit(a.func(a))
