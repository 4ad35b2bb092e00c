"""`companion` command line: one entry point, argparse subcommands.

Each subcommand's implementation lives next to the code it drives and is imported lazily, so
`companion gnss` does not pay for MAVLink imports and vice versa.
"""
from __future__ import annotations

import argparse
import logging
import sys

from . import __version__
from .extras import MissingExtra


def _add_gnss(sub) -> None:
    p = sub.add_parser("gnss", help="post-process RINEX observations (SPP, DGPS or RTK), RTKLIB-style; "
                                    "'gnss configure': set a u-blox receiver up")
    # --rover/--nav are checked in _run_gnss, not by argparse: 'companion gnss configure' has neither
    p.add_argument("--rover", nargs="+", metavar="ROVER",
                   help="rover RINEX observation file(s) (2.x or 3.x), or a u-blox capture (.ubx with RXM-RAWX and "
                        "RXM-SFRBX), or an ArduPilot DataFlash log with its u-blox's raw observations (.BIN, "
                        "GPS_RAW_DATA 1: GRXH/GRXS; with --nav); required.  Several RINEX files of one receiver "
                        "(hourly files, a logger restarted) are read as one")
    p.add_argument("--nav", action="extend", nargs="+", metavar="NAV",
                   help="RINEX navigation file(s) (GPS, Galileo, BeiDou, QZSS broadcast ephemerides; GLONASS's for "
                        "--mode rtk --sys with R): several after one --nav (--nav N/*.rnx) or --nav repeated; "
                        "required with a RINEX rover, optional with a .ubx one")
    p.add_argument("--base", nargs="+", metavar="BASE",
                   help="base station RINEX observation file(s) or u-blox capture (RXM-RAWX, RXM-SFRBX) for "
                        "--mode dgps and rtk; with rtk also an RTCM 3 capture (MSM4-7 or 1004/1012, its "
                        "1005/1006 position, ephemerides).  Several RINEX files of one station (a CORS's "
                        "hourly files, e.g. --base B/*.rnx) are read as one")
    p.add_argument("--base-xyz", help="base antenna ECEF X,Y,Z in metres (default: base file header; a u-blox base "
                                      "capture has none); rtk: 'spp' = the median of the base's own single-point "
                                      "solutions (metres off; the baseline stays exact)")
    p.add_argument("--mode", choices=["spp", "dgps", "rtk"], default="spp",
                   help="rtk: L1+L2 carrier phase, integer ambiguities (LAMBDA), fix-and-hold")
    p.add_argument("--direction", choices=["forward", "backward", "combined"], default="forward",
                   help="rtk: forward (each epoch from the ones before it), backward, or combined (both passes "
                        "compared per epoch: a fix the other pass contradicts is reported float; RTKLIB's "
                        "solution types)")
    p.add_argument("--static", action="store_true",
                   help="rtk: the rover stood still (RTKLIB's static mode): one position refined over the file, "
                        "the last epoch's (from every epoch) printed as the survey result; forward only")
    p.add_argument("--glonass-ar", choices=["auto", "on", "off"], default="auto",
                   help="rtk with GLONASS (--sys with R): fix its integers too (on), keep them float (off), or auto: "
                        "on when both RINEX headers name the same receiver model (inter-channel biases cancel)")
    p.add_argument("--truth-xyz", help="true rover ECEF X,Y,Z in metres: enables error statistics")
    p.add_argument("--against-demo5", action="store_true",
                   help="rtk with RINEX files: run RTKLIB demo5 on the same files with the same options and "
                        "compare epoch by epoch (fixed epochs, how far apart, with --truth-xyz both RMS); "
                        "with --pos its solutions go to NAME.demo5.pos (needs the [rtklib] extra, x86_64)")
    p.add_argument("--sys", default="auto",
                   help="constellations, e.g. G,E,C,J (GPS, Galileo, BeiDou, QZSS) or 'all'; default: every one "
                        "of G,E,C,J with observations and ephemerides in the files.  GLONASS (R) when asked "
                        "(G,R,E,C,J, all; its code inter-channel biases vary with the receiver), and with --mode rtk "
                        "also by default when its integers can be fixed (see --glonass-ar)")
    p.add_argument("--freq", choices=["l1", "if"], default=None,
                   help="spp/dgps: l1 (the default) = each system's single-frequency code (GPS/QZSS L1 C/A, "
                        "Galileo E1, BeiDou B1I) with Klobuchar; if = dual-frequency iono-free per system.  "
                        "rtk: both frequencies by default; l1 = each system's first one alone (what a "
                        "single-frequency receiver gives)")
    p.add_argument("--iono", choices=["off", "est"], default="off",
                   help="rtk: est = estimate the differential ionosphere (one slant delay per satellite, RTKLIB's "
                        "ionoopt est): a few km of baseline already carry centimetres of it, which 'off' (RTKLIB's "
                        "and demo5's default) leaves in the position, mostly its height; est needs more satellites "
                        "or time to fix")
    p.add_argument("--antennas", metavar="FILE",
                   help="rtk: receiver antenna calibrations, an IGS ANTEX (igs20.atx) or NGS ant_info (ngs_abs.pcv) "
                        "file (RTKLIB's file-rcvantfile): each receiver's phase centres from the antenna type its "
                        "RINEX header names.  Without it they are taken at the antenna reference point, which "
                        "puts centimetres into the height when the two antennas differ")
    p.add_argument("--rover-antenna", metavar="TYPE",
                   help="rtk with --antennas: the rover antenna's IGS type ('TRM59800.00 SCIS') instead of its "
                        "header's")
    p.add_argument("--base-antenna", metavar="TYPE",
                   help="rtk with --antennas: the base antenna's IGS type instead of its header's")
    p.add_argument("--start", metavar="GPST", help="process from this time on, GPST as RTKLIB writes it "
                   "('2021/09/22 06:31:00') or ISO ('2021-09-22T06:31:00'); default: the rover file's first epoch")
    p.add_argument("--end", metavar="GPST", help="process up to this time (GPST, as --start); default: the file's last")
    p.add_argument("--elevation-mask-deg", type=float, default=10.0)
    p.add_argument("--json", help="write statistics and per-epoch solutions as JSON here")
    p.add_argument("--pos", help="write per-epoch solutions in RTKLIB's .pos format here (rtkplot, pos2kml)")
    p.add_argument("--kml", help="write the solutions as a Google Earth KML track (points coloured by quality)")
    p.add_argument("--gpx", help="write the solutions as a GPX 1.1 track")
    p.add_argument("--plot", help="write a PNG here: the track by solution quality, the offsets over time "
                                  "with their 3-sigma, satellites and RTK ratio (needs the [plot] extra)")
    p.set_defaults(func=lambda a: _run_gnss(p, a))
    from .io import ubx_configure
    ubx_configure.register(p.add_subparsers(dest="gnss_command", metavar="{configure}"))


def _run_gnss(parser, args) -> int:
    missing = [o for o, v in (("--rover", args.rover),) if not v]
    if missing:
        parser.error("the following arguments are required: " + ", ".join(missing))
    return __import__("companion.gnss.postprocess", fromlist=["run"]).run(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="companion", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="count", default=0)
    parser.add_argument("--version", action="version", version=f"companion {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    _add_gnss(sub)
    from . import allan_cli, config_cli, export, run_cli, signing_cli
    run_cli.register(sub)
    export.register(sub)
    allan_cli.register(sub)
    config_cli.register(sub)
    signing_cli.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from .journal_log import configure_logging       # <N> syslog priorities when stderr is the journal
    configure_logging(logging.DEBUG if args.verbose > 1 else logging.INFO if args.verbose else logging.WARNING)
    from .config import ConfigError        # light: the standard library only
    try:
        return int(args.func(args) or 0)
    except (ConfigError, MissingExtra) as exc:     # a bad file or key, or a missing optional package
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
