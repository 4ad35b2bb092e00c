"""`companion signing setup`: make a MAVLink 2 signing key file and give the key to the autopilot.

    companion signing setup --key-file /etc/companion/mavlink.key
    companion signing setup --key-file /etc/companion/mavlink.key --connection tcp:127.0.0.1:5762 \\
        --config /etc/companion/companion.toml

Without the file, it writes a random 32-byte key as 64 hex characters, mode 0600 (an existing file
is never overwritten: it is checked and used).  With ``--connection`` it waits for the autopilot's
HEARTBEAT (``target_system``/``target_component`` from ``--config``, else 1/1), sends SETUP_SIGNING
with the key and the current signing timestamp -- itself signed with that key, so an autopilot that
already holds it takes it too -- and then waits for a HEARTBEAT signed with the key: exit 0 when one
arrives (the autopilot signs with our key), 1 when none does within ``--timeout``.

The key travels in clear in SETUP_SIGNING: do it over a trusted link (USB, a cable on the bench).
ArduPilot takes it on any port while it has no key, and, once it has one, only on a port where the
frame is accepted (signed with the current key, or channel 0 / USB, which accepts anything).  PX4
v1.15 has no signing and ignores the message (no signed HEARTBEAT follows: exit 1); the PX4
releases with signing (PX4-Autopilot PR #25284) take it while disarmed, signed with the current key
when one is active, and keep it on the SD card (``/mavlink/mavlink-signing-key.bin``).
"""
from __future__ import annotations

import sys
import time


def _ids(args) -> tuple[int, int, int, int]:
    if args.config:
        from .config import load_config
        m = load_config(args.config).mavlink
        return m.source_system, m.source_component, m.target_system, m.target_component
    return 1, 191, args.target_system, args.target_component


def cmd_setup(args) -> int:
    from .io.mavlink_signing import generate_key_file, key_file_warning, load_key, signing_timestamp
    if generate_key_file(args.key_file):
        print(f"{args.key_file}: new MAVLink signing key (64 hex characters, mode 0600)")
    key = load_key(args.key_file)                 # SigningKeyError -> "error: ..." and exit 2 (cli.main)
    warning = key_file_warning(args.key_file)
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    if not args.connection:
        print(f"{args.key_file}: OK ({key.kind}); set mavlink.signing_key_file to it, and give the key "
              f"to the autopilot (--connection, or MAVProxy `signing setup`)")
        return 0
    import os
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil

    from .io.mavlink_signing import LinkSigning
    src_sys, src_comp, tgt_sys, tgt_comp = _ids(args)
    conn = mavutil.mavlink_connection(args.connection, source_system=src_sys, source_component=src_comp,
                                      dialect="ardupilotmega", autoreconnect=True)
    try:
        mav = mavutil.mavlink

        def heartbeat(signed_only: bool):
            deadline = time.monotonic() + args.timeout
            while time.monotonic() < deadline:
                conn.mav.heartbeat_send(mav.MAV_TYPE_ONBOARD_CONTROLLER, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
                m = conn.recv_match(type="HEARTBEAT", blocking=True, timeout=0.5)
                if m is None or m.get_srcSystem() != tgt_sys or m.get_srcComponent() != tgt_comp:
                    continue
                if not signed_only or m.get_signed():
                    return m
            return None

        if heartbeat(signed_only=False) is None:
            print(f"error: no HEARTBEAT from {tgt_sys}/{tgt_comp} on {args.connection} within {args.timeout:g} s",
                  file=sys.stderr)
            return 1
        # from here on we sign, and accept only frames that verify with the key
        signing = LinkSigning(key, required=True)
        signing.attach(conn)
        conn.mav.setup_signing_send(tgt_sys, tgt_comp, list(key.key), signing_timestamp(time.time()))
        print(f"SETUP_SIGNING sent to {tgt_sys}/{tgt_comp}")
        if heartbeat(signed_only=True) is None:
            print(f"error: no HEARTBEAT signed with this key within {args.timeout:g} s: the autopilot did not "
                  f"take it (PX4 v1.15 has no signing; an ArduPilot that has another key takes a new one only "
                  f"on USB / SERIAL0)", file=sys.stderr)
            return 1
        print(f"the autopilot {tgt_sys}/{tgt_comp} signs with this key "
              f"({signing.counters['signing: good']} verified frames)")
        return 0
    finally:
        conn.close()


def register(subparsers) -> None:
    p = subparsers.add_parser("signing", help="MAVLink 2 signing: make a key file, give the key to the autopilot")
    sub = p.add_subparsers(dest="signing_command", required=True)
    s = sub.add_parser("setup", help="create the key file if absent; with --connection, send SETUP_SIGNING "
                                     "and check the autopilot signs with it")
    s.add_argument("--key-file", required=True, help="key file (created 0600 with a random key if absent)")
    s.add_argument("--connection", help="pymavlink connection to the autopilot, e.g. /dev/ttyACM0,115200 or "
                                        "tcp:127.0.0.1:5762")
    s.add_argument("--config", help="TOML configuration: our ids and the autopilot's (mavlink.*)")
    s.add_argument("--target-system", type=int, default=1, help="without --config (default 1)")
    s.add_argument("--target-component", type=int, default=1, help="without --config (default 1)")
    s.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for each HEARTBEAT (default 10)")
    s.set_defaults(func=cmd_setup)
