"""Post-process a receiver's recording with an IMU recorded beside it (CSV,
:mod:`companion.io.imu_csv`) through the same pipeline as the live service: ``companion replay
ROVER.ubx --imu-csv IMU.csv [--base BASE]``, or RINEX: ``companion replay ROVER.obs --nav NAV
--imu-csv IMU.csv [--base BASE]``; BASE is a base station's RINEX observations or RTCM 3 capture.

The IMU samples become the HIGHRES_IMU and SYSTEM_TIME messages an autopilot would have sent (the
DataFlash adapter, :mod:`companion.io.dataflash`, with the boot clock starting at the first IMU
sample's whole GPS second), and the UBX bytes are fed as the receiver's stream: each RXM-RAWX frame
and the frames after it (SFRBX, NAV) arrive ``ubx_latency_s`` after that epoch's receiver time, as
from a receiver on the companion's own port.  No ATTITUDE: the heading comes from motion (the yaw
estimator), as for a receiver and IMU that no autopilot ties together.  Without a base station the
solution is standalone (tightly coupled pseudoranges and TDCP).

RINEX observations (GPS, Galileo, BeiDou, QZSS: the filter uses its ``filter.systems``) go in as the epochs the decoders would produce
(:meth:`~companion.pipeline.NavPipeline.feed_decoded`), each ``ubx_latency_s`` after its time; the
navigation file's ephemerides at the start.  A base station's epochs (beside either) go in the
same way, with the station at its RINEX header position plus ``ANTENNA: DELTA H/E/N`` or at an
RTCM capture's last 1005/1006, which makes the solution DGPS.
"""
from __future__ import annotations

import dataclasses
import heapq
import math
import struct
import time

import numpy as np

from .io.capture_format import is_ubx_capture
from .io.ubx import ubx_checksum
from .messages import SECONDS_PER_WEEK

RAWX_HEADER = b"\xb5\x62\x02\x15"


def ubx_segments(data: bytes) -> list[tuple[float, bytes]]:
    """The capture cut at each valid RXM-RAWX frame: (receiver GPS time of that epoch, the bytes
    from it to the next one).  Bytes before the first epoch go with the first; a capture without
    RXM-RAWX gives none."""
    starts = []
    i = data.find(RAWX_HEADER)
    while i >= 0 and i + 8 <= len(data):
        n = struct.unpack_from("<H", data, i + 4)[0]
        end = i + 8 + n
        if n >= 16 and end <= len(data) and bytes(ubx_checksum(data[i + 2:i + 6 + n])) == data[end - 2:end]:
            tow, week = struct.unpack_from("<dH", data, i + 6)
            starts.append((i, week * SECONDS_PER_WEEK + tow))
            i = data.find(RAWX_HEADER, end)
        else:
            i = data.find(RAWX_HEADER, i + 2)
    out = []
    for k, (pos, t) in enumerate(starts):
        lo = 0 if k == 0 else pos
        hi = starts[k + 1][0] if k + 1 < len(starts) else len(data)
        out.append((t, data[lo:hi]))
    return out


GPS_WEEK_ROLLOVER = 1024


def _week_of(eph, t_gps_obs: float):
    """The ephemeris in the 1024-week era of the observations: LNAV broadcasts its week in 10 bits
    and a converter that resolves them against its own clock writes old data 1024 weeks late
    (RTKLIB 2.4.3's convbin on a 2005 capture: week 2340 for 1316).  A GLONASS record has no
    week (its t_b is a time of day, resolved on reading)."""
    if not hasattr(eph, "week"):
        return eph
    obs_week = int(t_gps_obs // SECONDS_PER_WEEK)
    k = round((eph.week - obs_week) / GPS_WEEK_ROLLOVER)
    return dataclasses.replace(eph, week=eph.week - k * GPS_WEEK_ROLLOVER) if k else eph


def nav_klobuchar(nav_path):
    """The Klobuchar coefficients of a RINEX navigation file's header (None: it has none)."""
    from .gnss.rinex import read_rinex_nav_header_iono
    try:
        return read_rinex_nav_header_iono(nav_path)
    except (OSError, ValueError, IndexError):
        return None


def read_nav(nav_path, t_gps_obs: float):
    """(ephemerides of the RINEX navigation file(s), moved into the 1024-week era of the
    observations at ``t_gps_obs``; how many were moved; GLONASS frequency channels)."""
    from .gnss.glonass import frequency_channels
    from .gnss.rinex import read_rinex_nav
    from .gnss.signals import PREPARED_SYSTEMS
    ephs = read_rinex_nav(nav_path, PREPARED_SYSTEMS)
    moved = [_week_of(e, t_gps_obs) for e in ephs]
    return moved, sum(1 for a, b in zip(ephs, moved) if a is not b), frequency_channels(ephs)


def read_base(base_path, channels, t_gps_obs: float = 0.0):
    """(the base station's position message, its epochs as base epochs) from a RINEX observation
    file (the header position plus ``ANTENNA: DELTA H/E/N``) or an RTCM 3 capture (its last
    1005/1006; MSM4-7 or 1004/1012 observations, decoded as the service decodes its NTRIP stream,
    their week from ``t_gps_obs``: MSM carries the time of week only)."""
    from .io.capture_format import is_rtcm_capture
    if is_rtcm_capture(base_path):
        return _read_rtcm_base(base_path, t_gps_obs)
    from .gnss.glonass import with_fdma_wavelengths
    from .gnss.rinex_obs import read_rinex_obs
    from .gnss.rtk_post import antenna_delta_e
    from .gnss.signals import PREPARED_SYSTEMS
    from .messages import BaseStationPosition
    hdr, base = read_rinex_obs(base_path, PREPARED_SYSTEMS)
    base = with_fdma_wavelengths(base, channels)
    r_b = hdr["approx_position_e"]
    if r_b is None:
        raise ValueError(f"{base_path}: no APPROX POSITION XYZ in the header: the base position is unknown")
    r_b = np.asarray(r_b, float)
    position = BaseStationPosition(station_id=0, r_e=r_b + antenna_delta_e(r_b, hdr.get("antenna_delta_hen_m")))
    return position, [dataclasses.replace(e, source="base") for e in base]


def _read_rtcm_base(path, t_gps_obs: float):
    from .io.rtcm import decode_rtcm_file
    from .messages import BaseStationPosition, GnssEpoch
    msgs, _ = decode_rtcm_file(str(path), week_hint=int(t_gps_obs // SECONDS_PER_WEEK))
    positions = [m for m in msgs if isinstance(m, BaseStationPosition)]
    epochs = [dataclasses.replace(m, source="base") for m in msgs if isinstance(m, GnssEpoch)]
    if not positions:
        raise ValueError(f"{path}: no RTCM 1005/1006 in the capture: the base position is unknown")
    if not epochs:
        raise ValueError(f"{path}: no base observations in the capture (MSM4-7 or 1004/1012 expected)")
    return positions[-1], epochs


def _rinex_stream(obs_path, nav_path, base_path):
    """(receiver GPS time, [decoded messages]) of RINEX rover (and base) observations; the
    ephemerides and the base position go with the first epoch."""
    from .gnss.glonass import with_fdma_wavelengths
    from .gnss.rinex_obs import read_rinex_obs
    from .gnss.signals import PREPARED_SYSTEMS
    if nav_path is None:
        raise ValueError("RINEX observations need --nav (a RINEX navigation file)")
    _, rover = read_rinex_obs(obs_path, PREPARED_SYSTEMS)       # the filter keeps its filter.systems
    first, shifted, channels = read_nav(nav_path, rover[0].t_gps if rover else 0.0)
    rover = with_fdma_wavelengths(rover, channels)              # RINEX leaves GLONASS FDMA wavelengths out
    if not rover:
        first, shifted = [], 0
    items = [(e.t_gps, [e]) for e in rover]
    if base_path is not None:
        position, base = read_base(base_path, channels, rover[0].t_gps if rover else 0.0)
        first.append(position)
        items += [(e.t_gps - 1e-6, [e]) for e in base]   # base before rover
    items.sort(key=lambda x: x[0])
    if items:
        items[0] = (items[0][0], first + items[0][1])
    return items, len(rover), shifted


def replay_receiver(obs_path, imu_csv, config=None, *, nav_path=None, base_path=None,
                    csv_options: dict | None = None, ubx_latency_s: float = 0.05, progress: bool = False,
                    needed_imu_hz: float | None = None, smooth: bool = False):
    """:class:`~companion.replay.ReplayResult` of the recording and the IMU CSV (see the module doc)."""
    from .config import Config
    from .io.imu_csv import read_imu_csv
    from .replay import IMU_RATE_NEEDED_HZ, ReplayResult, imu_rate_check
    t_start = time.perf_counter()
    ubx = is_ubx_capture(obs_path)        # a log may start mid-frame
    res = ReplayResult(kind="ubx+imu" if ubx else "rinex+imu")
    cfg = config or Config()
    try:
        imu, counters = read_imu_csv(imu_csv, leap_seconds=cfg.gnss.leap_seconds, **(csv_options or {}))
    except (ValueError, OSError) as exc:
        res.refusal = f"cannot read the IMU CSV: {exc}"
        return res
    if ubx:
        segments = ubx_segments(open(obs_path, "rb").read())
        n_epochs = len(segments)
        if base_path is not None and segments:
            try:                             # the base's epochs beside the capture's frames
                position, base = read_base(base_path, {}, segments[0][0])
            except (ValueError, IndexError, OSError) as exc:
                res.refusal = f"cannot read the base station's file: {exc}"
                return res
            segments = sorted(segments + [(segments[0][0] - 1e-6, [position])]
                              + [(e.t_gps - 1e-6, [e]) for e in base], key=lambda x: x[0])
    else:
        try:
            segments, n_epochs, shifted = _rinex_stream(obs_path, nav_path, base_path)
        except (ValueError, IndexError, OSError) as exc:
            res.refusal = f"cannot read the RINEX input: {exc}"
            res.elapsed_s = time.perf_counter() - t_start
            return res
        if shifted:
            res.notes.append(f"{shifted} ephemerides of {nav_path} were 1024 weeks off the observations "
                             f"(a converter's week roll-over): moved back")
    res.log_stats = {"imu_csv": counters, "imu_samples": int(len(imu)), "receiver_epochs": n_epochs}
    t0 = math.floor(imu[0, 0]) if len(imu) else 0.0
    boot_us = (imu[:, 0] - t0) * 1e6
    res.imu_check = imu_rate_check("IMU CSV" if len(imu) else "", boot_us, needed_imu_hz or IMU_RATE_NEEDED_HZ)
    if res.imu_check["reason"]:
        res.refusal = res.imu_check["reason"]
    elif not segments:
        res.refusal = (f"{obs_path}: no RXM-RAWX in the capture ('companion gnss configure' switches it on)" if ubx
                       else f"{obs_path}: no GPS, Galileo, BeiDou or QZSS observation epochs")
    elif segments[-1][0] < imu[0, 0] or segments[0][0] > imu[-1, 0]:
        res.refusal = (f"the receiver's epochs (GPS {segments[0][0]:.1f}-{segments[-1][0]:.1f} s) and the IMU "
                       f"({imu[0, 0]:.1f}-{imu[-1, 0]:.1f} s) do not overlap: check --imu-time")
    if res.refusal:
        res.elapsed_s = time.perf_counter() - t_start
        return res
    if config is None:
        cfg = dataclasses.replace(cfg, gnss=dataclasses.replace(cfg.gnss, source="serial"),
                                  mavlink=dataclasses.replace(cfg.mavlink, imu_message="HIGHRES_IMU", imu_cluster=(),
                                                              imu_rate_hz=float(min(max(res.imu_check["rate_hz"], 1.0), 2000.0))))
        res.notes.append("receiver on the companion's port (gnss.source 'serial'), IMU from the CSV as HIGHRES_IMU, "
                         "no ATTITUDE (heading from motion)" + (", base station from " + str(base_path) if base_path
                                                                 else ", no base station: standalone"))
    res.config_from = "--config" if config is not None else "defaults adapted to a receiver recording + IMU CSV"
    return replay_segments(segments, imu, cfg, res, name=str(obs_path), smooth=smooth, progress=progress,
                           t_start=t_start, ubx_latency_s=ubx_latency_s,
                           klobuchar=None if ubx or nav_path is None else nav_klobuchar(nav_path))


def replay_segments(segments, imu: np.ndarray, cfg, res, *, name: str = "", smooth: bool = False,
                    progress: bool = False, t_start: float | None = None, attitude_deg: np.ndarray | None = None,
                    ubx_latency_s: float = 0.05, klobuchar=None):
    """The pipeline over receiver ``segments`` ((receiver GPS time, UBX bytes or [decoded
    messages])) and an IMU ((N, 7): GPS time s, rate rad/s FRD, specific force m/s^2 FRD) as HIGHRES_IMU + SYSTEM_TIME, optionally ATTITUDE from ``attitude_deg`` ((M, 4):
    GPS time s, roll, pitch, yaw deg) as an autopilot would send it; ``klobuchar``: a RINEX
    navigation header's (the UBX stream brings its own).  Fills and returns ``res``."""
    from .io.dataflash import AdapterOptions, DataFlashLog, TimeBase, iter_mavlink_messages
    from .nav.earth import ecef_to_geodetic
    from .nav.smoother import SmootherRecorder
    from .pipeline import NavPipeline
    from .log_records import encode_solution
    from .replay import _Progress
    t_start = time.perf_counter() if t_start is None else t_start
    t0 = math.floor(imu[0, 0])
    boot_us = (imu[:, 0] - t0) * 1e6
    dlog = DataFlashLog(name)
    dlog.imu[0] = np.column_stack([boot_us, imu[:, 1:7]])
    if attitude_deg is not None:
        dlog.att = np.column_stack([(attitude_deg[:, 0] - t0) * 1e6, attitude_deg[:, 1:4]])
    tb = TimeBase(offset_s=t0, latency_s=0.0, gms_is_delivery=False, jitter_s=0.0, n_fixes=0)
    opts = AdapterOptions(earth_rate=False, leap_seconds=cfg.gnss.leap_seconds,
                          target_system=cfg.mavlink.target_system, target_component=cfg.mavlink.target_component)
    mav_stream = ((t_us, 0, msg) for t_us, msg in iter_mavlink_messages(dlog, opts, tb))
    ubx_stream = (((t - t0 + ubx_latency_s) * 1e6, 1, data) for t, data in segments)
    pipe = NavPipeline(cfg)
    pipe.adopt_klobuchar(klobuchar, "the RINEX navigation header")
    recorder = SmootherRecorder.attached_to(pipe.engine) if smooth else None
    prog = _Progress(len(imu), progress)
    for t_us, kind, item in heapq.merge(mav_stream, ubx_stream, key=lambda x: (x[0], x[1])):
        res.records += 1
        if not res.records & 1023:
            prog.update(res.records)
        t_ns = int(t_us * 1000)
        if kind == 0:
            sols = pipe.feed_mavlink_record(t_ns, item)
        elif isinstance(item, (bytes, bytearray)):
            sols = pipe.feed("ubx", t_ns, item)
        else:
            sols = pipe.feed_decoded(t_ns, item)
        for sol in sols:
            res.solutions.append(sol)
            res.produced.append(encode_solution(sol))
    prog.update(len(imu), final=True)
    res.pipeline_health = pipe.health()
    if recorder is not None:
        res.solutions = recorder.smoothed(res.solutions)
        res.notes.append(f"solutions RTS-smoothed over {recorder.n_checkpoints} checkpoints (companion.nav.smoother)")
    good = [s for s in res.solutions if np.all(np.isfinite(s.r_e))]
    if good:
        llh = np.array([ecef_to_geodetic(s.r_e) for s in good])
        res.tracks["ours"] = np.c_[np.degrees(llh[:, 0]), np.degrees(llh[:, 1]), llh[:, 2]]
    res.elapsed_s = time.perf_counter() - t_start
    return res


__all__ = ["replay_receiver", "replay_segments", "ubx_segments", "read_nav", "read_base", "nav_klobuchar"]
