"""`companion config check FILE` and `companion config example`: register(subparsers) wires them in.

``check`` validates a configuration the way ``companion run`` does, without starting anything and
without importing numpy, scipy or pymavlink, so the answer comes at once (on the board, before a
flight).  It prints ``FILE: OK`` and exits 0, or prints the error (file and key) to stderr and exits 2;
it also reports an optional dependency the file needs but the machine lacks and an unusable
MAVLink signing key file (exit 2), and warns (exit 0) when a file holding a password, or the
signing key file, is readable by other users.

``example`` prints a complete, commented configuration with every key at its default; ``check``
accepts it, and ``deploy/companion.toml`` holds the same keys and values (tests/test_config.py).
"""
from __future__ import annotations

import sys


def cmd_check(args) -> int:
    from .config import ConfigError, load_config, missing_extras, secrets_readable_by_others
    status = 0
    for path in args.files:
        try:
            cfg = load_config(path)
        except ConfigError as exc:
            print(f"error: {exc}", file=sys.stderr)
            status = 2
            continue
        problems = missing_extras(cfg)
        for msg in problems:
            print(f"error: {msg}", file=sys.stderr)
        warning = secrets_readable_by_others(cfg)
        if warning:
            print(f"warning: {warning}", file=sys.stderr)
        from .io.mavlink_signing import SigningKeyError, signing_preflight
        try:
            warning = signing_preflight(cfg)
        except SigningKeyError as exc:
            problems.append(str(exc))
            print(f"error: {exc}", file=sys.stderr)
            warning = None
        if warning:
            print(f"warning: {warning}", file=sys.stderr)
        from .nav.rtk_antennas import antennas_preflight
        problem = antennas_preflight(cfg)
        if problem:
            problems.append(problem)
            print(f"error: {problem}", file=sys.stderr)
        if problems:
            status = 2
        else:
            print(f"{path}: OK")
    return status


def cmd_example(args) -> int:
    from .config import example_config_toml
    sys.stdout.write(example_config_toml())
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("config", help="check a configuration file, or print a complete example")
    sub = p.add_subparsers(dest="config_command", required=True)
    c = sub.add_parser("check", help="validate FILE(s): prints 'FILE: OK', or the error and exits 2")
    c.add_argument("files", nargs="+", metavar="FILE", help="TOML configuration")
    c.set_defaults(func=cmd_check)
    e = sub.add_parser("example", help="print a complete commented configuration (every key, its default)")
    e.set_defaults(func=cmd_example)
