"""`companion run` and `companion replay`: register(subparsers) wires them into companion.cli.

Also runnable on its own: ``python -m companion.run_cli run --config FILE.toml``.
"""
from __future__ import annotations

import argparse
import logging
import sys


def cmd_run(args) -> int:
    import asyncio
    from .config import ConfigError, load_config
    from .service import Service
    root = logging.getLogger()
    if root.level > logging.INFO:
        root.setLevel(logging.INFO)          # a service logs its health at INFO
    try:
        cfg = load_config(args.config)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if args.log_dir:
        import dataclasses
        cfg = dataclasses.replace(cfg, log=dataclasses.replace(cfg.log, dir=args.log_dir))
    asyncio.run(Service(cfg).run())
    return 0


def cmd_replay(args) -> int:
    from .replay import run_replay_cli
    return run_replay_cli(args)


def register(subparsers) -> None:
    p = subparsers.add_parser("run", help="run the companion service (MAVLink, GNSS, corrections, fusion, outputs)")
    p.add_argument("--config", required=True, help="TOML configuration (see deploy/companion.toml)")
    p.add_argument("--log-dir", help="override log.dir of the configuration")
    p.set_defaults(func=cmd_run)
    r = subparsers.add_parser("replay", help="replay a field log (or a MAVLink .tlog) through the navigation pipeline")
    r.add_argument("log", help="field log file, rotated-log directory or stem, or a .tlog")
    r.add_argument("--config", help="TOML configuration (default: the one recorded in the field log)")
    r.add_argument("--json", help="write solutions and the comparison as JSON here")
    r.add_argument("--plot", help="write a PNG of the track and sigmas here")
    r.add_argument("--no-progress", action="store_true", help="no progress bar")
    r.set_defaults(func=cmd_replay)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="companion")
    parser.add_argument("-v", "--verbose", action="count", default=0)
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose > 1 else logging.INFO if args.verbose else logging.WARNING,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
