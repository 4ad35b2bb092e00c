"""``python -m sitl faults``: the integrity fault matrix (issue 10).

The simulated flight (``sitl.fly``: the emulated autopilot, the base station behind an NTRIP caster,
``companion run`` as its own process) is flown once per fault, plus a clean control flight, and only
what the emulated autopilot *received* is scored:

* ``estimates_received``;
* ``hmi_fraction``: share of received estimates whose true horizontal error exceeds the
  horizontal protection level sent with them -- hazardously misleading information.  The
  injected messages have no field for it: the companion's NAMED_VALUE_FLOAT ``CC_HPL`` (sent at
  ``HPL_NAMED_VALUE_RATE_HZ`` in these flights) is matched by receive time, the last one received
  at or before the estimate (it comes right after the estimate of its own solution, so an
  estimate is scored against the previous solution's HPL: never a later, larger one).  Without
  a CC_HPL (none received yet, or older than ``HPL_MAX_AGE_S``) the bound is 3 x the horizontal
  sigma the estimate carried (``sqrt(var_x + var_y)`` of VISION_POSITION_ESTIMATE's covariance,
  the service's own sigma_h); ``hmi_reference`` counts which bound each estimate was scored on;
* ``max_injected_error_h_m``;
* ``injection_gap_s``: the longest time without an estimate after the first one (to the end of the
  flight);
* ``recovered``: an estimate with a horizontal error under 1 m arrived within 20 s of the fault's
  end (``recovery_s`` says when).  A fault that lasts the whole flight (wrong or missing initial
  heading, a late SYSTEM_TIME) "ends" at ``WHOLE_FLIGHT_END_S``: the companion has that long to
  find out.

Faults start at ``FAULT_AT_S`` into the flight (the 'uav' survey flight is then on its first leg).
"""
from __future__ import annotations

import asyncio
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

G_MPS2 = 9.80665
FAULT_AT_S = 40.0
WHOLE_FLIGHT_END_S = 30.0
RECOVERY_WINDOW_S = 20.0
RECOVERED_ERROR_H_M = 1.0
HMI_SIGMA_FACTOR = 3.0
HPL_NAMED_VALUE_RATE_HZ = 10.0      # the companion's NAMED_VALUE_FLOAT rate in these flights (its maximum)
HPL_MAX_AGE_S = 0.5                 # a CC_HPL older than this (receive time) is not matched to an estimate
#: RAW_IMU's int16 full scale in mG, as m/s^2 (what a clipped ArduPilot accelerometer reports)
RAW_IMU_FULL_SCALE_MPS2 = 32.767 * G_MPS2


@dataclass
class FaultCase:
    name: str
    what: str
    window_s: tuple[float, float]              # (start, end) from the start of the flight
    faults: dict = field(default_factory=dict)  # sitl.autopilot.Faults keyword arguments
    fly: dict = field(default_factory=dict)     # extra sitl.fly.fly keyword arguments


def fault_cases() -> list[FaultCase]:
    T = FAULT_AT_S
    g = G_MPS2
    fs = RAW_IMU_FULL_SCALE_MPS2
    return [
        FaultCase("control", "no fault", (0.0, 0.0)),
        FaultCase("accel_16g", "one 16-g accelerometer sample (x)", (T, T),
                  {"imu_override": [(T, 1, (16.0 * g, 0.0, -g), None)]}),
        FaultCase("accel_full_scale_x4", "four consecutive full-scale accelerometer samples", (T, T + 0.02),
                  {"imu_override": [(T, 4, (fs, fs, fs), None)]}),
        FaultCase("gyro_2000dps", "one 2000 deg/s gyro sample (z)", (T, T),
                  {"imu_override": [(T, 1, None, (0.0, 0.0, math.radians(2000.0)))]}),
        FaultCase("imu_noise_10s", "10 s of IMU noise (5 m/s^2, 0.5 rad/s per sample)", (T, T + 10.0),
                  {"imu_noise": [(T, T + 10.0, 5.0, 0.5)]}),
        FaultCase("spoof_100m_20s", "GNSS position 100 m north for 20 s (raw observations and GPS_RAW_INT)",
                  (T, T + 20.0), {"gnss_offset_ned": [(T, T + 20.0, (100.0, 0.0, 0.0))]}),
        FaultCase("receiver_clock_jump_1ms", "the receiver clock steps by 1 ms", (T, T),
                  {"rover_clock_jump": [(T, 1e-3)]}),
        FaultCase("gnss_outage_30s", "no GNSS for 30 s", (T, T + 30.0), {"gnss_outage": [(T, T + 30.0)]}),
        FaultCase("gnss_outage_60s", "no GNSS for 60 s", (T, T + 60.0), {"gnss_outage": [(T, T + 60.0)]}),
        FaultCase("heading_180", "the autopilot's ATTITUDE yaw is 180 deg off", (0.0, WHOLE_FLIGHT_END_S),
                  {"attitude_yaw_error_deg": 180.0}),
        FaultCase("no_attitude", "the autopilot sends no ATTITUDE", (0.0, WHOLE_FLIGHT_END_S),
                  {"no_attitude": True}),
        FaultCase("system_time_late_80ms", "SYSTEM_TIME 80 ms late", (0.0, WHOLE_FLIGHT_END_S),
                  fly={"system_time_late_s": 0.08}),
        FaultCase("corrections_outage_60s", "no base-station corrections for 60 s", (T, T + 60.0),
                  fly={"base_outage_s": (T, T + 60.0)}),
    ]


def _sigma_h_m(r) -> float:
    """Horizontal 1-sigma a received estimate states (the service's sigma_h)."""
    msg = r.msg
    cov = getattr(msg, "covariance", None) if r.msg_type == "VISION_POSITION_ESTIMATE" else \
        getattr(msg, "pose_covariance", None)
    if cov is None or not all(math.isfinite(c) for c in (cov[0], cov[6])):
        return float("nan")
    return math.sqrt(max(cov[0], 0.0) + max(cov[6], 0.0))


def _named_value_series(ap, name: str) -> tuple[list, list]:
    """(receive times ns, values) of the NAMED_VALUE_FLOAT ``name`` the autopilot received, in order
    (-1 is what the companion sends for a non-finite value: kept as NaN)."""
    t, v = [], []
    for r in ap.received:
        if r.msg_type != "NAMED_VALUE_FLOAT":
            continue
        nm = r.msg.name
        nm = (nm.decode("ascii", "replace") if isinstance(nm, bytes) else str(nm)).rstrip("\x00")
        if nm == name:
            t.append(r.t_mono_ns)
            x = float(r.msg.value)
            v.append(x if x >= 0.0 else math.nan)
    return t, v


def _hpl_for(r, hpl_t: list, hpl_v: list) -> float:
    """The CC_HPL received last at or before estimate ``r`` (NaN: none recent enough)."""
    import bisect
    k = bisect.bisect_right(hpl_t, r.t_mono_ns) - 1
    if k < 0 or r.t_mono_ns - hpl_t[k] > HPL_MAX_AGE_S * 1e9:
        return math.nan
    return hpl_v[k]


def score_fault(ap, sim, case: FaultCase, duration_s: float) -> dict:
    """The matrix's figures for one flight, from the estimates the emulated autopilot received."""
    from .fly import scored_estimates
    hpl_t, hpl_v = _named_value_series(ap, "CC_HPL")
    t_rel, err_h, sig_h, hpl = [], [], [], []
    for r, e in scored_estimates(ap, sim):
        if e is None:
            continue
        t_rel.append(e[1] - ap.t0)
        err_h.append(e[3])
        sig_h.append(_sigma_h_m(r))
        hpl.append(_hpl_for(r, hpl_t, hpl_v))
    t, eh, sh, hp = np.array(t_rel), np.array(err_h), np.array(sig_h), np.array(hpl)
    n = len(t)
    on_hpl = np.isfinite(hp)
    bound = np.where(on_hpl, hp, HMI_SIGMA_FACTOR * sh)
    hmi = int(np.sum(~(eh <= bound))) if n else 0      # a NaN bound counts as misleading
    order = np.sort(t)
    gaps = np.diff(np.concatenate([order, [duration_s]])) if n else np.array([duration_s])
    end = case.window_s[1]
    good = (t >= end) & (t <= end + RECOVERY_WINDOW_S) & (eh < RECOVERED_ERROR_H_M)
    recovery = float(t[good].min() - end) if good.any() else None
    after = t >= end
    return {
        "fault": case.name, "what": case.what, "window_s": list(case.window_s),
        "estimates_received": n,
        "hmi_fraction": round(hmi / n, 5) if n else 0.0,
        "hmi_estimates": hmi,
        "hmi_reference": {"hpl": int(np.sum(on_hpl)), "3_sigma_h": int(n - np.sum(on_hpl))},
        "max_hpl_m": round(float(hp[on_hpl].max()), 3) if on_hpl.any() else None,
        "min_hpl_over_error": round(float(np.min(hp[on_hpl] / np.maximum(eh[on_hpl], 1e-9))), 3)
        if on_hpl.any() else None,
        "max_injected_error_h_m": round(float(eh.max()), 3) if n else None,
        "rms_h_m": round(float(np.sqrt(np.mean(eh ** 2))), 4) if n else None,
        "rms_h_after_recovery_m": (round(float(np.sqrt(np.mean(eh[after & (t >= end + (recovery or 0))] ** 2))), 4)
                                   if recovery is not None else None),
        "injection_gap_s": round(float(gaps.max()), 2),
        "recovered": recovery is not None,
        "recovery_s": None if recovery is None else round(recovery, 2),
    }


async def _fly_case(case: FaultCase, *, duration_s: float, speedup: float, out_dir: Path, seed: int) -> dict:
    from .autopilot import Faults
    from .fly import fly
    captured = {}
    res = await fly("uav", duration_s, speedup, seed=seed, out_dir=str(out_dir / case.name),
                    faults=Faults(**case.faults), keep_autopilot=captured, handle_signals=True,
                    named_value_rate_hz=HPL_NAMED_VALUE_RATE_HZ, **case.fly)
    if res["interrupted"]:          # Ctrl-C/SIGTERM: that flight's processes are stopped; stop the matrix
        raise KeyboardInterrupt
    row = score_fault(captured["ap"], captured["sim"], case, res["duration_s"])
    applied = {k: v for k, v in captured["ap"].counters.items()
               if k in ("imu_samples_overridden", "rover_epochs_faulty", "clock_jumps")}
    row.update({"applied": applied, "statustext": res["statustext"][-20:],
                "companion_exit_code": res["companion_exit_code"],
                "reset_counters_seen": res["reset_counters_seen"],
                "imu_time_offset": imu_time_offset_series(res["field_log_dir"], captured["ap"].t0)})
    return row


def imu_time_offset_series(field_log_dir, t0_gps: float) -> list[list[float]]:
    """The companion's IMU time-tag offset estimate over the flight, from the health reports of its
    field log: [time from the start of the flight (s), offset (s), its 1-sigma (s)] per report."""
    from companion.io.fieldlog import read_field_log
    out = []
    try:
        for rec in read_field_log(field_log_dir):
            if rec.kind != "event":
                continue
            obj = json.loads(rec.payload)
            f = obj.get("health", {}).get("filter", {}) if obj.get("event") in ("health", "stop") else {}
            if "imu_time_offset_s" in f and f.get("t_gps") is not None:
                out.append([round(float(f["t_gps"]) - t0_gps, 2), f["imu_time_offset_s"], f["imu_time_offset_sigma_s"]])
    except (OSError, ValueError):
        pass
    return out


def summarise(rows: list[dict]) -> dict:
    faulty = [r for r in rows if r["fault"] != "control"]
    control = next((r for r in rows if r["fault"] == "control"), None)
    n = sum(r["estimates_received"] for r in faulty)
    return {
        "all_recovered": all(r["recovered"] for r in faulty),
        "hmi_fraction": round(sum(r["hmi_estimates"] for r in faulty) / n, 5) if n else 0.0,
        "max_injected_error_h_m": max((r["max_injected_error_h_m"] or 0.0) for r in faulty) if faulty else None,
        "control_rms_h_m": None if control is None else control["rms_h_m"],
        "control_hmi_fraction": None if control is None else control["hmi_fraction"],
    }


def format_rows(rows: list[dict], summary: dict) -> str:
    head = (f"{'fault':26s} {'est':>5s} {'HMI':>8s} {'on HPL':>6s} {'max err h':>10s} {'max HPL':>8s} "
            f"{'HPL/err':>7s} {'gap':>7s} {'recovered':>10s}")
    lines = [head, "-" * len(head)]
    for r in rows:
        rec = "n/a" if r["fault"] == "control" else ("yes" if r["recovered"] else "NO")
        if r["recovered"] and r["fault"] != "control":
            rec += f" {r['recovery_s']:.1f}s"
        mx = "n/a" if r["max_injected_error_h_m"] is None else f"{r['max_injected_error_h_m']:.2f} m"
        on_hpl = r.get("hmi_reference", {}).get("hpl", 0)
        mh = "n/a" if r.get("max_hpl_m") is None else f"{r['max_hpl_m']:.2f} m"
        ratio = "n/a" if r.get("min_hpl_over_error") is None else f"{r['min_hpl_over_error']:.2f}"
        lines.append(f"{r['fault']:26s} {r['estimates_received']:5d} {r['hmi_fraction']:8.4f} {on_hpl:6d} {mx:>10s} "
                     f"{mh:>8s} {ratio:>7s} {r['injection_gap_s']:6.1f}s {rec:>10s}")
    lines.append(f"overall: all recovered {summary['all_recovered']}, HMI fraction {summary['hmi_fraction']:.4f}, "
                 f"max injected error {summary['max_injected_error_h_m']} m; control RMS h "
                 f"{summary['control_rms_h_m']} m, control HMI {summary['control_hmi_fraction']}")
    return "\n".join(lines)


def select_cases(cases: list, only: str | None, what: str = "fault") -> list | None:
    """The cases named in ``only`` (comma-separated; None/empty: all), in matrix order; None (and
    a message on stderr) when a name is unknown."""
    if not only:
        return list(cases)
    want = set(only.split(","))
    unknown = want - {c.name for c in cases}
    if unknown:
        print(f"unknown {what}(s): {', '.join(sorted(unknown))}; known: {', '.join(c.name for c in cases)}",
              file=sys.stderr)
        return None
    return [c for c in cases if c.name in want]


def run_cases(cases: list, fly_case, describe, what: str = "fault", cmd: str = "sitl faults") -> tuple[list, bool]:
    """Fly every case (``fly_case(case) -> row``, one ``asyncio.run`` each, so a case cannot leak
    into the next), with a progress line per case on stderr (``describe(row)`` after it).  Ctrl-C or
    SIGTERM during a flight (it stops cleanly: KeyboardInterrupt) ends the matrix: (rows flown so
    far, interrupted)."""
    rows = []
    t0 = time.monotonic()
    try:
        for i, case in enumerate(cases, 1):
            print(f"[{time.monotonic() - t0:6.0f} s] {what} {i}/{len(cases)}: {case.name} ({case.what})",
                  file=sys.stderr, flush=True)
            row = asyncio.run(fly_case(case))
            rows.append(row)
            print(f"         {describe(row)}", file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        print(f"{cmd}: interrupted", file=sys.stderr)
        return rows, True
    return rows, False


def cmd_faults(args) -> int:
    cases = select_cases(fault_cases(), args.only)
    if cases is None:
        return 2
    short = [c.name for c in cases if args.duration < c.window_s[1] + RECOVERY_WINDOW_S]
    if short:
        need = max(c.window_s[1] for c in cases) + RECOVERY_WINDOW_S
        print(f"--duration {args.duration:g} s is too short for {', '.join(short)}: the fault and its "
              f"{RECOVERY_WINDOW_S:g}-s recovery window need {need:g} s", file=sys.stderr)
        return 2
    rows, interrupted = run_cases(
        cases, lambda case: _fly_case(case, duration_s=args.duration, speedup=args.speedup,
                                      out_dir=Path(args.out), seed=args.seed),
        lambda row: (f"{row['estimates_received']} estimates, HMI {row['hmi_fraction']:.4f}, max error "
                     f"{row['max_injected_error_h_m']} m, recovered {row['recovered']}"))
    summary = summarise(rows)
    print(format_rows(rows, summary))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps({"faults": rows, "overall": summary, "interrupted": interrupted,
                                               "duration_s": args.duration, "speedup": args.speedup},
                                              indent=2, default=str))
        print(f"wrote {args.json}")
    for r in rows:
        if r.get("imu_time_offset"):
            print(f"{r['fault']}: IMU time offset estimate (t s: ms +- 1-sigma ms) " + ", ".join(
                f"{t:.0f}: {1e3 * o:.1f} +- {1e3 * s:.1f}" for t, o, s in r["imu_time_offset"]))
    return 130 if interrupted else 0


def register(subparsers) -> None:
    p = subparsers.add_parser("faults", help="integrity fault matrix: one simulated flight per fault, scored on "
                                             "what the autopilot received")
    p.add_argument("--duration", type=float, default=125.0, help="simulated seconds per flight (default 125)")
    p.add_argument("--speedup", type=float, default=2.0, help="simulated time per wall-clock second (default 2)")
    p.add_argument("--only", help="comma-separated fault names (default: all)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="out/faults", help="directory for each flight's config and logs")
    p.add_argument("--json", help="write the matrix as JSON here")
    p.set_defaults(func=cmd_faults)
