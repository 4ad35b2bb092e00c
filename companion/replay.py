"""Replay a field log (or a MAVLink telemetry log) through the same :class:`NavPipeline` as the
live service, as fast as the CPU allows, and compare with the solutions the service logged.

Field logs (``*.cflog``, a file, a rotated directory or a stem): the configuration comes from the
log's ``event`` record (``--config`` overrides it, and then equality is not expected).  Every
``mavlink``/``ubx``/``rtcm`` record is fed in order; the solutions produced are compared, in
order, with the logged ``solution`` records by their binary encoding (every float64 bit, status,
injection flag, reset counter, IMU time stamp, protection level; a version-1 record of an older
log on the fields it has): the report counts identical and differing solutions and names the
first difference.  The per aid source status records (kind ``aid_status``, outputs like the
solutions) are recomputed at the logged configuration's rate and compared with the logged ones
when the log has them; ``--plot PATH`` writes a second figure ``<stem>.aid<suffix>`` from the
recomputed ones (innovations and test ratios per source, the HPL against sigma_h), so an old log
without the records gets it too.

MAVLink telemetry logs (``.tlog``: 8-byte big-endian UNIX-microsecond time + one MAVLink frame,
as written by MAVProxy / Mission Planner / QGroundControl): every frame is fed as a ``mavlink``
record (receive time from the tlog stamp).  What works depends on what was logged: the IMU
(HIGHRES_IMU / RAW_IMU at whatever rate the GCS requested -- typically only a few Hz), SYSTEM_TIME,
ATTITUDE, GPS_RAW_INT (loose coupling: the pipeline falls back to it when no raw observations
arrive) and SERIAL_CONTROL replies (raw UBX, if a GCS was tunnelling the receiver).  There is no
RTCM in a tlog (GPS_RTCM_DATA *to* the vehicle is not fed back) and no reference solution, so
the comparison is empty.  A tlog recorded by a GCS usually has the IMU at 1-10 Hz: below
:data:`IMU_RATE_NEEDED_HZ` the replay refuses (names the rate found and the rate needed, exit
status 3) rather than return nothing in silence.

ArduPilot DataFlash logs (``.BIN``, recognised by their first bytes): the records become the
MAVLink messages the service would have received (:mod:`companion.io.dataflash`) and go through
the same pipeline.  Without ``--config`` the configuration is the default one adapted to what the
log holds (:func:`dataflash_config`: loose coupling on the GPS fixes, the IMU rate found, the lever
arm from ``GPS_POS``/``INS_POS``, SITL's simulated gyro drift).  A log with its u-blox's raw
observations (``GPS_RAW_DATA = 1``: ``GRXH``/``GRXS``) and ``--nav`` RINEX ephemerides is tightly
coupled instead: the rebuilt RXM-RAWX frames (:mod:`companion.io.dataflash_raw`) are the
receiver's stream at their ``TimeUS``; ``--base`` adds a base station's RINEX observations.
When the log has the simulator's truth (``SIM``) the trajectory is scored against it beside the autopilot EKF's ``POS`` over the
same span (:mod:`companion.post_report`).  With ``smooth`` (``--smooth``) the solutions are the
RTS-smoothed ones (:mod:`companion.nav.smoother`) and the forward pass is scored beside them.
"""
from __future__ import annotations

import heapq
import json
import logging
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .aid_status_record import KIND as AID_KIND
from .aid_status_record import AidStatusPacer
from .nav.smoother import SmootherRecorder
from .pipeline import NavPipeline
from .replay_raw import logged_raw, raw_records
from .log_records import encode_solution, solution_records_equal

log = logging.getLogger(__name__)

# The pipeline integrates each IMU sample as rate x interval and drops any interval of 0.1 s or
# more (ImuDecoder.max_dt_s, NavEngine.process_imu): 10 Hz is the hard floor, twice that leaves
# room for jitter and an odd lost sample.  The live service streams 200 Hz.
IMU_RATE_NEEDED_HZ = 20.0
EXIT_NO_SOLUTION = 3            # the input cannot give a solution (reason on stderr)
_IMU_TYPES = ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3", "SCALED_IMU")


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
    kind: str = "field log"         # 'field log', 'tlog', 'dataflash' or 'ulog'
    imu_check: dict = field(default_factory=dict)   # stream, rate found, rate needed
    refusal: str = ""               # why this log cannot give a solution (nothing was run)
    notes: list = field(default_factory=list)       # what was assumed or adapted, for the report
    truth_score: dict = field(default_factory=dict)  # against the log's truth (SIM), if any
    forward_score: dict = field(default_factory=dict)  # with smoothing: the forward pass's truth_score
    time_base: dict = field(default_factory=dict)   # DataFlash: boot -> GPS time
    tracks: dict = field(default_factory=dict)      # name -> (N, 3) lat deg, lon deg, alt m (plot)
    # per aid source status (companion.aid_status_record): recomputed by the replay (objects) and
    # as logged (payload bytes; none in a log older than the record kind)
    aid_status: list = field(default_factory=list)
    aid_status_produced: list = field(default_factory=list)
    aid_status_logged: list = field(default_factory=list)

    def comparison(self) -> dict:
        n = min(len(self.logged), len(self.produced))
        eq = [solution_records_equal(a, b) for a, b in zip(self.logged, self.produced)]
        same = sum(eq)
        first = next((i for i, e in enumerate(eq) if not e), None)
        out = {"logged_solutions": len(self.logged), "replayed_solutions": len(self.produced),
               "identical": same, "differing": n - same + abs(len(self.logged) - len(self.produced)),
               "first_difference_index": first,
               "bit_for_bit": bool(self.logged) and same == len(self.logged) == len(self.produced)}
        if self.aid_status_logged:
            la, pa = self.aid_status_logged, self.aid_status_produced
            out["aid_status"] = {"logged": len(la), "replayed": len(pa),
                                 "identical": sum(1 for a, b in zip(la, pa) if a == b)}
        return out


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


def _config_from_event(payload: bytes, antennas_path: str | None = None, notes: list | None = None):
    """The configuration of a 'config' / 'config_change' record (None for another event), its
    antenna calibration file found here (:func:`companion.nav.rtk_antennas.for_replay`; what it
    could not find goes to ``notes``)."""
    from .config import loads_config
    from .nav.rtk_antennas import for_replay
    obj = json.loads(payload.decode())
    if obj.get("event") not in ("config", "config_change"):
        return None
    cfg, note = for_replay(loads_config(obj["toml"], "<field log>"), obj.get("rtk_antennas_sha256"), antennas_path)
    if note and notes is not None and note not in notes:
        notes.append(note)
    return cfg


def replay_field_log(path, config=None, progress: bool = False, smooth: bool = False,
                     antennas_path: str | None = None) -> ReplayResult:
    from .io.fieldlog import FieldLogReader
    reader = FieldLogReader(path)
    total = sum(f.stat().st_size for f in reader.files)
    res = ReplayResult(config_from="--config" if config is not None else "")
    pipe = NavPipeline(config) if config is not None else None
    pacer = recorder = None
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
        if k == AID_KIND:                   # an output of the service, like 'solution'
            res.aid_status_logged.append(bytes(rec.payload))
            continue
        if k == "event":
            if pipe is not None and config is None and b'"config_change"' in bytes(rec.payload):
                pipe.apply_settings(_config_from_event(rec.payload, antennas_path))   # a ground station set one
                continue
            if pipe is None:
                try:
                    cfg = _config_from_event(rec.payload, antennas_path, res.notes)
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
        if pacer is None:
            pacer = AidStatusPacer(getattr(pipe.cfg.log, "aid_status_rate_hz", 0.0))
            recorder = SmootherRecorder.attached_to(pipe.engine) if smooth else None
        sols = pipe.feed(k, rec.t_mono_ns, rec.payload)
        for sol in sols:
            res.solutions.append(sol)
            res.produced.append(encode_solution(sol))
        if sols:                            # as the service: right after the feed that produced them
            for obj, payload in pacer.records(pipe, sols):
                res.aid_status.append(obj)
                res.aid_status_produced.append(payload)
    prog.update(total, final=True)
    res.elapsed_s = time.perf_counter() - t0
    st = reader.stats
    res.log_stats = {"files": st.files, "records": st.records, "crc_errors": st.crc_errors,
                     "bad_records": st.bad_records, "truncated_tails": len(st.truncated_tails)}
    if pipe is not None:
        res.pipeline_health = pipe.health()
    if recorder is not None:       # the backward (RTS) pass; the comparison with the log stays on the forward one
        res.solutions = recorder.smoothed(res.solutions)
        res.notes.append(f"solutions RTS-smoothed over {recorder.n_checkpoints} checkpoints (companion.nav.smoother)")
    return res


def imu_rate_check(stream: str, times_us, needed_hz: float = IMU_RATE_NEEDED_HZ) -> dict:
    """The IMU stream's rate (median of the positive intervals of its time stamps) against the
    rate the pipeline needs; ``reason`` is empty when it is enough."""
    t = np.asarray(times_us, float)
    d = np.diff(t)
    d = d[d > 0]
    rate = float(1e6 / np.median(d)) if len(d) else 0.0
    out = {"stream": stream, "samples": int(len(t)), "rate_hz": round(rate, 3), "needed_hz": needed_hz,
           "median_interval_s": float(np.median(d) * 1e-6) if len(d) else None, "reason": ""}
    if not stream:
        out["reason"] = ("no IMU in the log (HIGHRES_IMU, RAW_IMU or SCALED_IMU2/3; DataFlash IMU): "
                         "an inertial solution needs one")
    elif rate < needed_hz:
        out["reason"] = (f"IMU {stream} at {rate:.2f} Hz (median interval {out['median_interval_s'] or 0:.3f} s, "
                         f"{len(t)} samples); the inertial filter needs at least {needed_hz:.0f} Hz: it integrates "
                         f"rate x interval and drops every interval of 0.1 s or more, so this log cannot give a "
                         f"tightly (or loosely) coupled solution")
    return out


def _tlog_imu_stream(msgs, cfg) -> tuple[str, list]:
    """The IMU stream the pipeline would fuse from these messages (its rules: the configured
    message, the cluster's primary, or 'auto' = HIGHRES_IMU if present, else the first seen) and
    its time stamps in microseconds."""
    from .io.mavlink_decode import parse_imu_stream
    target = (cfg.mavlink.target_system, cfg.mavlink.target_component)
    want, want_id = (parse_imu_stream(cfg.mavlink.imu_cluster[0]) if cfg.mavlink.imu_cluster
                     else (None if cfg.mavlink.imu_message == "auto" else cfg.mavlink.imu_message, None))
    times: dict[str, list] = {}
    first = None
    for _, msg in msgs:
        mt = msg.get_type()
        if mt not in _IMU_TYPES or (msg.get_srcSystem(), msg.get_srcComponent()) != target:
            continue
        if want_id is not None and int(getattr(msg, "id", 0)) != want_id:
            continue
        first = first or mt
        t_us = int(msg.time_boot_ms) * 1000 if mt.startswith("SCALED_IMU") else int(msg.time_usec)
        times.setdefault(mt, []).append(t_us)
    stream = want or ("HIGHRES_IMU" if "HIGHRES_IMU" in times else first or "")
    return stream, times.get(stream, [])


def _tlog_messages(path) -> list:
    from pymavlink import mavutil
    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega", robust_parsing=True)
    out = []
    while True:
        msg = conn.recv_msg()
        if msg is None:
            break
        if msg.get_type() != "BAD_DATA":
            out.append((int(getattr(msg, "_timestamp", 0.0) * 1e9), msg))
    return out


def replay_tlog(path, config=None, progress: bool = False, needed_imu_hz: float = IMU_RATE_NEEDED_HZ) -> ReplayResult:
    from .config import Config
    cfg = config or Config()
    res = ReplayResult(config_from="--config" if config is not None else "defaults", kind="tlog")
    t0 = time.perf_counter()
    msgs = _tlog_messages(path)
    res.imu_check = imu_rate_check(*_tlog_imu_stream(msgs, cfg), needed_hz=needed_imu_hz)
    if res.imu_check["reason"]:
        res.refusal = res.imu_check["reason"] + (
            "; a ground station logs the IMU at the rate it requested (ArduPilot SRn_RAW_SENS, "
            "often 1-4 Hz): replay the autopilot's DataFlash .BIN log from its SD card instead, or "
            "record the telemetry with the IMU at 50 Hz or more")
        res.records = len(msgs)
        res.elapsed_s = time.perf_counter() - t0
        return res
    pipe = NavPipeline(cfg)
    pacer = AidStatusPacer(cfg.log.aid_status_rate_hz)
    prog = _Progress(len(msgs), progress)
    for k, (t_ns, msg) in enumerate(msgs):
        res.records += 1
        prog.update(k)
        sols = pipe.feed("mavlink", t_ns, bytes(msg.get_msgbuf()))
        for sol in sols:
            res.solutions.append(sol)
            res.produced.append(encode_solution(sol))
        res.aid_status += [obj for obj, _ in pacer.records(pipe, sols)] if sols else []
    prog.update(len(msgs), final=True)
    res.elapsed_s = time.perf_counter() - t0
    res.pipeline_health = pipe.health()
    return res


def dataflash_config(dlog, imu_rate_hz: float, base=None, raw_observations: bool = False):
    """The configuration for a DataFlash log without ``--config``: the defaults, adapted to what
    the log holds.  Returns ``(config, notes)``; every adaptation is named in the notes.

    * ``raw_observations`` (the log's GRXH/GRXS with a navigation file): ``gnss.source = 'serial'``,
      the receiver's stream as on the companion's own port (tightly coupled; the GPS fixes only if
      it stops); else ``'none'`` (loose coupling on the GPS fixes from the first one, not after
      waiting for raw data);
    * ``mavlink.imu_message = 'HIGHRES_IMU'``, ``imu_rate_hz`` = the rate found;
    * ``gnss.lever_arm_b_m`` = ``GPS_POS{n}`` - ``INS_POS{n}`` when the log sets them;
    * a SITL log with ``SIM_DRIFT_SPEED`` (deg/s per minute; ArduPilot's simulated gyro drifts on
      all three axes as a triangle wave, ``minutes x SIM_DRIFT_SPEED``, rising for
      ``SIM_DRIFT_TIME`` minutes): the gyro-bias random walk is set so that its spread over one
      rise equals the rise, ``sigma = r sqrt(T)`` with ramp ``r`` (rad/s per s) and ``T`` (s) --
      the default (1e-5 rad/s/sqrt(s), a real MEMS gyro at constant temperature) lags a
      1.5e-5 rad/s^2 ramp and leaves a tilt error (0.10 m horizontal RMS instead of 0.02 m on the
      shared SITL log).
    """
    import dataclasses
    from .config import Config
    from .io.dataflash import lever_arm_from_params
    notes = []
    cfg = base or Config()
    if base is not None:
        return cfg, ["configuration from --config, used as it is"]
    if raw_observations:
        g = dataclasses.replace(cfg.gnss, source="serial")
    else:
        g = dataclasses.replace(cfg.gnss, source="none")
        notes.append("GPS fixes only (GPS/GPA records, loosely coupled): no raw GNSS observations used")
    lever = lever_arm_from_params(dlog)
    if lever is not None and any(abs(x) > 0 for x in lever):
        g = dataclasses.replace(g, lever_arm_b_m=lever)
        notes.append(f"lever arm {lever} m (body FRD) from GPS_POS/INS_POS")
    mc = dataclasses.replace(cfg.mavlink, imu_message="HIGHRES_IMU", imu_cluster=(),
                             imu_rate_hz=float(min(max(imu_rate_hz, 1.0), 2000.0)))
    f = cfg.filter
    speed, period = dlog.params.get("SIM_DRIFT_SPEED", 0.0), dlog.params.get("SIM_DRIFT_TIME", 0.0)
    if dlog.sitl and speed > 0 and period > 0:
        ramp = math.radians(speed) / 60.0
        sigma = ramp * math.sqrt(period * 60.0)
        if sigma > f.gyro_bias_rw_radps_per_sqrt_s:
            f = dataclasses.replace(f, gyro_bias_rw_radps_per_sqrt_s=sigma)
            notes.append(f"SITL gyro drift SIM_DRIFT_SPEED {speed:g} deg/s/min over SIM_DRIFT_TIME {period:g} min: "
                         f"gyro bias random walk {sigma:.2e} rad/s/sqrt(s)")
    noise = imu_noise_at_rest(dlog)
    if noise is not None:
        arw, vrw, span_s = noise
        changed = {}
        if arw > f.gyro_arw_rad_per_sqrt_s:
            changed["gyro_arw_rad_per_sqrt_s"] = float(f"{arw:.3g}")
        if vrw > f.accel_vrw_mps_per_sqrt_s:
            changed["accel_vrw_mps_per_sqrt_s"] = float(f"{vrw:.3g}")
        if changed:
            f = dataclasses.replace(f, **changed)
            notes.append(f"IMU white noise measured at rest before arming ({span_s:.0f} s) exceeds the defaults: "
                         + ", ".join(f"filter.{k} = {v:g}" for k, v in changed.items()))
    return dataclasses.replace(cfg, gnss=g, mavlink=mc, filter=f), notes


def imu_noise_at_rest(dlog, instance: int = 0, min_s: float = 10.0):
    """(gyro ARW rad/sqrt(s), accel VRW m/s/sqrt(s), seconds used) of the IMU while the vehicle sat
    disarmed before its first arming (1 s trimmed at both ends), or None without such a span.
    The white-noise terms N of the Allan deviation fit (:mod:`companion.nav.allan`, worst axis):
    right for the low-pass filtered samples an autopilot logs, where the sample deviation times
    sqrt(interval) is not (PX4 SIH at 250 Hz: 0.0063 from the deviation, 0.0053 rad/sqrt(s) from
    Allan).  The bias terms are not taken: tens of seconds cannot show them.  A simulator's IMU is
    far noisier than the defaults, which describe a real MEMS IMU: told the defaults, the filter
    was 0.61 m off (horizontal RMS) on a 45-s SIH flight, 0.07 m with the measured noise."""
    from .nav.allan import analyse_imu
    imu = dlog.imu.get(instance)
    arm = sorted(dlog.arm)
    if imu is None or len(imu) < 10 or not arm or arm[0][1]:
        return None                       # the log starts armed (ArduPilot's default): no rest span
    t_arm = next((t for t, a in arm if a), imu[-1, 0])
    sel = (imu[:, 0] > imu[0, 0] + 1e6) & (imu[:, 0] < t_arm - 1e6)
    if np.sum(sel) < 100 or (imu[sel, 0][-1] - imu[sel, 0][0]) * 1e-6 < min_s:
        return None
    a = imu[sel]
    noise = analyse_imu(a[:, 0] * 1e-6, a[:, 1:4], a[:, 4:7])["noise"]
    return (float(noise["gyro_arw_rad_per_sqrt_s"]), float(noise["accel_vrw_mps_per_sqrt_s"]),
            float((a[-1, 0] - a[0, 0]) * 1e-6))


def replay_dataflash(path, config=None, progress: bool = False, t_start_s: float | None = None,
                     t_end_s: float | None = None, options=None,
                     needed_imu_hz: float = IMU_RATE_NEEDED_HZ, smooth: bool = False, nav_path=None,
                     base_path=None) -> ReplayResult:
    """Post-process an ArduPilot DataFlash log through the pipeline (boot-time window optional);
    with ``nav_path`` (RINEX navigation) its u-blox raw observations (GRXH/GRXS) tightly coupled,
    with ``base_path`` (RINEX observations) against that base station."""
    from .io.dataflash import read_dataflash
    t0 = time.perf_counter()
    dlog = read_dataflash(path, t_start_s, t_end_s)
    return _replay_autopilot_log(dlog, "dataflash", t0, config, progress, options, needed_imu_hz, smooth=smooth,
                                 raw=logged_raw(dlog, nav_path, base_path))


def replay_ulog(path, config=None, progress: bool = False, t_start_s: float | None = None,
                t_end_s: float | None = None, options=None,
                needed_imu_hz: float = IMU_RATE_NEEDED_HZ, smooth: bool = False, nav_path=None,
                base_path=None) -> ReplayResult:
    """Post-process a PX4 ULog through the pipeline (:mod:`companion.io.ulog`: the same adapter as
    DataFlash after reading; SIH truth scored beside EKF2's vehicle_global_position); its
    receiver's bytes (``gps_dump``) tightly coupled (:mod:`companion.replay_raw`)."""
    import dataclasses
    from .io.dataflash import AdapterOptions
    from .io.ulog import is_sih, read_ulog
    t0 = time.perf_counter()
    dlog, notes = read_ulog(path, t_start_s, t_end_s)
    opts = options or AdapterOptions()
    if opts.earth_rate is None:
        opts = dataclasses.replace(opts, earth_rate=is_sih(dlog))
    return _replay_autopilot_log(dlog, "ulog", t0, config, progress, opts, needed_imu_hz, notes, smooth=smooth,
                                 raw=logged_raw(dlog, nav_path, base_path))


_AUTOPILOT_LOG = {"dataflash": {"imu": "IMU", "estimate": "EKF3 POS", "truth": "SIM truth",
                                "rate_hint": "; ArduPilot logs the IMU at the loop rate with the INS_LOG_BAT_* "
                                             "batch sampler or 'Fast IMU' in LOG_BITMASK",
                                "no_time": "no GPS fix with a GPS week and time in the log (GPS records)"},
                  "ulog": {"imu": "sensor_combined", "estimate": "EKF2 vehicle_global_position",
                           "truth": "SIH truth",
                           "rate_hint": "; PX4 logs sensor_combined at the full rate in its default profile",
                           "no_time": "no GPS fix in the log (vehicle_gps_position)"}}


def _replay_autopilot_log(dlog, kind: str, t0: float, config, progress, options, needed_imu_hz,
                          notes: list | None = None, smooth: bool = False, raw: dict | None = None) -> ReplayResult:
    """An autopilot's own log (DataFlash or ULog, read into a DataFlashLog) through the pipeline;
    ``raw``: :func:`companion.replay_raw.logged_raw`'s answer."""
    import dataclasses
    from .io.dataflash import AdapterOptions, iter_mavlink_messages, time_base
    from .nav.earth import ecef_to_geodetic
    from .post_report import score_against_truth
    names = _AUTOPILOT_LOG[kind]
    res = ReplayResult(kind=kind)
    opts = options or AdapterOptions()
    imu = dlog.imu.get(opts.imu_instance, np.zeros((0, 7)))
    stream = names["imu"] + (f"[{opts.imu_instance}]" if kind == "dataflash" else "")
    res.imu_check = imu_rate_check(stream if len(imu) else "", imu[:, 0], needed_imu_hz)
    res.log_stats = {"imu_samples": {str(i): int(len(a)) for i, a in dlog.imu.items()},
                     "imu_unhealthy": {str(i): n for i, n in dlog.imu_unhealthy.items()},
                     "gps_fixes": {str(i): int(len(a)) for i, a in dlog.gps.items()},
                     "gps_fixes_without_week": {str(i): int(np.sum(a[:, 3] <= 0)) for i, a in dlog.gps.items()},
                     "sim_truth": int(len(dlog.sim)), "ekf_pos": int(len(dlog.pos)),
                     "raw_gnss_records": dlog.raw_gnss_records, "sitl": dlog.sitl, "parameters": len(dlog.params)}
    if res.imu_check["reason"]:
        res.refusal = res.imu_check["reason"] + names["rate_hint"]
        res.elapsed_s = time.perf_counter() - t0
        return res
    raw = raw or {"reason": "", "notes": []}
    if raw.get("refusal"):
        res.refusal = raw["refusal"]
        res.elapsed_s = time.perf_counter() - t0
        return res
    cfg, res.notes = dataflash_config(dlog, res.imu_check["rate_hz"], config, raw_observations=bool(raw.get("items")))
    res.notes += list(notes or ()) + raw["notes"] + ([raw["reason"]] if raw["reason"] else [])
    if raw.get("counters"):
        res.log_stats["raw_gnss"] = dict(raw["counters"])
    res.config_from = "--config" if config is not None else f"defaults adapted to the {kind} log"
    opts = dataclasses.replace(opts, leap_seconds=cfg.gnss.leap_seconds, target_system=cfg.mavlink.target_system,
                               target_component=cfg.mavlink.target_component)
    tb = time_base(dlog, opts)
    if tb is None:
        res.refusal = names["no_time"] + ": no GPS time, no position"
        res.elapsed_s = time.perf_counter() - t0
        return res
    res.time_base = tb.as_dict()
    if tb.gms_is_delivery and tb.latency_s > 0:
        res.notes.append(f"SITL GPS: fix time = GMS - {tb.latency_s * 1e3:.0f} ms (SIM_GPS_LAG_MS)")
    elif tb.latency_s > 0:
        res.notes.append(f"GPS delivered {tb.latency_s * 1e3:.0f} ms after its epoch (GPS_DELAY_MS)")
    earth = dlog.sitl if opts.earth_rate is None else opts.earth_rate
    if earth:
        res.notes.append("simulated gyros do not sense the Earth's rotation: added from the attitude")
    pipe = NavPipeline(cfg)
    pipe.adopt_klobuchar(raw.get("klobuchar"), "the RINEX navigation header")
    recorder = SmootherRecorder.attached_to(pipe.engine) if smooth else None
    pacer = AidStatusPacer(cfg.log.aid_status_rate_hz)
    prog = _Progress(len(imu), progress)          # about one message per IMU sample
    mav = ((t_us, 0, "mavlink", msg)
           for t_us, msg in iter_mavlink_messages(dlog, dataclasses.replace(opts, earth_rate=earth), tb))
    for t_us, _, what, item in heapq.merge(mav, raw_records(raw, tb), key=lambda x: (x[0], x[1])):
        res.records += 1
        if not res.records & 1023:
            prog.update(res.records)
        t_ns = int(t_us * 1000)
        if what == "mavlink":
            sols = pipe.feed_mavlink_record(t_ns, item)
        elif what == "ubx":
            sols = pipe.feed("ubx", t_ns, item)
        else:
            sols = pipe.feed_decoded(t_ns, item)
        for sol in sols:
            res.solutions.append(sol)
            res.produced.append(encode_solution(sol))
        res.aid_status += [obj for obj, _ in pacer.records(pipe, sols)] if sols else []
    prog.update(len(imu), final=True)
    res.pipeline_health = pipe.health()
    forward = res.solutions
    if recorder is not None:       # the backward (RTS) pass: the smoothed solutions replace the forward ones
        res.solutions = recorder.smoothed(forward)
        res.notes.append(f"solutions RTS-smoothed over {recorder.n_checkpoints} checkpoints (companion.nav.smoother)")
    for which, solutions in (("", res.solutions),) + ((("forward", forward),) if recorder is not None else ()):
        sols = [s for s in solutions if np.all(np.isfinite(s.r_e))]
        if sols:
            llh = np.array([ecef_to_geodetic(s.r_e) for s in sols])
            ours = np.c_[np.degrees(llh[:, 0]), np.degrees(llh[:, 1]), llh[:, 2]]
            t_boot = np.array([tb.to_boot(s.t_gps) for s in sols])
            res.tracks["ours" + (f" ({which})" if which else "")] = ours
            if len(dlog.sim) >= 2:
                score = score_against_truth(t_boot, ours[:, 0], ours[:, 1], ours[:, 2], dlog.sim,
                                            dlog.pos if len(dlog.pos) else None, names["estimate"])
                setattr(res, "forward_score" if which else "truth_score", score)
    for name, arr in ((names["truth"], dlog.sim), (names["estimate"], dlog.pos)):
        if len(arr):
            res.tracks[name] = arr[:, 1:4]
    res.elapsed_s = time.perf_counter() - t0
    return res


def replay(path, config=None, progress: bool = False, *, needed_imu_hz: float = IMU_RATE_NEEDED_HZ,
           dataflash_options=None, t_start_s: float | None = None, t_end_s: float | None = None,
           smooth: bool = False, antennas_path: str | None = None, nav_path=None, base_path=None) -> ReplayResult:
    """Replay any log: a DataFlash .BIN or a PX4 .ulg (by its first bytes or name), a .tlog, else a
    field log.  ``dataflash_options`` (:class:`~companion.io.dataflash.AdapterOptions`) and the
    boot-time window apply to DataFlash and ULog logs only; ``antennas_path``, to field logs: the
    antenna calibration file the flight used, where it is here."""
    p = str(path)
    if Path(p).is_file() and (p.lower().endswith(".bin") or _is_dataflash(p)):
        return replay_dataflash(path, config, progress, t_start_s, t_end_s, dataflash_options, needed_imu_hz, smooth,
                                nav_path, base_path)
    if Path(p).is_file() and (p.lower().endswith((".ulg", ".ulg.xz", ".ulg.gz")) or _is_ulog(p)):
        return replay_ulog(path, config, progress, t_start_s, t_end_s, dataflash_options, needed_imu_hz, smooth,
                           nav_path, base_path)
    if p.endswith(".tlog") or p.endswith(".mavlink"):
        if smooth:
            raise ValueError("smoothing is implemented for field logs, DataFlash and ULog replays")
        return replay_tlog(path, config, progress, needed_imu_hz)
    return replay_field_log(path, config, progress, smooth, antennas_path)


def _cli_options(args) -> dict:
    """Optional replay flags (``--min-imu-rate-hz``, ``--gps-latency-ms``, ``--imu-instance``,
    ``--start``, ``--end``), read with defaults so the parser may or may not define them."""
    from .io.dataflash import AdapterOptions
    lat_ms = getattr(args, "gps_latency_ms", None)
    opts = AdapterOptions(imu_instance=int(getattr(args, "imu_instance", None) or 0),
                          gps_latency_s=None if lat_ms is None else float(lat_ms) * 1e-3)
    return {"needed_imu_hz": float(getattr(args, "min_imu_rate_hz", None) or IMU_RATE_NEEDED_HZ),
            "dataflash_options": opts, "t_start_s": getattr(args, "start", None), "t_end_s": getattr(args, "end", None),
            "smooth": bool(getattr(args, "smooth", False)), "antennas_path": getattr(args, "antennas_file", None),
            "nav_path": getattr(args, "nav", None), "base_path": getattr(args, "base", None)}


def _is_ulog(p) -> bool:
    from .io.ulog import is_ulog
    return is_ulog(p)


def _is_dataflash(p) -> bool:
    from .io.dataflash import is_dataflash
    return is_dataflash(p)


def why_no_solution(res: ReplayResult) -> str:
    """The likeliest reason a replay that ran produced no solution, from the pipeline's counters."""
    h = res.pipeline_health
    pc, imu, tm = h.get("pipeline", {}), h.get("imu", {}), h.get("time_map", {})
    if not imu.get("samples"):
        if imu.get("no_time") or not tm.get("system_time"):
            return "IMU samples could not be put on GPS time: no SYSTEM_TIME with UTC in the log"
        if imu.get("gap_reset"):
            return f"every IMU interval was 0.1 s or more ({imu['gap_reset']} dropped)"
        return "no usable IMU sample"
    if not pc.get("GPS_RAW_INT fixes") and not pc.get("rover epochs"):
        return "no GPS fix (GPS_RAW_INT with a 3-D fix) and no raw GNSS observations in the log"
    if pc.get("init: waiting for ATTITUDE") or pc.get("init: ATTITUDE too old"):
        return "no recent ATTITUDE to initialise the attitude from, and no heading from motion (the vehicle " \
               "never moved enough for the yaw estimator)"
    return "the filter never initialised (see the pipeline counters in --json)"


def _sol_json(sol) -> dict:
    def f(a):
        return [float(x) if math.isfinite(float(x)) else None for x in np.asarray(a, float)]
    return {"t_gps": sol.t_gps, "r_e": f(sol.r_e), "status": sol.status, "sigma_r_ned_m": f(sol.sigma_r_n_m),
            "sigma_v_ned_mps": f(sol.sigma_v_n_mps), "inject": sol.extras.get("inject"),
            "hpl_m": f([sol.extras.get("hpl_m", math.nan)])[0],
            "reset_counter": sol.reset_counter}


def plot_replay(res: ReplayResult, path: str) -> None:
    from .extras import pyplot
    from .nav.earth import ecef_to_ned, geodetic_to_ecef
    plt = pyplot("companion replay --plot")
    sols = [s for s in res.solutions if np.all(np.isfinite(s.r_e))]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(12, 5))
    if sols:
        ref = sols[0].r_e
        for name, llh in res.tracks.items():
            if name == "ours":
                continue
            ned = np.array([ecef_to_ned(geodetic_to_ecef(math.radians(r[0]), math.radians(r[1]), r[2]), ref)
                            for r in llh])
            a1.plot(ned[:, 1], ned[:, 0], "-", lw=0.8, label=name)
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
    title = f"replay: {len(res.solutions)} solutions"
    sc = res.truth_score
    if sc.get("ours", {}).get("horizontal", {}).get("rms_m") is not None:
        title += f"; horizontal RMS vs truth {sc['ours']['horizontal']['rms_m']:.3f} m"
        if "reference" in sc:
            title += f" ({sc['reference_name']} {sc['reference']['horizontal']['rms_m']:.3f} m)"
    elif res.kind == "field log":
        title += f"; bit-for-bit {c['identical']}/{c['logged_solutions']}"
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    if sols:
        plot_aid_status(res, aid_status_plot_path(path))


def aid_status_plot_path(path: str) -> str:
    """The second figure of ``--plot PATH``: ``<stem>.aid<suffix>`` beside it."""
    p = Path(path)
    return str(p.with_name(p.stem + ".aid" + (p.suffix or ".png")))


MAX_PLOTTED_SOURCES = 6


def aid_status_series(records: list) -> dict:
    """Per source: (t_gps, row test ratio, row innovation, accepted) of every row of every distinct
    update in the aid-status records (a source repeated unchanged between records counted once)."""
    out: dict[str, list] = {}
    seen: dict[str, float] = {}
    for rec in records:
        for name, st in rec.get("sources", {}).items():
            t = st.get("t_gps")
            if t is None or seen.get(name) == t:
                continue
            seen[name] = t
            rows = out.setdefault(name, [])
            for ratio, innov, acc in zip(st.get("test_ratio", []), st.get("innovation", []), st.get("accepted", [])):
                rows.append((t, np.nan if ratio is None else ratio, np.nan if innov is None else innov, bool(acc)))
    return {k: np.array(v, float).reshape(-1, 4) for k, v in out.items() if v}


def plot_aid_status(res: ReplayResult, path: str) -> None:
    """Innovations and test ratios per aid source over time, and the HPL against sigma_h.  The
    aid-source series come from the replay's own records (recomputed, companion.aid_status_record:
    the same as the logged ones when the replay is bit for bit, and available for old logs and
    tlog/DataFlash replays too); HPL and sigma_h from the replayed solutions."""
    from .extras import pyplot
    plt = pyplot("companion replay --plot")
    sols = [s for s in res.solutions if np.all(np.isfinite(s.r_e))]
    series = aid_status_series(res.aid_status)
    names = sorted(series, key=lambda k: -len(series[k]))[:MAX_PLOTTED_SOURCES]
    t0 = sols[0].t_gps if sols else 0.0
    fig, axes = plt.subplots(len(names) + 1, 2, figsize=(12, 2.4 * (len(names) + 1)), squeeze=False, sharex=True)
    for row, name in enumerate(names):
        a = series[name]
        acc = a[:, 3] > 0.5
        ai, ar = axes[row]
        ai.plot(a[acc, 0] - t0, a[acc, 2], ".", ms=2, label="fused")
        ai.plot(a[~acc, 0] - t0, a[~acc, 2], "x", ms=3, color="tab:red", label="rejected")
        ai.set_ylabel(f"{name}\ninnovation")
        ar.semilogy(a[acc, 0] - t0, np.maximum(a[acc, 1], 1e-6), ".", ms=2, label="fused")
        ar.semilogy(a[~acc, 0] - t0, np.maximum(a[~acc, 1], 1e-6), "x", ms=3, color="tab:red", label="rejected")
        ar.axhline(1.0, color="k", lw=0.6)
        ar.set_ylabel("test ratio")
        if row == 0:
            ai.set_title("innovation per row (m, m/s or rad)")
            ar.set_title("test ratio per row (> 1 rejected by the gate)")
            ar.legend(loc="upper right", fontsize=7)
    ah, ax2 = axes[-1]
    if sols:
        t = np.array([s.t_gps for s in sols]) - t0
        sig_h = np.array([math.hypot(float(s.sigma_r_n_m[0]), float(s.sigma_r_n_m[1])) for s in sols])
        hpl = np.array([float(s.extras.get("hpl_m", np.nan)) for s in sols])
        inj = np.array([bool(s.extras.get("inject")) for s in sols])
        ah.semilogy(t, hpl, "-", lw=0.9, label="HPL")
        ah.semilogy(t, sig_h, "-", lw=0.9, label="sigma_h")
        ah.set_ylabel("[m]")
        ah.set_xlabel("time [s]")
        ah.legend(fontsize=7)
        ah.set_title("protection level against sigma_h (replayed solutions)")
        with np.errstate(divide="ignore", invalid="ignore"):
            ax2.plot(t, hpl / sig_h, "-", lw=0.9, label="HPL / sigma_h")
        ax2.plot(t, inj.astype(float), "-", lw=0.6, color="0.5", label="injected (1/0)")
        ax2.set_xlabel("time [s]")
        ax2.legend(fontsize=7)
    fig.suptitle(f"aid sources (recomputed by the replay: {len(res.aid_status)} records)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _print_summary(res: ReplayResult, c: dict) -> None:
    rate = res.records / res.elapsed_s if res.elapsed_s > 0 else float("nan")
    if res.refusal:
        ic = res.imu_check
        print(f"read {res.records} records in {res.elapsed_s:.2f} s: not replayed"
              + (f" (IMU {ic['stream'] or 'none'} at {ic['rate_hz']:.1f} Hz, needed {ic['needed_hz']:.0f} Hz)"
                 if ic and ic.get("reason") else ""))
        return
    print(f"replayed {res.records} records in {res.elapsed_s:.2f} s ({rate:,.0f} records/s); "
          f"config from {res.config_from or 'nowhere (no config event: nothing replayed)'}")
    if res.imu_check:
        ic = res.imu_check
        print(f"IMU: {ic['stream'] or 'none'} at {ic['rate_hz']:.1f} Hz ({ic['samples']} samples; "
              f"needed {ic['needed_hz']:.0f} Hz)")
    for n in res.notes:
        print(f"note: {n}")
    if res.kind == "field log":
        print(f"solutions: {c['replayed_solutions']} replayed, {c['logged_solutions']} logged; "
              f"identical {c['identical']}, differing {c['differing']}"
              + (f", first difference at #{c['first_difference_index']}" if c["first_difference_index"] is not None else "")
              + ("  -> BIT FOR BIT" if c["bit_for_bit"] else ""))
        if "aid_status" in c:
            a = c["aid_status"]
            print(f"aid status records: {a['replayed']} replayed, {a['logged']} logged; identical {a['identical']}")
    else:
        modes = sorted({str(s.extras.get("mode")) for s in res.solutions})
        print(f"solutions: {len(res.solutions)} (mode {', '.join(modes) or 'none'}; "
              f"{'RTS-smoothed' if res.forward_score else 'forward filter only'})")
    if res.solutions:
        last = res.solutions[-1]
        print(f"last solution: status {last.status}, sigma NED {np.round(last.sigma_r_n_m, 3).tolist()} m")
    if res.truth_score:
        from .post_report import format_score
        for line in format_score(res.truth_score, _AUTOPILOT_LOG.get(res.kind, {}).get("truth", "SIM truth")):
            print(line.replace("forward filter only", "RTS-smoothed") if res.forward_score else line)
    if res.forward_score:
        print("forward pass alone (before smoothing):")
        for line in format_score(res.forward_score, _AUTOPILOT_LOG.get(res.kind, {}).get("truth", "SIM truth")):
            print("  " + line)


def run_replay_cli(args) -> int:
    cfg = None
    if getattr(args, "config", None):
        from .config import load_config
        cfg = load_config(args.config)
    if not Path(args.log).exists() and not list(Path(args.log).parent.glob(Path(args.log).name + "*")):
        print(f"error: {args.log}: no such field log, directory, .tlog, DataFlash .BIN or PX4 .ulg", file=sys.stderr)
        return 2
    if getattr(args, "imu_csv", None):
        from .replay_receiver import replay_receiver
        res = replay_receiver(args.log, args.imu_csv, cfg, nav_path=getattr(args, "nav", None),
                              base_path=getattr(args, "base", None), progress=not getattr(args, "no_progress", False),
                              csv_options={"columns": args.imu_columns, "time": args.imu_time,
                                           "gyro_unit": args.gyro_unit, "accel_unit": args.accel_unit,
                                           "rotation": args.imu_rotation},
                              ubx_latency_s=args.ubx_latency_ms * 1e-3, smooth=bool(getattr(args, "smooth", False)),
                              needed_imu_hz=getattr(args, "min_imu_rate_hz", None))
    else:
        res = replay(args.log, cfg, progress=not getattr(args, "no_progress", False), **_cli_options(args))
    c = res.comparison()
    _print_summary(res, c)
    if args.json:
        obj = {"log": str(args.log), "kind": res.kind, "records": res.records, "elapsed_s": res.elapsed_s,
               "config_from": res.config_from, "imu": res.imu_check, "refusal": res.refusal, "notes": res.notes,
               "forward_only": not res.forward_score, "comparison": c, "truth": res.truth_score,
               "truth_forward_pass": res.forward_score, "time_base": res.time_base,
               "log_stats": res.log_stats, "pipeline": res.pipeline_health,
               "solutions": [_sol_json(s) for s in res.solutions]}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(obj, default=str))
        print(f"wrote {args.json}")
    if res.solutions and any(getattr(args, k, None) for k in ("pos", "kml", "gpx")):
        from .io.track_export import write_solution_files
        n = write_solution_files(res.solutions, name=f"companion replay ({res.kind}): {Path(args.log).name}",
                                 pos=args.pos, kml=args.kml, gpx=args.gpx, inputs=[str(args.log)],
                                 options={"pos": "IMU (the fused solution, not the antenna)",
                                          "solution": "smoothed (forward + backward RTS)" if getattr(args, "smooth", False) else "forward"})
        print(f"wrote {n} epochs to " + ", ".join(p for p in (args.pos, args.kml, args.gpx) if p))
    if args.plot and res.solutions:
        plot_replay(res, args.plot)
        print(f"wrote {args.plot} and {aid_status_plot_path(args.plot)}")
    if res.refusal:
        print(f"error: {args.log}: {res.refusal}", file=sys.stderr)
        return EXIT_NO_SOLUTION
    if res.records == 0:
        print(f"error: {args.log}: no records found (a field log is a *.cflog file or a directory of them)",
              file=sys.stderr)
        return 2
    if not res.config_from and res.config_error:
        print(f"error: the field log's configuration cannot be read by this version ({res.config_error}); "
              f"replay with --config FILE", file=sys.stderr)
        return 2
    if res.kind != "field log" and not res.solutions:
        print(f"error: {args.log}: no solution: {why_no_solution(res)}", file=sys.stderr)
        return EXIT_NO_SOLUTION
    if res.logged and not c["bit_for_bit"] and res.config_from == "field log":
        return 1
    return 0


__all__ = ["replay", "replay_field_log", "replay_tlog", "replay_dataflash", "replay_ulog", "dataflash_config", "imu_rate_check",
           "why_no_solution", "ReplayResult", "plot_replay", "plot_aid_status", "aid_status_series", "run_replay_cli",
           "IMU_RATE_NEEDED_HZ", "EXIT_NO_SOLUTION"]
