"""The ``rtk`` scenario through the engine offline, scored against the truth.

``python -m sitl rtk [--scenario rtk|rtk-gec] [--runs N] [--seed S] [--duration S] [--json PATH]``

The production tight coupling (``sitl.paper`` mode ``tdcp_dgps``: DGPS pseudoranges and TDCP) with
carrier-phase RTK on (:mod:`companion.nav.rtk_update`), base epochs fed as they come, the filter
told the simulator's noise levels (:func:`rtk_config`), nothing tuned to the truth; on 'rtk-gec'
every system of the scenario double-differenced within itself on its two frequencies.  Per run:

* **first fix**: seconds from the start to the application of the first epoch whose fix state is
  ``fixed`` (epoch time + the tuning's 80-ms GNSS latency);
* **horizontal RMS after the first fix, outside outages**: the IMU position error (1 Hz samples,
  local horizontal) from the first fix to the end, the outage windows left out -- every sample,
  fixed or not -- and the same over the fixed epochs only (the error after each fixed epoch's
  update);
* **re-fix after an outage**: an outage lasts from its start until the first rover epoch after
  it has been applied (before that there is no GNSS to fix with); the re-fix time is from then to
  the first fixed epoch (0: that very epoch fixed);
* **wrong fixes**: fixed epochs whose true 3-D error after the update exceeds 0.1 m.
"""
from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from companion.nav.earth import C_n_e, ecef_to_geodetic, rotation_from_rotvec
from companion.nav.engine import EngineConfig, NavEngine
from .simulate import feed_engine

WRONG_FIX_M = 0.1


def rtk_config(scenario, tuning) -> EngineConfig:
    """tdcp_dgps with RTK on; the SD phase and code variances from the scenario's receivers
    (noise and multipath of both, zenith, x 1/sin(el) when the simulator scales them)."""
    from .paper import mode_config
    rv, bs = scenario.rover_rx, scenario.base_rx
    phase_var = rv.carrier_noise_m ** 2 + rv.carrier_mp_m ** 2 + bs.carrier_noise_m ** 2 + bs.carrier_mp_m ** 2
    code_var = rv.code_noise_m ** 2 + rv.code_mp_m ** 2 + bs.code_noise_m ** 2 + bs.code_mp_m ** 2
    # sd_variance_m2 = 2 (a^2 + b^2 / sin^2 el): all in b when the errors scale with elevation
    a, b = (1e-4, math.sqrt(phase_var / 2.0)) if rv.el_scaling else (math.sqrt(phase_var / 2.0), 1e-4)
    systems = getattr(scenario, "systems", "G")
    cfg = mode_config("tdcp_dgps", tuning, scenario.lever_arm_b, systems)
    return dataclasses.replace(cfg, elevation_mask_deg=scenario.mask_deg, rtk_enabled=True,
                               rtk_signals=rtk_signals(systems, scenario.dual_frequency),
                               rtk_sigma_phase_a_m=a, rtk_sigma_phase_b_m=b,
                               rtk_code_phase_ratio=math.sqrt(code_var / phase_var))


def rtk_signals(systems: str, dual_frequency: bool) -> tuple[str, ...]:
    """The canonical RTK codes (companion.rtk_signals) of the simulator's signals of ``systems``
    (one or two per system); GPS alone: ('L1C', 'L2W') as before."""
    from companion.rtk_signals import canonical_signal
    from .simulate import SIGNALS
    out = []
    for sys in systems:
        for sig in SIGNALS[sys][:2 if dual_frequency else 1]:
            c = canonical_signal(sys + "01", sig)
            if c is not None and c not in out:
                out.append(c)
    return tuple(out)


def _renamed(epochs):
    """The epochs with their codes renamed to the RTK families, as the pipeline does (QZSS L2L ->
    L2X); unchanged epochs are the same objects."""
    from companion.rtk_signals import rtk_epoch
    return [rtk_epoch(e) for e in epochs]


def run_rtk(seed: int = 0, duration_s: float | None = None, scenario_name: str = "rtk", cfg=None,
            rover_hook=None, keep_engine: bool = False, hook=None, base_hook=None) -> dict:
    """One run of the rtk scenario (optionally only its first ``duration_s``).  ``rover_hook``,
    ``base_hook``: functions rewriting the list of rover / base epochs (a test strips the
    receiver's slip flags, another switches base stations); ``hook(engine, t_s)``: called after
    every IMU sample (a test meddles with the state)."""
    from .paper import initial_errors
    from .scenario import build_scenario
    from .simulate import simulate
    from .tuning import tuning_for
    scn = build_scenario(scenario_name)
    if duration_s is not None:
        scn = dataclasses.replace(scn, duration_s=float(duration_s))
    t_sim = time.process_time()
    sim = simulate(scn, seed)
    t_sim = time.process_time() - t_sim
    tuning = tuning_for(scn)
    cfg = cfg or rtk_config(scn, tuning)
    eng = NavEngine(cfg)
    for eph in sim.ephemerides:
        eng.process(eph)
    eng.process(sim.base)
    truth = sim.truth
    rng = np.random.default_rng(10_000 + seed)
    d_att, d_pos, d_vel = initial_errors(rng, tuning.p0, truth.r_e[0])
    eng.initialize(truth.t_gps[0], truth.r_e[0] + d_pos, truth.v_e[0] + d_vel,
                   rotation_from_rotvec(d_att) @ truth.C_b_e[0], tuning.p0)
    t0 = float(truth.t_gps[0])
    lat0, lon0, _ = ecef_to_geodetic(truth.r_e[0])
    up_e = -C_n_e(lat0, lon0)[:, 2]
    epochs = []

    def on_epoch(rep):
        r_true = sim.truth_at(eng.t_gps)[0]
        d = eng.r_e - r_true
        epochs.append((eng.t_gps - t0, rep.fix_state, rep.fix_ratio, rep.n_fixed, float(np.linalg.norm(d)),
                       float(np.linalg.norm(d - up_e * (d @ up_e)))))

    eng.on_epoch = on_epoch
    lat = tuning.gnss_latency_s
    rover = _renamed(rover_hook(sim.rover_epochs) if rover_hook is not None else sim.rover_epochs)
    step = max(1, int(round(1.0 / (truth.t_gps[1] - truth.t_gps[0]))))
    ts, err_h = [], []
    t_eng = time.process_time()
    base = base_hook(sim.base_epochs) if base_hook is not None else sim.base_epochs
    for k, s in feed_engine(eng, sim, lat, rover=rover, base=_renamed(base)):
        if hook is not None:
            hook(eng, s.t_gps - t0)
        if k % step == 0:
            d = eng.r_e - truth.r_e[k]
            ts.append(s.t_gps - t0)
            err_h.append(float(np.linalg.norm(d - up_e * (d @ up_e))))
    t_eng = time.process_time() - t_eng
    # an outage lasts until the first rover epoch after it has been applied (no GNSS before)
    t_applied = np.array([e[0] for e in epochs])
    outages = []
    for a, b in scn.rover_outages:
        later = t_applied[t_applied >= b - t0]
        outages.append((a - t0, float(later[0]) if len(later) else scn.duration_s))
    extra = {"engine": eng, "sim": sim} if keep_engine else {}
    return {**extra, "scenario": scenario_name, "seed": seed, "duration_s": scn.duration_s, "outages_s": outages, "t_s": np.array(ts),
            "err_h_m": np.array(err_h), "epochs": epochs, "counters": dict(eng.counters),
            "cpu_simulate_s": t_sim, "cpu_engine_s": t_eng, "imu_samples": len(sim.imu),
            **score(np.array(ts), np.array(err_h), epochs, outages)}


def score(ts, err_h, epochs, outages) -> dict:
    fixed = [e for e in epochs if e[1] == "fixed"]
    first = fixed[0][0] if fixed else math.nan
    out = np.zeros(len(ts), bool)
    for a, b in outages:
        out |= (ts >= a) & (ts < b)
    sel = (ts >= first) & ~out if fixed else np.zeros(len(ts), bool)
    refix = []
    for a, b in outages:
        fx = [e[0] for e in fixed if e[0] >= b]
        refix.append(fx[0] - b if fx else math.inf)
    n_rtk = sum(1 for e in epochs if e[1] in ("float", "fixed"))
    return {"first_fix_s": first,
            "rms_h_after_first_fix_m": float(np.sqrt(np.mean(err_h[sel] ** 2))) if np.any(sel) else math.nan,
            "rms_h_fixed_epochs_m": float(np.sqrt(np.mean(np.array([e[5] for e in fixed]) ** 2))) if fixed else math.nan,
            "refix_after_outage_s": refix,
            "wrong_fixes": sum(1 for e in fixed if e[4] > WRONG_FIX_M),
            "fixed_epochs": len(fixed), "rtk_epochs": n_rtk, "n_epochs": len(epochs)}


def format_rtk(runs: list[dict]) -> str:
    lines = ["seed  first fix  RMS_h after 1st fix  RMS_h fixed  re-fix after outage  wrong  fixed/epochs  CPU engine"]
    for r in runs:
        refix = ", ".join(f"{x:.0f} s" for x in r["refix_after_outage_s"]) or "-"
        lines.append(f"{r['seed']:4d}  {r['first_fix_s']:7.0f} s  {r['rms_h_after_first_fix_m']:17.4f} m  "
                     f"{r['rms_h_fixed_epochs_m']:9.4f} m  {refix:>19s}  {r['wrong_fixes']:5d}  "
                     f"{r['fixed_epochs']:5d}/{r['n_epochs']:<6d}  {r['cpu_engine_s']:6.1f} s")
    return "\n".join(lines)


def cmd_rtk(args) -> int:
    from .__main__ import _write_json
    runs = [run_rtk(args.seed + i, args.duration, scenario_name=args.scenario) for i in range(args.runs)]
    print(f"scenario {args.scenario}")
    print(format_rtk(runs))
    _write_json(args.json, [{k: v for k, v in r.items() if k not in ("t_s", "err_h_m", "epochs")} for r in runs])
    return 0


def register(sub) -> None:
    p = sub.add_parser("rtk", help="the rtk scenario through the engine offline: first fix, RMS, re-fix, wrong fixes")
    p.add_argument("--scenario", default="rtk", choices=("rtk", "rtk-gec"),
                   help="rtk (GPS L1+L2) or rtk-gec (GPS+Galileo+BeiDou, two frequencies each)")
    p.add_argument("--runs", type=int, default=1)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--duration", type=float, default=None, help="seconds of the scenario (default: all)")
    p.add_argument("--json", help="write the figures as JSON here")
    p.set_defaults(func=cmd_rtk)
