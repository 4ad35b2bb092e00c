"""`companion run` and `companion replay`: register(subparsers) wires them into companion.cli.

Also runnable on its own: ``python -m companion.run_cli run --config FILE.toml``.
"""
from __future__ import annotations

import argparse
import logging
import sys


def cmd_run(args) -> int:
    from .config import ConfigError, load_config, missing_extras, secrets_readable_by_others
    root = logging.getLogger()
    if root.level > logging.INFO:
        root.setLevel(logging.INFO)          # a service logs its health at INFO
    try:                                     # the configuration first: its errors come in milliseconds
        cfg = load_config(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    missing = missing_extras(cfg)
    if missing:
        for msg in missing:
            print(f"error: {msg}", file=sys.stderr)
        return 2
    warning = secrets_readable_by_others(cfg)
    if warning:
        logging.getLogger("companion").warning("%s", warning)
    from .io.mavlink_signing import SigningKeyError, signing_preflight
    try:                     # no start without the signing key it is configured with (the service
        signing_preflight(cfg)   # warns about its permissions itself, and counts it)
    except SigningKeyError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    from .nav.rtk_antennas import antennas_preflight
    problem = antennas_preflight(cfg)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    import asyncio

    from .service import Service
    if args.log_dir:
        import dataclasses
        cfg = dataclasses.replace(cfg, log=dataclasses.replace(cfg.log, dir=args.log_dir))
    asyncio.run(Service(cfg).run())
    return 0


def cmd_replay(args) -> int:
    from .replay import run_replay_cli
    if getattr(args, "smooth", False) and str(args.log).endswith((".tlog", ".mavlink")):
        print(f"error: {args.log}: --smooth post-processes a field log, a DataFlash .BIN or a PX4 .ulg "
              f"(not yet a tlog)", file=sys.stderr)
        return 2
    return run_replay_cli(args)


def register(subparsers) -> None:
    p = subparsers.add_parser("run", help="run the companion service (MAVLink, GNSS, corrections, fusion, outputs)")
    p.add_argument("--config", required=True, help="TOML configuration (see deploy/companion.toml)")
    p.add_argument("--log-dir", help="override log.dir of the configuration")
    p.set_defaults(func=cmd_run)
    r = subparsers.add_parser("replay", help="replay a field log, a MAVLink .tlog or an ArduPilot DataFlash .BIN "
                                             "through the navigation pipeline")
    r.add_argument("log", help="field log file, rotated-log directory or stem, a .tlog, a DataFlash .BIN, a PX4 "
                   ".ulg, or a u-blox .ubx with --imu-csv")
    r.add_argument("--config", help="TOML configuration (default: the one recorded in the field log)")
    r.add_argument("--antennas-file", metavar="FILE",
                   help="field log: the antenna calibration file (filter.rtk_antennas) the flight used, where it "
                        "is on this machine (default: the logged path; its SHA-256 is checked against the log's)")
    r.add_argument("--json", help="write solutions and the comparison as JSON here")
    r.add_argument("--plot", help="write a PNG of the track and sigmas here")
    r.add_argument("--pos", help="write the replayed solutions in RTKLIB's .pos format (rtkplot, pos2kml)")
    r.add_argument("--kml", help="write the replayed solutions as a KML track (Google Earth)")
    r.add_argument("--gpx", help="write the replayed solutions as a GPX track")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.add_argument("--min-imu-rate-hz", type=float, help="refuse a log whose IMU is slower (default 20)")
    r.add_argument("--gps-latency-ms", type=float, help="DataFlash: GPS fix age at its record "
                   "(default SIM_GPSn_LAG_MS in SITL, else GPSn_DELAY_MS, else 0)")
    r.add_argument("--imu-instance", type=int, help="DataFlash: IMU instance (default 0)")
    r.add_argument("--start", type=float, help="DataFlash: first boot time used, s")
    r.add_argument("--end", type=float, help="DataFlash: last boot time used, s")
    r.add_argument("--smooth", action="store_true", help="field log, DataFlash, ULog: RTS-smooth the forward solutions "
                   "(post-flight: the best trajectory, through GNSS outages); with a truth the forward pass is "
                   "scored beside it")
    r.add_argument("--imu-csv", help="LOG is a u-blox .ubx capture (RXM-RAWX + RXM-SFRBX) or RINEX observations "
                   "(with --nav), and this the IMU recorded beside it (companion.io.imu_csv)")
    r.add_argument("--imu-columns", help="IMU CSV: t=COL,gx=COL,gy=COL,gz=COL,ax=COL,ay=COL,az=COL "
                   "(default: those names)")
    r.add_argument("--imu-time", choices=("gps", "unix"), default="gps",
                   help="IMU CSV time: GPS seconds (week*604800+TOW) or UNIX seconds (UTC)")
    r.add_argument("--gyro-unit", choices=("rad/s", "deg/s"), default="rad/s")
    r.add_argument("--accel-unit", choices=("m/s2", "g"), default="m/s2")
    r.add_argument("--imu-rotation", help="IMU CSV: the body FRD axis of each sensor axis, e.g. x,-y,-z for a "
                   "sensor in FLU (default x,y,z)")
    r.add_argument("--nav", help="the RINEX navigation file (the day's broadcast ephemerides, e.g. IGS BRDC): with "
                   "--imu-csv and RINEX observations, a DataFlash .BIN whose u-blox raw observations ArduPilot "
                   "logged (GPS_RAW_DATA 1: GRXH/GRXS), or a PX4 .ulg whose receiver output RTCM (gps_dump, "
                   "GPS_DUMP_COMM 2); the raw observations are then used tightly coupled")
    r.add_argument("--base", help="a base station's RINEX observations or RTCM 3 capture (1005/1006 + MSM4-7 or "
                   "1004/1012), beside --imu-csv, a DataFlash .BIN or a PX4 .ulg with raw observations: DGPS")
    r.add_argument("--ubx-latency-ms", type=float, default=50.0,
                   help=".ubx: receiver output latency after each epoch's time (default 50)")
    r.set_defaults(func=cmd_replay)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="companion")
    parser.add_argument("-v", "--verbose", action="count", default=0)
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(argv)
    from .journal_log import configure_logging       # <N> syslog priorities when stderr is the journal
    configure_logging(logging.DEBUG if args.verbose > 1 else logging.INFO if args.verbose else logging.WARNING)
    from .extras import MissingExtra
    try:
        return int(args.func(args) or 0)
    except MissingExtra as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
