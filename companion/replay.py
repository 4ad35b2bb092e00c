"""Replay a field log (or a MAVLink telemetry log) through the same :class:`NavPipeline` as the
live service, as fast as the CPU allows, and compare with the solutions the service logged.

Field logs (``*.cflog``, a file, a rotated directory or a stem): the configuration comes from the
log's ``event`` record (``--config`` overrides it, and then equality is not expected).  Every
``mavlink``/``ubx``/``rtcm`` record is fed in order; the solutions produced are compared, in
order, with the logged ``solution`` records by their binary encoding (every float64 bit, status,
injection flag, reset counter, IMU time stamp): the report counts identical and differing
solutions and names the first difference.

MAVLink telemetry logs (``.tlog``: 8-byte big-endian UNIX-microsecond time + one MAVLink frame,
as written by MAVProxy / Mission Planner / QGroundControl): every frame is fed as a ``mavlink``
record (receive time from the tlog stamp).  What works depends on what was logged: the IMU
(HIGHRES_IMU / RAW_IMU at whatever rate the GCS requested -- typically only a few Hz), SYSTEM_TIME,
ATTITUDE, GPS_RAW_INT (loose coupling: the pipeline falls back to it when no raw observations
arrive) and SERIAL_CONTROL replies (raw UBX, if a GCS was tunnelling the receiver).  There is no
RTCM in a tlog (GPS_RTCM_DATA *to* the vehicle is not fed back) and no reference solution, so
the comparison is empty.  A tlog recorded by a GCS usually has the IMU at 2-10 Hz: the filter
runs, but it is not the navigation the service would do at 200 Hz.
"""
from __future__ import annotations

import json
import logging
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .pipeline import NavPipeline, encode_solution

log = logging.getLogger(__name__)


@dataclass
class ReplayResult:
    solutions: list = field(default_factory=list)        # NavSolution produced by the replay
    logged: list = field(default_factory=list)           # bytes of the logged solution records
    produced: list = field(default_factory=list)         # bytes of the replayed solutions
    records: int = 0
    elapsed_s: float = 0.0
    config_from: str = ""
    config_error: str = ""          # the log's configuration could not be read (e.g. a newer version's)
    log_stats: dict = field(default_factory=dict)
    pipeline_health: dict = field(default_factory=dict)

    def comparison(self) -> dict:
        n = min(len(self.logged), len(self.produced))
        same = sum(1 for a, b in zip(self.logged, self.produced) if a == b)
        first = next((i for i, (a, b) in enumerate(zip(self.logged, self.produced)) if a != b), None)
        return {"logged_solutions": len(self.logged), "replayed_solutions": len(self.produced),
                "identical": same, "differing": n - same + abs(len(self.logged) - len(self.produced)),
                "first_difference_index": first,
                "bit_for_bit": bool(self.logged) and same == len(self.logged) == len(self.produced)}


class _Progress:
    def __init__(self, total: int, enabled: bool):
        self.total = max(total, 1)
        self.enabled = enabled and sys.stderr.isatty() or enabled == "force"
        self.last = 0.0
        self.t0 = time.monotonic()

    def update(self, done: int, final: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not final and now - self.last < 0.2:
            return
        self.last = now
        frac = min(1.0, done / self.total)
        bar = "#" * int(30 * frac) + "." * (30 - int(30 * frac))
        sys.stderr.write(f"\r[{bar}] {100 * frac:5.1f} %  {now - self.t0:6.1f} s")
        if final:
            sys.stderr.write("\n")
        sys.stderr.flush()


def _config_from_event(payload: bytes):
    from .config import loads_config
    obj = json.loads(payload.decode())
    if obj.get("event") == "config":
        return loads_config(obj["toml"], "<field log>")
    return None


def replay_field_log(path, config=None, progress: bool = False) -> ReplayResult:
    from .io.fieldlog import FieldLogReader
    reader = FieldLogReader(path)
    total = sum(f.stat().st_size for f in reader.files)
    res = ReplayResult(config_from="--config" if config is not None else "")
    pipe = NavPipeline(config) if config is not None else None
    prog = _Progress(total, progress)
    done_files = 0
    cur_file = None
    t0 = time.perf_counter()
    for rec in reader:
        res.records += 1
        if rec.file != cur_file:
            if cur_file is not None:
                done_files += Path(cur_file).stat().st_size
            cur_file = rec.file
        prog.update(done_files + rec.offset)
        k = rec.kind
        if k == "solution":
            res.logged.append(bytes(rec.payload))
            continue
        if k == "event":
            if pipe is None:
                try:
                    cfg = _config_from_event(rec.payload)
                except Exception as exc:
                    log.warning("unreadable event record: %r", exc)
                    res.config_error = res.config_error or str(exc)
                    cfg = None
                if cfg is not None:
                    pipe = NavPipeline(cfg)
                    res.config_from = "field log"
            continue
        if pipe is None:
            continue
        for sol in pipe.feed(k, rec.t_mono_ns, rec.payload):
            res.solutions.append(sol)
            res.produced.append(encode_solution(sol))
    prog.update(total, final=True)
    res.elapsed_s = time.perf_counter() - t0
    st = reader.stats
    res.log_stats = {"files": st.files, "records": st.records, "crc_errors": st.crc_errors,
                     "bad_records": st.bad_records, "truncated_tails": len(st.truncated_tails)}
    if pipe is not None:
        res.pipeline_health = pipe.health()
    return res


def replay_tlog(path, config=None, progress: bool = False) -> ReplayResult:
    from pymavlink import mavutil
    from .config import Config
    cfg = config or Config()
    pipe = NavPipeline(cfg)
    res = ReplayResult(config_from="--config" if config is not None else "defaults")
    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega", robust_parsing=True)
    total = os.path.getsize(path)
    prog = _Progress(total, progress)
    t0 = time.perf_counter()
    while True:
        msg = conn.recv_msg()
        if msg is None:
            break
        if msg.get_type() == "BAD_DATA":
            continue
        res.records += 1
        prog.update(getattr(conn, "offset", 0) or 0)
        t_ns = int(getattr(msg, "_timestamp", 0.0) * 1e9)
        for sol in pipe.feed("mavlink", t_ns, bytes(msg.get_msgbuf())):
            res.solutions.append(sol)
            res.produced.append(encode_solution(sol))
    prog.update(total, final=True)
    res.elapsed_s = time.perf_counter() - t0
    res.pipeline_health = pipe.health()
    return res


def replay(path, config=None, progress: bool = False) -> ReplayResult:
    p = str(path)
    if p.endswith(".tlog") or p.endswith(".mavlink"):
        return replay_tlog(path, config, progress)
    return replay_field_log(path, config, progress)


def _sol_json(sol) -> dict:
    def f(a):
        return [float(x) if math.isfinite(float(x)) else None for x in np.asarray(a, float)]
    return {"t_gps": sol.t_gps, "r_e": f(sol.r_e), "status": sol.status, "sigma_r_ned_m": f(sol.sigma_r_n_m),
            "sigma_v_ned_mps": f(sol.sigma_v_n_mps), "inject": sol.extras.get("inject"),
            "reset_counter": sol.reset_counter}


def plot_replay(res: ReplayResult, path: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from .nav.earth import ecef_to_ned
    sols = [s for s in res.solutions if np.all(np.isfinite(s.r_e))]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 5))
    if sols:
        ref = sols[0].r_e
        ned = np.array([ecef_to_ned(s.r_e, ref) for s in sols])
        inj = np.array([bool(s.extras.get("inject")) for s in sols])
        a1.plot(ned[:, 1], ned[:, 0], "-", lw=0.8, color="0.6", label="all")
        a1.plot(ned[inj, 1], ned[inj, 0], ".", ms=1.5, label="injected")
        a1.set_xlabel("east [m]")
        a1.set_ylabel("north [m]")
        a1.axis("equal")
        a1.legend()
        t = np.array([s.t_gps for s in sols]) - sols[0].t_gps
        sig = np.array([s.sigma_r_n_m for s in sols])
        for i, n in enumerate("NED"):
            a2.semilogy(t, sig[:, i], label=f"sigma {n}")
        a2.set_xlabel("time [s]")
        a2.set_ylabel("1-sigma position [m]")
        a2.legend()
    c = res.comparison()
    fig.suptitle(f"replay: {len(res.solutions)} solutions; bit-for-bit {c['identical']}/{c['logged_solutions']}")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_replay_cli(args) -> int:
    cfg = None
    if getattr(args, "config", None):
        from .config import load_config
        cfg = load_config(args.config)
    if not Path(args.log).exists() and not list(Path(args.log).parent.glob(Path(args.log).name + "*")):
        print(f"error: {args.log}: no such field log, directory or .tlog", file=sys.stderr)
        return 2
    res = replay(args.log, cfg, progress=not getattr(args, "no_progress", False))
    c = res.comparison()
    rate = res.records / res.elapsed_s if res.elapsed_s > 0 else float("nan")
    print(f"replayed {res.records} records in {res.elapsed_s:.2f} s ({rate:,.0f} records/s); "
          f"config from {res.config_from or 'nowhere (no config event: nothing replayed)'}")
    print(f"solutions: {c['replayed_solutions']} replayed, {c['logged_solutions']} logged; "
          f"identical {c['identical']}, differing {c['differing']}"
          + (f", first difference at #{c['first_difference_index']}" if c["first_difference_index"] is not None else "")
          + ("  -> BIT FOR BIT" if c["bit_for_bit"] else ""))
    if res.solutions:
        last = res.solutions[-1]
        print(f"last solution: status {last.status}, sigma NED {np.round(last.sigma_r_n_m, 3).tolist()} m")
    if args.json:
        obj = {"log": str(args.log), "records": res.records, "elapsed_s": res.elapsed_s, "comparison": c,
               "log_stats": res.log_stats, "pipeline": res.pipeline_health,
               "solutions": [_sol_json(s) for s in res.solutions]}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(obj, default=str))
        print(f"wrote {args.json}")
    if args.plot:
        plot_replay(res, args.plot)
        print(f"wrote {args.plot}")
    if res.records == 0:
        print(f"error: {args.log}: no records found (a field log is a *.cflog file or a directory of them)",
              file=sys.stderr)
        return 2
    if not res.config_from and res.config_error:
        print(f"error: the field log's configuration cannot be read by this version ({res.config_error}); "
              f"replay with --config FILE", file=sys.stderr)
        return 2
    if res.logged and not c["bit_for_bit"] and res.config_from == "field log":
        return 1
    return 0


__all__ = ["replay", "replay_field_log", "replay_tlog", "ReplayResult", "plot_replay", "run_replay_cli"]
