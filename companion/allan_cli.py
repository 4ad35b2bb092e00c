"""`companion allan LOG`: Allan deviation of a static IMU recording and the [filter] noise block.

LOG may be
* a CSV (optional header; columns t_s, gx, gy, gz [rad/s], ax, ay, az [m/s^2]) or an NPZ with
  arrays ``t`` (n,), ``gyro`` (n,3), ``accel`` (n,3) (or one (n,7) array ``data``);
* a MAVLink telemetry log (``.tlog``) or an ArduPilot dataflash log (``.bin``, IMU messages;
  untested against a real flight log), read with pymavlink: HIGHRES_IMU (SI units, ``id``),
  RAW_IMU (ArduPilot scaling: mG and mrad/s, ``id``), SCALED_IMU2 (id 1) and SCALED_IMU3 (id 2)
  (mG, mrad/s);
* a companion field log (directory or ``.cflog``): records of kind 'mavlink' parsed as above.

The sample times are the autopilot's (time_usec or time_boot_ms); the Allan analysis assumes
uniform sampling at the median interval (the fraction of irregular intervals is reported).
"""
from __future__ import annotations

import json
from pathlib import Path

# numpy is imported inside the functions: `companion` builds its parser from every subcommand's
# register(), and `companion config check` must not pay for numpy.

G0 = 9.80665
MG_TO_MPS2 = G0 * 1e-3
MRAD_TO_RAD = 1e-3


def _imu_row(msg):
    """(imu_id, t_s, gyro(3), accel(3)) of a MAVLink IMU message, or None."""
    typ = msg.get_type()
    if typ == "HIGHRES_IMU":
        return (int(getattr(msg, "id", 0) or 0), msg.time_usec * 1e-6,
                (msg.xgyro, msg.ygyro, msg.zgyro), (msg.xacc, msg.yacc, msg.zacc))
    if typ in ("RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3"):
        if typ == "RAW_IMU":
            imu_id, t = int(getattr(msg, "id", 0) or 0), msg.time_usec * 1e-6
        else:
            imu_id = {"SCALED_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}[typ]
            t = msg.time_boot_ms * 1e-3
        return (imu_id, t, (msg.xgyro * MRAD_TO_RAD, msg.ygyro * MRAD_TO_RAD, msg.zgyro * MRAD_TO_RAD),
                (msg.xacc * MG_TO_MPS2, msg.yacc * MG_TO_MPS2, msg.zacc * MG_TO_MPS2))
    if typ == "IMU":   # dataflash
        return (int(getattr(msg, "I", 0) or 0), msg.TimeUS * 1e-6,
                (msg.GyrX, msg.GyrY, msg.GyrZ), (msg.AccX, msg.AccY, msg.AccZ))
    return None


IMU_TYPES = ["HIGHRES_IMU", "RAW_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "IMU"]


def _rows_from_messages(msgs, imu_id):
    rows = {}
    for m in msgs:
        r = _imu_row(m)
        if r is not None:
            rows.setdefault(r[0], []).append(r[1:])
    return rows


def _select(rows: dict, imu_id):
    import numpy as np
    if not rows:
        raise ValueError("no IMU messages (HIGHRES_IMU, RAW_IMU, SCALED_IMU2/3) in the log")
    if imu_id is None:
        imu_id = min(rows)
    if imu_id not in rows:
        raise ValueError(f"no IMU with id {imu_id}; ids present: {sorted(rows)}")
    r = rows[imu_id]
    t = np.array([x[0] for x in r])
    g = np.array([x[1] for x in r], float)
    a = np.array([x[2] for x in r], float)
    o = np.argsort(t, kind="stable")
    t, g, a = t[o], g[o], a[o]
    keep = np.concatenate([[True], np.diff(t) > 0])      # drop duplicates (several streams)
    return imu_id, t[keep], g[keep], a[keep]


def load_imu_log(path: str, imu_id: int | None = None):
    """(imu_id, t_s, gyro (n,3) rad/s, accel (n,3) m/s^2) from any supported LOG."""
    import numpy as np
    p = Path(path)
    suf = p.suffix.lower()
    if suf == ".npz":
        z = np.load(p)
        if "data" in z:
            d = z["data"]
            return imu_id or 0, d[:, 0], d[:, 1:4], d[:, 4:7]
        return imu_id or 0, z["t"], z["gyro"], z["accel"]
    if suf in (".csv", ".txt"):
        with open(p) as f:
            first = f.readline()
        skip = 0 if _is_numeric_row(first) else 1
        d = np.loadtxt(p, delimiter=",", skiprows=skip, ndmin=2)
        return imu_id or 0, d[:, 0], d[:, 1:4], d[:, 4:7]
    if p.is_dir() or suf == ".cflog":
        return _select(_rows_from_messages(_field_log_messages(p), imu_id), imu_id)
    mavutil = mavlink2_mavutil()
    conn = mavutil.mavlink_connection(str(p), robust_parsing=True) if suf != ".bin" \
        else mavutil.mavlink_connection(str(p))

    def it():
        while True:
            m = conn.recv_match(type=IMU_TYPES)
            if m is None:
                return
            yield m
    return _select(_rows_from_messages(it(), imu_id), imu_id)


def mavlink2_mavutil():
    """pymavlink's mavutil with the MAVLink 2 ardupilotmega dialect (it also parses MAVLink 1
    frames).  mavutil picks v1 unless MAVLINK20 is set; v1 lacks the ``id`` extension fields."""
    import os
    os.environ.setdefault("MAVLINK20", "1")
    from pymavlink import mavutil
    if getattr(mavutil, "current_dialect", None) != "ardupilotmega" or mavutil.mavlink.WIRE_PROTOCOL_VERSION != "2.0":
        mavutil.set_dialect("ardupilotmega")
    return mavutil


def _is_numeric_row(line: str) -> bool:
    try:
        [float(x) for x in line.strip().split(",") if x.strip()]
        return True
    except ValueError:
        return False


def _field_log_messages(path):
    from pymavlink.dialects.v20 import ardupilotmega as mav

    from .io.fieldlog import read_field_log
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    for rec in read_field_log(path):
        if rec.kind != "mavlink":
            continue
        try:
            msgs = parser.parse_buffer(rec.payload) or []
        except Exception:   # a corrupt record: skip it, the parser resynchronises
            continue
        yield from msgs


def plot_allan(res: dict, path: str, title: str = "") -> None:
    import numpy as np

    from .extras import pyplot
    plt = pyplot("companion allan --plot")

    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for ax, name, unit in ((axes[0], "gyro", "rad/s"), (axes[1], "accel", "m/s^2")):
        r = res[name]
        tau = r["tau_s"]
        for j, lab in enumerate("xyz"):
            line, = ax.loglog(tau, r["adev"][:, j], ".", label=f"{lab}")
            f = r["fits"][j]
            ax.loglog(tau, f.model(tau), "-", color=line.get_color(), alpha=0.6,
                      label=f"{lab} fit N={f.N:.3g} B={f.B:.3g} K={f.K:.3g}")
            ax.loglog(tau, f.N / np.sqrt(tau), ":", color=line.get_color(), alpha=0.4)
            ax.loglog(tau, f.K * np.sqrt(tau / 3.0), ":", color=line.get_color(), alpha=0.4)
            ax.axhline(0.664 * f.B, color=line.get_color(), ls=":", alpha=0.4)
        ax.set_xlabel("cluster time tau [s]")
        ax.set_ylabel(f"Allan deviation [{unit}]")
        ax.set_title(f"{name} {title}")
        ax.set_ylim(bottom=np.nanmin(r["adev"]) / 3)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def run(args) -> int:
    from .nav.allan import analyse_imu, format_noise_block
    if args.plot:
        from .extras import pyplot
        pyplot("companion allan --plot")          # a missing [plot] extra fails now, not after the analysis
    imu_id, t, g, a = load_imu_log(args.log, args.imu_id)
    if len(t) < 100:
        raise SystemExit(f"only {len(t)} IMU samples: too few for an Allan analysis")
    res = analyse_imu(t, g, a)
    print(f"IMU {imu_id}: {res['samples']} samples at {res['fs_hz']:.2f} Hz over {res['duration_s'] / 60:.1f} min"
          f" ({100 * res['irregular_fraction']:.2f} % irregular intervals)")
    for name, un, ub, uk in (("gyro", "rad/sqrt(s)", "rad/s", "rad/s/sqrt(s)"),
                             ("accel", "m/s/sqrt(s)", "m/s^2", "m/s^2/sqrt(s)")):
        for lab, f in zip("xyz", res[name]["fits"]):
            print(f"  {name} {lab}: N {f.N:.4g} {un}  B {f.B:.4g} {ub} (min at {f.tau_min_s:.0f} s)  K {f.K:.4g} {uk}")
    print(format_noise_block(res["noise"]))
    if args.json:
        out = {"imu_id": imu_id, "fs_hz": res["fs_hz"], "duration_s": res["duration_s"], "samples": res["samples"],
               "noise": res["noise"]}
        for name in ("gyro", "accel"):
            out[name] = {"tau_s": res[name]["tau_s"].tolist(), "adev": res[name]["adev"].tolist(),
                         "fits": [f.as_dict() for f in res[name]["fits"]]}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=2))
        print(f"wrote {args.json}")
    if args.plot:
        Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
        plot_allan(res, args.plot, f"(IMU {imu_id})")
        print(f"wrote {args.plot}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("allan", help="Allan deviation of a static IMU recording; prints the [filter] noise block")
    p.add_argument("log", help="CSV/NPZ (t, gyro xyz, accel xyz), MAVLink .tlog / .bin, or a field log")
    p.add_argument("--imu-id", type=int, default=None, help="which IMU (HIGHRES_IMU/RAW_IMU id; "
                                                            "SCALED_IMU2 = 1, SCALED_IMU3 = 2); default: lowest")
    p.add_argument("--plot", help="write a PNG of the curves with the fitted lines here")
    p.add_argument("--json", help="write the curves and fits as JSON here")
    p.set_defaults(func=run)

