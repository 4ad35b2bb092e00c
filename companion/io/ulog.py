"""PX4 ULog files (``.ulg``) -> the records :mod:`companion.io.dataflash` turns into MAVLink.

A ULog is what PX4 writes to its SD card.  pyulog reads it; this module fills the same container
as an ArduPilot DataFlash log (:class:`~companion.io.dataflash.DataFlashLog`: IMU, GPS, attitude,
truth, the autopilot's estimate, arming, parameters), so both logs reach the pipeline through one
adapter and their figures compare.

Topic -> record
---------------
* ``sensor_combined`` -> IMU: ``timestamp`` (the gyro sample, boot us; the accelerometer's
  ``accelerometer_timestamp_relative`` is added to it for the accelerometer), ``gyro_rad`` and
  ``accelerometer_m_s2`` in body FRD, as EKF2 gets them (calibrated, filtered).
* ``vehicle_gps_position`` -> GPS + GPA: the fix at its ``timestamp_sample`` (the measurement's boot
  time), ``time_utc_usec`` as GPS week / milliseconds (UTC + leap seconds), ``eph``/``epv``/
  ``s_variance_m_s`` as the accuracies, ``altitude_ellipsoid_m``.
* ``vehicle_attitude`` -> ATT (the initial attitude); ``vehicle_status.arming_state`` -> arming.
* ``vehicle_global_position`` -> POS (EKF2's estimate), ``vehicle_global_position_groundtruth``
  (PX4's SIH simulator) -> SIM (truth).
* ``gps_dump`` (``GPS_DUMP_COMM`` 1 or 2) -> ``raw_stream``: the first receiver's own bytes, in
  log order (what PX4 sent it is left out); :mod:`companion.replay_raw` feeds them.

GPS time.  A receiver's fix carries UTC (``time_utc_usec``), and the boot-to-GPS offset is the
median over the log.  PX4's SIH simulator leaves ``time_utc_usec`` at 0: its log has no absolute
time at all; the offset is then an arbitrary fixed epoch (:data:`NO_UTC_EPOCH_GPS_S`, said so in the
notes), good for a loosely coupled replay, which needs no satellite positions.

SIH's gyros do not sense the Earth's rotation (a flat, non-rotating Earth): :func:`is_sih` tells the
replay to add it, as for ArduPilot's SITL.
"""
from __future__ import annotations

import math

import numpy as np

from ..messages import SECONDS_PER_WEEK
from .dataflash import DataFlashLog

ULOG_MAGIC = b"ULog\x01\x12\x35"
#: GPS time taken for boot time 0 when the log has no UTC (PX4 SIH): 2025-12-28 00:00 GPS, a week start
NO_UTC_EPOCH_GPS_S = 2399 * SECONDS_PER_WEEK
GPS_EPOCH_UNIX_S = 315964800.0            # 1980-01-06 00:00:00 UTC
ARMING_STATE_ARMED = 2                     # vehicle_status.arming_state (PX4 v1.14+)
TOPICS = ["sensor_combined", "vehicle_gps_position", "vehicle_attitude", "vehicle_status",
          "vehicle_global_position", "vehicle_global_position_groundtruth", "gps_dump"]
GPS_DUMP_TO_DEVICE = 0x80                  # gps_dump.len's top bit: bytes sent to the receiver


def _open(path):
    """The file, decompressed when it is xz or gzip (a log archived as .ulg.xz / .ulg.gz)."""
    with open(path, "rb") as fh:
        head = fh.read(6)
    if head.startswith(b"\xfd7zXZ"):
        import lzma
        return lzma.open(path, "rb")
    if head.startswith(b"\x1f\x8b"):
        import gzip
        return gzip.open(path, "rb")
    return open(path, "rb")


def is_ulog(path) -> bool:
    """True when the file (or its xz/gzip content) starts with the ULog magic ('ULog' 0x01 0x12 0x35)."""
    try:
        with _open(path) as fh:
            return fh.read(7) == ULOG_MAGIC
    except (OSError, EOFError):
        return False


def is_sih(log: DataFlashLog) -> bool:
    """A log of PX4's SIH simulator (it has SIH_ parameters)."""
    return any(k.startswith("SIH_") for k in log.params)


def _vec(d: dict, name: str, n: int = 3) -> np.ndarray:
    return np.column_stack([np.asarray(d[f"{name}[{k}]"], float) for k in range(n)])


def _euler_deg_from_q(q: np.ndarray) -> np.ndarray:
    """(N, 4) Hamilton quaternions w, x, y, z (body FRD -> NED) -> roll, pitch, yaw in degrees."""
    w, x, y, z = q.T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.degrees(np.column_stack([roll, pitch, yaw]))


def _first(ulog, name: str):
    for d in ulog.data_list:
        if d.name == name and d.multi_id == 0:
            return d.data
    return None


def read_ulog(path, t_start_s: float | None = None, t_end_s: float | None = None,
              leap_seconds: int = 18) -> tuple[DataFlashLog, list[str]]:
    """The log's navigation records (boot-time window optional) and notes on what was assumed."""
    import io
    from ..extras import require
    ULog = require("pyulog", "ulog", "Reading PX4 ULog files").ULog
    with _open(path) as fh:
        data = io.BytesIO(fh.read())
    ul = ULog(data, TOPICS, disable_str_exceptions=True)
    out = DataFlashLog(str(path))
    out.params = {k: float(v) for k, v in ul.initial_parameters.items()}
    out.firmware = f"PX4 {ul.msg_info_dict.get('ver_sw', '')}".strip()
    notes: list[str] = []
    lo = -math.inf if t_start_s is None else t_start_s * 1e6
    hi = math.inf if t_end_s is None else t_end_s * 1e6

    def window(t_us):
        return (t_us >= lo) & (t_us <= hi)

    sc = _first(ul, "sensor_combined")
    if sc is not None:
        t = np.asarray(sc["timestamp"], float)
        sel = window(t)
        out.imu[0] = np.column_stack([t, _vec(sc, "gyro_rad"), _vec(sc, "accelerometer_m_s2")])[sel]
        rel = np.asarray(sc["accelerometer_timestamp_relative"], float)[sel]
        if np.any(np.abs(rel) > 0):
            notes.append(f"accelerometer sampled up to {np.max(np.abs(rel)) * 1e-3:.1f} ms from the gyro "
                         f"(accelerometer_timestamp_relative): taken at the gyro's time")
    gp = _first(ul, "vehicle_gps_position")
    if gp is not None:
        ts = np.asarray(gp["timestamp_sample"], float)
        t = np.where(ts > 0, ts, np.asarray(gp["timestamp"], float))
        utc = np.asarray(gp["time_utc_usec"], float)
        if np.any(utc > 0):
            t_gps = np.where(utc > 0, utc * 1e-6 - GPS_EPOCH_UNIX_S + leap_seconds, np.nan)
        else:
            t_gps = NO_UTC_EPOCH_GPS_S + t * 1e-6
            notes.append("no UTC in the log (time_utc_usec 0, as PX4's SIH writes it): GPS time = boot time + "
                         "a fixed epoch (fine for loose coupling, meaningless for satellite positions)")
        week = np.floor(t_gps / SECONDS_PER_WEEK)
        gms = (t_gps - week * SECONDS_PER_WEEK) * 1e3
        week = np.where(np.isfinite(t_gps), week, 0.0)
        vn, ve, vd = (np.asarray(gp[k], float) for k in ("vel_n_m_s", "vel_e_m_s", "vel_d_m_s"))
        valid = np.asarray(gp["vel_ned_valid"], bool)
        spd = np.where(valid, np.hypot(vn, ve), 0.0)
        crs = np.where(valid, np.degrees(np.arctan2(ve, vn)) % 360.0, 0.0)
        rows = np.column_stack([t, np.asarray(gp["fix_type"], float), gms, week,
                                np.asarray(gp["satellites_used"], float), np.asarray(gp["hdop"], float),
                                np.asarray(gp["latitude_deg"], float), np.asarray(gp["longitude_deg"], float),
                                np.asarray(gp["altitude_msl_m"], float), spd, crs, vd, np.full(len(t), np.nan)])
        gpa = np.column_stack([t, np.asarray(gp["vdop"], float), np.asarray(gp["eph"], float),
                               np.asarray(gp["epv"], float), np.asarray(gp["s_variance_m_s"], float),
                               np.asarray(gp["altitude_ellipsoid_m"], float)])
        sel = window(t)
        order = np.argsort(t[sel], kind="stable")
        out.gps[0], out.gpa[0] = rows[sel][order], gpa[sel][order]
    att = _first(ul, "vehicle_attitude")
    if att is not None:
        t = np.asarray(att["timestamp"], float)
        sel = window(t)
        out.att = np.column_stack([t, _euler_deg_from_q(_vec(att, "q", 4))])[sel]
    for name, attr in (("vehicle_global_position_groundtruth", "sim"), ("vehicle_global_position", "pos")):
        d = _first(ul, name)
        if d is not None:
            t = np.asarray(d["timestamp"], float)
            sel = window(t)
            setattr(out, attr, np.column_stack([t, np.asarray(d["lat"], float), np.asarray(d["lon"], float),
                                                np.asarray(d["alt"], float)])[sel])
    dump = _first(ul, "gps_dump")
    if dump is not None:
        out.raw_stream = _receiver_bytes(dump, window)
    st = _first(ul, "vehicle_status")
    if st is not None:
        armed = np.asarray(st["arming_state"]) == ARMING_STATE_ARMED
        t = np.asarray(st["timestamp"], float)
        prev = None
        for k in range(len(t)):
            if armed[k] != prev:
                out.arm.append((float(t[k]), bool(armed[k])))
                prev = armed[k]
    return out, notes


def _receiver_bytes(dump: dict, window) -> list[tuple[int, bytes]]:
    """(timestamp us, bytes) of what the first receiver sent (``gps_dump`` with ``GPS_DUMP_COMM``
    1: its whole stream; 2: the RTCM it was set to output), in log order; the bytes sent to it
    (``len``'s top bit) and other instances left out."""
    t = np.asarray(dump["timestamp"], np.int64)
    n = np.asarray(dump["len"], np.int64)
    inst = np.asarray(dump["instance"], np.int64) if "instance" in dump else np.zeros(len(t), np.int64)
    data = np.column_stack([np.asarray(dump[f"data[{k}]"], np.uint8) for k in range(79) if f"data[{k}]" in dump])
    keep = (inst == 0) & ((n & GPS_DUMP_TO_DEVICE) == 0) & window(t)
    return [(int(t[k]), bytes(data[k, :min(int(n[k]), data.shape[1])])) for k in np.flatnonzero(keep)]


__all__ = ["is_ulog", "is_sih", "read_ulog", "ULOG_MAGIC", "NO_UTC_EPOCH_GPS_S"]
