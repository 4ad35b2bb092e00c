"""python -m sitl: simulation, reproduction of the papers' experiments, benchmarks."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def _write_json(path: str | None, obj) -> None:
    if path:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        Path(path).write_text(json.dumps(obj, indent=2))
        print(f"wrote {path}")


def _progress(done: int, total: int, elapsed_s: float) -> None:
    width = 30
    filled = int(width * done / total)
    eta = elapsed_s / done * (total - done)
    sys.stderr.write(f"\r[{'#' * filled}{'.' * (width - filled)}] run {done}/{total}  "
                     f"{elapsed_s:6.1f} s elapsed, ~{eta:5.1f} s left")
    if done == total:
        sys.stderr.write("\n")
    sys.stderr.flush()


def cmd_paper(args) -> int:
    if args.scenario in ("nhc", "nhc-skid", "attitude", "attitude-mems"):
        return _cmd_compare(args)
    if args.scenario in ("rtk", "rtk-gec"):        # the production mode with RTK on: sitl rtk's scoring
        from .rtk_score import cmd_rtk
        if args.plot:
            print("note: --plot is not drawn for the rtk scenarios (python -m sitl smooth --scenario rtk plots one)",
                  file=sys.stderr)
        return cmd_rtk(argparse.Namespace(scenario=args.scenario, runs=args.runs or 5, seed=args.seed,
                                          duration=None, json=args.json))
    if args.runs is None:
        args.runs = 20
    from .paper import format_table, plot, run_experiment
    from .paper import EXTRA_MODES, MODES
    modes = tuple(args.modes.split(",")) if args.modes else MODES
    unknown = [m for m in modes if m not in MODES + EXTRA_MODES]
    if unknown:
        print(f"unknown mode(s) {unknown}; known: {', '.join(MODES + EXTRA_MODES)}", file=sys.stderr)
        return 2
    result = run_experiment(args.scenario, args.runs, args.seed, modes=modes, progress=_progress, jobs=args.jobs)
    print(format_table(result))
    if "tdcp_dgps_avg_nees_9dof" in result:
        nees = result["tdcp_dgps_avg_nees_9dof"]
        print(f"tdcp_dgps: run-averaged NEES (9 dof: attitude, position, velocity) mean {nees['mean']:.2f}")
    if "outage" in result:
        o = result["outage"]
        print(f"tdcp_dgps over the GNSS outage ({o['duration_s']:.0f} s): 3-D error {o['err_start_m']:.2f} m at "
              f"its start, {o['err_end_m']:.2f} m at its end (max {o['err_max_m']:.2f} m)")
        td = result["modes"]["tdcp_dgps"]
        print(f"tdcp_dgps horizontal RMS: {td['rms_h_m']:.3f} m over the whole flight, "
              f"{td['rms_h_m_outside_outage']:.3f} m outside the outage")
    _write_json(args.json, result)
    if args.plot:
        plot(result, args.plot)
        print(f"wrote {args.plot}")
    return 0


def _cmd_compare(args) -> int:
    """Seeds 002 and 003: the same flight with and without the constraint / attitude updates."""
    from . import compare
    if args.scenario.startswith("nhc"):
        result = compare.run_nhc(runs=args.runs or 4, seed=args.seed, jobs=args.jobs, scenario_name=args.scenario)
        print(compare.format_nhc(result))
    else:
        result = compare.run_attitude(runs=args.runs or 2, seed=args.seed, jobs=args.jobs, scenario_name=args.scenario)
        print(compare.format_attitude(result))
    _write_json(args.json, result)
    return 0


def cmd_bench(args) -> int:
    from .bench import format_bench, run_bench
    result = run_bench(args.duration, kf_gins_dir=args.kf_gins_format)
    print(format_bench(result))
    if args.kf_gins_format:
        e = result["kf_gins_export"]
        print(f"  KF-GINS input: {e['imu_records']} IMU and {e['gnss_records']} GNSS records in {e['dir']}")
    _write_json(args.json, result)
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m sitl", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    pp = sub.add_parser("paper", help="seed 000's experiment: five navigation modes on the same simulated data")
    pp.add_argument("--scenario", default="paper",
                    help="paper (seed 000 sec 4.1), paper-nosa, uav (realistic survey flight), "
                         "uav-gec (uav with GPS+Galileo+BeiDou), rtk / rtk-gec (carrier-phase RTK in the "
                         "filter, scored as python -m sitl rtk: first fix, RMS, re-fix, wrong fixes; 5 runs), "
                         "nhc / nhc-skid (seed 002: with vs without NHC), attitude / attitude-mems "
                         "(seed 003: PV vs PVA)")
    pp.add_argument("--runs", type=int, default=None,
                    help="Monte Carlo runs (default 20; nhc 4, attitude 2 to stay under a minute)")
    pp.add_argument("--seed", type=int, default=1, help="seed of the first run; run i uses seed+i")
    pp.add_argument("--jobs", type=int, default=0, help="worker processes (default: one per CPU core)")
    pp.add_argument("--modes", help="comma-separated modes (default: the paper's five; also tdcp_dgps_sd)")
    pp.add_argument("--json", help="write the results as JSON here")
    pp.add_argument("--plot", help="write a PNG of the error of every mode against time here")
    pp.set_defaults(func=cmd_paper)
    pb = sub.add_parser("bench", help="engine throughput, latency and memory")
    pb.add_argument("--duration", type=float, default=None, help="seconds of the uav flight to use (default: all)")
    pb.add_argument("--json", help="write the figures as JSON here")
    pb.add_argument("--kf-gins-format", metavar="DIR",
                    help="also write the workload (IMU increments, DGPS fixes, kf-gins.yaml) in KF-GINS's formats here")
    pb.set_defaults(func=cmd_bench)
    from . import attack, faults, fly, ins_errors, rtk_score, slips, smooth
    smooth.register(sub)
    rtk_score.register(sub)
    fly.register(sub)
    faults.register(sub)
    attack.register(sub)
    ins_errors.register(sub)
    slips.register(sub)
    from . import ardupilot, px4
    ardupilot.register(sub)
    px4.register(sub)
    args = p.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
