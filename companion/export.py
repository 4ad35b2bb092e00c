"""``companion export LOG``: a field log's raw streams and its solutions in the formats other tools read.

* ``--ubx PATH``: the receiver's byte stream as it arrived: ``ubx`` records (a receiver on the
  companion's own serial port) and the payloads of the autopilot's SERIAL_CONTROL replies of one
  GPS port (a receiver on the autopilot's GPS port, through the tunnel), in log order -- for
  RTKLIB's ``convbin`` / ``rnx2rtkp`` or u-center.
* ``--rtcm PATH``: the correction bytes as received (NTRIP, radio, MQTT, file).
* ``--kml PATH`` / ``--gpx PATH`` / ``--csv PATH`` / ``--pos PATH``: the logged solutions (IMU
  position) as Google Earth track, GPX track, a table with time, position, sigmas, status and
  whether it was injected, or RTKLIB's solution file (rtkplot, pos2kml; Q 5, the NED sigmas).
  ``--injected-only`` keeps the solutions that reached the autopilot.

No replay is needed: the solutions are the ones the service computed and logged.
"""
from __future__ import annotations

import csv
import math
import os
import sys
from pathlib import Path

from .io.track_export import gps_to_utc_iso, write_solution_files

# numpy, pymavlink and the field log are imported where they are used: `companion --help` and
# `companion config check` must not pay for them (tests/test_packaging.py)
SECONDS_PER_WEEK = 604800.0
SERIAL_CONTROL_GPS_DEVICES = ("GPS1", "GPS2")


def _serial_control_parser():
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink.dialects.v20 import ardupilotmega as m
    parser = m.MAVLink(None)
    parser.robust_parsing = True
    return m, parser


def export_field_log(log, *, ubx=None, rtcm=None, kml=None, gpx=None, csv_path=None, pos=None,
                     injected_only: bool = False, leap_seconds: int | None = None,
                     device: str = "auto") -> dict:
    """Write the requested outputs; returns counts of what went into each.

    ``device``: whose SERIAL_CONTROL replies are the receiver's bytes: 'GPS1', 'GPS2' or 'auto'
    (the first GPS port that replies).  Replies of any other device (a ground station's shell
    session on the same link) would corrupt the UBX stream: skipped and counted."""
    from .io.fieldlog import read_field_log
    from .nav.earth import ecef_to_geodetic
    from .log_records import decode_solution
    counts = {"records": 0, "ubx_bytes": 0, "serial_control_replies": 0, "serial_control_other_devices": 0,
              "serial_control_device": None, "rtcm_bytes": 0, "solutions": 0, "solutions_skipped": 0}
    if device not in ("auto", *SERIAL_CONTROL_GPS_DEVICES):
        raise ValueError(f"device: auto, GPS1 or GPS2; got {device!r}")
    want_dev = None
    f_ubx = open(ubx, "wb") if ubx else None
    f_rtcm = open(rtcm, "wb") if rtcm else None
    m = parser = None
    sols = []
    try:
        for rec in read_field_log(log):
            counts["records"] += 1
            if rec.kind == "ubx" and f_ubx:
                f_ubx.write(rec.payload)
                counts["ubx_bytes"] += len(rec.payload)
            elif rec.kind == "rtcm" and f_rtcm:
                f_rtcm.write(rec.payload)
                counts["rtcm_bytes"] += len(rec.payload)
            elif rec.kind == "mavlink" and f_ubx:
                if parser is None:
                    m, parser = _serial_control_parser()
                    gps_ids = {getattr(m, f"SERIAL_CONTROL_DEV_{d}"): d for d in SERIAL_CONTROL_GPS_DEVICES}
                    if device != "auto":
                        want_dev = getattr(m, f"SERIAL_CONTROL_DEV_{device}")
                for msg in parser.parse_buffer(rec.payload) or ():
                    if msg.get_type() == "SERIAL_CONTROL" and msg.flags & m.SERIAL_CONTROL_FLAG_REPLY \
                            and msg.count:
                        if want_dev is None and msg.device in gps_ids:
                            want_dev = msg.device
                        if msg.device != want_dev:
                            counts["serial_control_other_devices"] += 1
                            continue
                        counts["serial_control_device"] = gps_ids[want_dev]
                        data = bytes(msg.data[:msg.count])
                        f_ubx.write(data)
                        counts["ubx_bytes"] += len(data)
                        counts["serial_control_replies"] += 1
            elif rec.kind == "solution" and (kml or gpx or csv_path or pos):
                try:
                    sol = decode_solution(rec.payload)
                except Exception:
                    counts["solutions_skipped"] += 1
                    continue
                if sol.status == "init" or (injected_only and not sol.extras.get("inject")):
                    counts["solutions_skipped"] += 1
                    continue
                if not all(math.isfinite(float(x)) for x in sol.r_e):
                    counts["solutions_skipped"] += 1
                    continue
                sols.append(sol)
    finally:
        for f in (f_ubx, f_rtcm):
            if f:
                f.close()
    counts["solutions"] = len(sols)
    rows = []
    for s in sols:
        lat, lon, h = ecef_to_geodetic(s.r_e)
        rows.append((s, math.degrees(lat), math.degrees(lon), h))
    if csv_path:
        _write_csv(csv_path, rows, leap_seconds)
    if kml or gpx or pos:
        write_solution_files(sols, name=f"companion export: {Path(str(log)).name}", pos=pos, kml=kml, gpx=gpx,
                             inputs=[str(log)], leap_seconds=leap_seconds,
                             options={"pos": "IMU (the fused solution, not the antenna)",
                                      "solutions": "injected only" if injected_only else "all but init"})
    return counts


def _write_csv(path, rows, leap_seconds: int | None) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["t_gps_s", "gps_week", "tow_s", "utc", "lat_deg", "lon_deg", "h_ellipsoid_m", "sigma_n_m",
                    "sigma_e_m", "sigma_d_m", "v_e_x_mps", "v_e_y_mps", "v_e_z_mps", "status", "mode", "injected",
                    "reset_counter"])
        for s, lat, lon, h in rows:
            week = int(s.t_gps // SECONDS_PER_WEEK)
            sig = [float(x) for x in s.sigma_r_n_m]
            w.writerow([f"{s.t_gps:.4f}", week, f"{s.t_gps - week * SECONDS_PER_WEEK:.4f}",
                        gps_to_utc_iso(s.t_gps, leap_seconds), f"{lat:.9f}", f"{lon:.9f}", f"{h:.4f}",
                        *(f"{x:.4f}" for x in sig), *(f"{float(x):.4f}" for x in s.v_e), s.status,
                        s.extras.get("mode", ""), int(bool(s.extras.get("inject"))), s.reset_counter])


def run_export_cli(args) -> int:
    if not (args.ubx or args.rtcm or args.kml or args.gpx or args.csv or args.pos):
        print("companion export: nothing to do: give --ubx, --rtcm, --kml, --gpx, --csv and/or --pos",
              file=sys.stderr)
        return 2
    try:
        counts = export_field_log(args.log, ubx=args.ubx, rtcm=args.rtcm, kml=args.kml, gpx=args.gpx,
                                  csv_path=args.csv, pos=args.pos, injected_only=args.injected_only,
                                  leap_seconds=args.leap_seconds, device=args.device)
    except (OSError, ValueError) as exc:
        print(f"companion export: error: {exc}", file=sys.stderr)
        return 2
    if counts["records"] == 0:
        print(f"companion export: error: no field-log records in {args.log} (a field log is a *.cflog file, "
              "a directory of them or their common stem)", file=sys.stderr)
        return 2
    parts = [f"{counts['records']} records"]
    if args.ubx:
        via = (f" ({counts['serial_control_replies']} SERIAL_CONTROL replies of {counts['serial_control_device']})"
               if counts["serial_control_replies"] else "")
        other = (f", {counts['serial_control_other_devices']} replies of other devices skipped"
                 if counts["serial_control_other_devices"] else "")
        parts.append(f"{counts['ubx_bytes']} UBX bytes{via} -> {args.ubx}{other}")
    if args.rtcm:
        parts.append(f"{counts['rtcm_bytes']} RTCM bytes -> {args.rtcm}")
    if args.kml or args.gpx or args.csv or args.pos:
        parts.append(f"{counts['solutions']} solutions -> "
                     + ", ".join(p for p in (args.kml, args.gpx, args.csv, args.pos) if p))
    print("companion export: " + "; ".join(parts))
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("export",
                              help="a field log's raw UBX/RTCM streams and its solutions (KML, GPX, CSV, .pos)")
    p.add_argument("log", help="field log file, rotated-log directory or stem")
    p.add_argument("--ubx", help="write the receiver's UBX bytes here (for convbin, u-center)")
    p.add_argument("--device", choices=["auto", *SERIAL_CONTROL_GPS_DEVICES], default="auto",
                   help="--ubx through the autopilot: whose SERIAL_CONTROL replies (default: the first GPS port "
                        "that replies; other devices' replies, e.g. a ground station's shell, are skipped)")
    p.add_argument("--rtcm", help="write the correction bytes here (RTCM3)")
    p.add_argument("--kml", help="write the solutions as a KML track")
    p.add_argument("--gpx", help="write the solutions as a GPX track")
    p.add_argument("--csv", help="write the solutions as CSV")
    p.add_argument("--pos", help="write the solutions in RTKLIB's .pos format (rtkplot, pos2kml)")
    p.add_argument("--injected-only", action="store_true", help="only the solutions sent to the autopilot")
    p.add_argument("--leap-seconds", type=int, default=None,
                   help="GPS - UTC for the UTC times (default: the leap-second table, 18 since 2017)")
    p.set_defaults(func=lambda a: run_export_cli(a))
