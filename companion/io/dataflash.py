"""ArduPilot DataFlash logs (``.BIN``) -> the MAVLink messages :class:`~companion.pipeline.NavPipeline` eats.

A DataFlash log is what the autopilot writes to its SD card: every IMU sample at the loop rate
(``IMU``, up to 400 Hz), the GPS driver's fixes (``GPS``/``GPA``), the EKF's own attitude and
position (``ATT``, ``POS``), the parameters (``PARM``) and, in SITL, the simulator's truth
(``SIM``).  pymavlink's DFReader reads it; this module turns the records into the very pymavlink
message objects the live service receives over MAVLink (HIGHRES_IMU, SYSTEM_TIME, GPS_RAW_INT,
ATTITUDE, HEARTBEAT), so a log goes through the same pipeline and its figures compare with the
service's.  Pure: no clock, no socket; the output is a function of the file.

Record -> message
-----------------
* ``IMU`` (instance ``imu_instance``, healthy samples only: ``GH`` and ``AH`` set) -> HIGHRES_IMU,
  ``time_usec`` = ``TimeUS`` (boot time), rad/s and m/s^2 in body FRD as logged.  ArduPilot logs
  the *filtered* rates (``INS_GYRO_FILTER``/``INS_ACCEL_FILTER`` 2-pole low-pass), sampled at the
  loop rate.
* GPS time base: ``GPS.GWk``/``GPS.GMS`` against the record's ``TimeUS`` give the boot-to-GPS
  offset (median over the log, robust to UART jitter).  It is delivered as an exact SYSTEM_TIME
  every second (``time_unix_usec`` = UTC of that boot instant), as the autopilot would send it.
* ``GPS`` + the latest ``GPA`` of the same instance -> GPS_RAW_INT with ``time_usec`` = the fix's
  own GPS time as UNIX microseconds (the pipeline takes such a stamp as absolute time), fed at the
  record's ``TimeUS`` (when the autopilot had it).  Accuracies from ``GPA`` (``HAcc``/``VAcc``/
  ``SAcc``), ellipsoidal height from ``GPA.AEl``.  GPS_RAW_INT has no vertical velocity (the
  pipeline takes the climb rate as zero with ``vel_acc``): ``gps_velocity`` chooses whether the
  velocity is passed on at all.
* ``GRXH``/``GRXS`` (``GPS_RAW_DATA = 1`` with a u-blox) -> its RXM-RAWX frames again
  (:mod:`companion.io.dataflash_raw`), which ``companion replay LOG.BIN --nav NAV`` feeds as the
  receiver's stream at their ``TimeUS`` (tightly coupled; the ephemerides from the RINEX file).
* ``ATT`` -> ATTITUDE (the initial attitude); ``ARM`` (and the log starting armed, as it does with
  ``LOG_DISARMED = 0``) -> HEARTBEAT at 1 Hz with STANDBY/ACTIVE and the vehicle type from the
  firmware name in ``MSG`` (a rover or boat puts the pipeline in ground mode).

Latency.  On a real receiver ``GMS`` is the measurement epoch and the record arrives
``GPS_DELAY_MS`` later; the fix time is ``GMS``.  ArduPilot's simulated GPS stamps ``GMS`` when it
*delivers* the fix, which it measured ``SIM_GPSn_LAG_MS`` earlier (checked on the shared SITL log:
the fix matches SIM truth 100-104 ms before its ``TimeUS``, 1.5 cm RMS, against 28 cm at 0 ms).
So in a SITL log (it has ``SIM_`` parameters) the fix time is ``GMS - SIM_GPSn_LAG_MS``.

SITL's gyros do not sense the Earth's rotation (a real gyro does, and the mechanization removes
it): in a SITL log ``earth_rate`` adds ``C_n_b omega_ie_n`` to the gyro, with the attitude from
``ATT`` (its error of a degree changes 7.3e-5 rad/s by 1e-6).
"""
from __future__ import annotations

import heapq
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from ..messages import SECONDS_PER_WEEK  # noqa: E402
from .dataflash_raw import RawEpoch  # noqa: E402
from .mavlink_time import gps_to_unix_s  # noqa: E402

m = mavlink2
DATAFLASH_MAGIC = b"\xa3\x95"
OMEGA_IE_RADPS = 7.292115e-5            # WGS-84 Earth rotation rate
_READ_TYPES = ["IMU", "GPS", "GPA", "ATT", "SIM", "POS", "PARM", "ARM", "MSG", "GRXH", "GRXS"]
_FIRMWARE_NAMES = ("ArduCopter", "ArduPlane", "ArduRover", "Rover", "ArduSub", "Blimp", "AntennaTracker")


def is_dataflash(path) -> bool:
    """True when the file starts with a DataFlash record header (0xA3 0x95)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(2) == DATAFLASH_MAGIC
    except OSError:
        return False


@dataclass
class DataFlashLog:
    """The records of a DataFlash log that navigation needs, as numpy arrays (``t_us`` = TimeUS)."""

    path: str
    params: dict = field(default_factory=dict)
    imu: dict = field(default_factory=dict)    # instance -> (N, 7): t_us, gyro xyz rad/s, accel xyz m/s^2
    imu_unhealthy: dict = field(default_factory=dict)
    gps: dict = field(default_factory=dict)    # instance -> (N, 13): t_us, status, GMS ms, GWk, nsats, hdop,
    #                                            lat deg, lng deg, alt m (MSL), spd m/s, gcrs deg, vz m/s, yaw deg
    gpa: dict = field(default_factory=dict)    # instance -> (N, 6): t_us, vdop, hacc, vacc, sacc, ael
    att: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))   # t_us, roll, pitch, yaw (deg)
    sim: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))   # t_us, lat, lng (deg), alt (m)
    pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))   # t_us, lat, lng (deg), alt (m)
    arm: list = field(default_factory=list)                             # (t_us, armed)
    raw_gnss_records: int = 0                                           # GRXH/GRXS records
    # a u-blox's RXM-RAWX as ArduPilot logs it with GPS_RAW_DATA (companion.io.dataflash_raw)
    raw_epochs: list = field(default_factory=list)                      # RawEpoch, in log order
    raw_orphans: int = 0                                                # GRXS without its GRXH, or unreadable
    # a PX4 log's receiver bytes (gps_dump: UBX, or RTCM 3 in PPK mode) as (t_us, bytes) chunks
    raw_stream: list = field(default_factory=list)
    firmware: str = ""                                                  # first MSG naming the firmware

    @property
    def sitl(self) -> bool:
        """A log of ArduPilot's simulator: it has the simulator's SIM_ parameters."""
        return any(k.startswith("SIM_") for k in self.params)

    def imu_rate_hz(self, instance: int = 0) -> float:
        """Median sample rate of one IMU instance (0 when it has fewer than two samples)."""
        a = self.imu.get(instance)
        if a is None or len(a) < 2:
            return 0.0
        d = np.diff(a[:, 0])
        d = d[d > 0]
        return float(1e6 / np.median(d)) if len(d) else 0.0

    def span_s(self) -> tuple[float, float]:
        ts = [a[[0, -1], 0] for a in self.imu.values() if len(a)]
        if not ts:
            return (math.nan, math.nan)
        return (min(t[0] for t in ts) * 1e-6, max(t[1] for t in ts) * 1e-6)


def read_dataflash(path, t_start_s: float | None = None, t_end_s: float | None = None) -> DataFlashLog:
    """One pass over the log with DFReader; records outside [t_start_s, t_end_s] (boot time, s)
    are skipped (parameters are always kept)."""
    from pymavlink import DFReader
    rd = DFReader.DFReader_binary(str(path), zero_time_base=True)
    lo = -math.inf if t_start_s is None else t_start_s * 1e6
    hi = math.inf if t_end_s is None else t_end_s * 1e6
    out = DataFlashLog(str(path))
    imu: dict[int, list] = {}
    gps: dict[int, list] = {}
    gpa: dict[int, list] = {}
    att, sim, pos = [], [], []
    while True:
        r = rd.recv_match(type=_READ_TYPES)
        if r is None:
            break
        t = r.get_type()
        if t == "PARM":
            out.params[r.Name] = float(r.Value)
            continue
        if t == "MSG":
            if not out.firmware and str(r.Message).startswith(_FIRMWARE_NAMES):
                out.firmware = str(r.Message)
            continue
        tu = getattr(r, "TimeUS", None)
        if tu is None or not (lo <= tu <= hi):
            continue
        if t == "IMU":
            i = int(getattr(r, "I", 0))
            if int(getattr(r, "GH", 1)) and int(getattr(r, "AH", 1)):
                imu.setdefault(i, []).append((tu, r.GyrX, r.GyrY, r.GyrZ, r.AccX, r.AccY, r.AccZ))
            else:
                out.imu_unhealthy[i] = out.imu_unhealthy.get(i, 0) + 1
        elif t == "GPS":
            gps.setdefault(int(getattr(r, "I", 0)), []).append(
                (tu, r.Status, r.GMS, r.GWk, r.NSats, r.HDop, r.Lat, r.Lng, r.Alt, r.Spd, r.GCrs,
                 getattr(r, "VZ", 0.0), getattr(r, "Yaw", 0.0)))
        elif t == "GPA":
            gpa.setdefault(int(getattr(r, "I", 0)), []).append(
                (tu, r.VDop, r.HAcc, r.VAcc, r.SAcc, getattr(r, "AEl", 0.0)))
        elif t == "ATT":
            att.append((tu, r.Roll, r.Pitch, r.Yaw))
        elif t == "SIM":
            sim.append((tu, r.Lat, r.Lng, r.Alt))
        elif t == "POS":
            pos.append((tu, r.Lat, r.Lng, r.Alt))
        elif t == "ARM":
            out.arm.append((tu, bool(r.ArmState)))
        elif t in ("GRXH", "GRXS"):
            out.raw_gnss_records += 1
            try:
                _raw_record(out, t, int(tu), r)
            except (AttributeError, TypeError, ValueError, OverflowError):
                out.raw_orphans += 1         # a record of another layout than ArduPilot's
    out.imu = {i: _by_time(v) for i, v in imu.items()}
    out.gps = {i: _by_time(v) for i, v in gps.items()}
    out.gpa = {i: _by_time(v) for i, v in gpa.items()}
    for name, rows in (("att", att), ("sim", sim), ("pos", pos)):
        if rows:
            setattr(out, name, _by_time(rows))
    return out


def _raw_record(out: DataFlashLog, t: str, tu: int, r) -> None:
    """One GRXH (a new epoch) or GRXS (a measurement of the last epoch: the same TimeUS, no more
    than its numMeas; else counted as an orphan, its header lost from a full log buffer)."""
    if t == "GRXH":
        out.raw_epochs.append(RawEpoch(tu, float(r.rcvTime), int(r.week), int(r.leapS), int(r.numMeas),
                                       int(r.recStat)))
        return
    ep = out.raw_epochs[-1] if out.raw_epochs else None
    if ep is None or ep.t_us != tu or len(ep.meas) >= ep.num_meas:
        out.raw_orphans += 1
        return
    ep.meas.append((float(r.prMes), float(r.cpMes), float(r.doMes), int(r.gnss), int(r.sv), int(r.freq),
                    int(r.lock), int(r.cno), int(r.prD), int(r.cpD), int(r.doD), int(r.trk)))


def _by_time(rows) -> np.ndarray:
    a = np.array(rows, float)
    return a[np.argsort(a[:, 0], kind="stable")]


@dataclass(frozen=True)
class AdapterOptions:
    """How DataFlash records become MAVLink messages.  ``None`` = decide from the log."""

    imu_instance: int = 0
    gps_instance: int = 0
    gps_latency_s: float | None = None      # None: SIM_GPSn_LAG_MS in SITL, else 0 (GMS is the epoch)
    earth_rate: bool | None = None          # None: add the Earth's rotation to the gyro in SITL logs
    gps_velocity: bool = True               # pass the GPS horizontal velocity on in GPS_RAW_INT
    leap_seconds: int = 18
    target_system: int = 1
    target_component: int = 1


@dataclass
class TimeBase:
    """Boot time -> GPS time of the log: ``t_gps = t_boot_s + offset_s``."""

    offset_s: float
    latency_s: float                 # GPS fix measured this long before its record's TimeUS
    gms_is_delivery: bool            # SITL: GMS stamps the delivery, not the measurement
    jitter_s: float                  # max |GMS - TimeUS - median| over the log
    n_fixes: int

    def to_gps(self, t_boot_s):
        return t_boot_s + self.offset_s

    def to_boot(self, t_gps):
        return t_gps - self.offset_s

    def as_dict(self) -> dict:
        return {"offset_s": self.offset_s, "gps_latency_s": self.latency_s,
                "gms_is_delivery_time": self.gms_is_delivery, "jitter_s": self.jitter_s, "fixes": self.n_fixes}


def gps_latency_s(log: DataFlashLog, instance: int = 0) -> float:
    """The GPS fix's age at its record's TimeUS from the log's parameters: SITL's
    ``SIM_GPS{n}_LAG_MS`` (``SIM_GPS_LAG_MS`` before 4.5), else ``GPS{n}_DELAY_MS``/``GPS_DELAY_MS``,
    else 0."""
    n = instance + 1
    for k in (f"SIM_GPS{n}_LAG_MS", "SIM_GPS_LAG_MS", f"GPS{n}_DELAY_MS",
              "GPS_DELAY_MS" if n == 1 else f"GPS_DELAY_MS{n}"):
        if k in log.params and log.params[k] > 0:
            return log.params[k] * 1e-3
    return 0.0


def time_base(log: DataFlashLog, opts: AdapterOptions = AdapterOptions()) -> TimeBase | None:
    """The boot-to-GPS offset from the GPS records with a valid week (None: no GPS time in the log)."""
    g = log.gps.get(opts.gps_instance)
    if g is None:
        return None
    ok = (g[:, 3] > 0) & (g[:, 1] >= 2)
    if not np.any(ok):
        return None
    g = g[ok]
    t_gps = g[:, 3] * SECONDS_PER_WEEK + g[:, 2] * 1e-3
    d = t_gps - g[:, 0] * 1e-6
    med = float(np.median(d))
    lat = gps_latency_s(log, opts.gps_instance) if opts.gps_latency_s is None else float(opts.gps_latency_s)
    sitl = log.sitl
    # measurement: boot time TimeUS - latency; GPS time GMS (real receiver) or GMS - latency (SITL)
    offset = med if sitl else med + lat
    return TimeBase(offset, lat, sitl, float(np.max(np.abs(d - med))), int(len(g)))


def _header(msg, opts: AdapterOptions):
    msg._header = m.MAVLink_header(msg.id, srcSystem=opts.target_system, srcComponent=opts.target_component)
    return msg


def _earth_rate_b(att_deg_row, lat_rad: float) -> np.ndarray:
    """omega_ie in body axes: C_n_b omega_ie_n, omega_ie_n = Omega (cos lat, 0, -sin lat)."""
    r, p, y = np.radians(att_deg_row)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    C_b_n = np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                      [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                      [-sp, sr * cp, cr * cp]])
    w_n = OMEGA_IE_RADPS * np.array([math.cos(lat_rad), 0.0, -math.sin(lat_rad)])
    return C_b_n.T @ w_n


def _imu_messages(log: DataFlashLog, opts: AdapterOptions, earth: bool, lat_rad: float):
    imu = log.imu.get(opts.imu_instance, np.zeros((0, 7)))
    att = log.att
    ia = np.searchsorted(att[:, 0], imu[:, 0], side="right") - 1 if len(att) else np.full(len(imu), -1)
    w_cache: dict[int, np.ndarray] = {}
    for k in range(len(imu)):
        t_us, gx, gy, gz, ax, ay, az = imu[k].tolist()
        j = int(ia[k])
        if earth and j >= 0:
            w = w_cache.get(j)
            if w is None:
                w = w_cache[j] = _earth_rate_b(att[j, 1:4], lat_rad)
            gx, gy, gz = gx + w[0], gy + w[1], gz + w[2]
        msg = m.MAVLink_highres_imu_message(int(t_us), ax, ay, az, gx, gy, gz, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                            0x3F, opts.imu_instance)
        yield int(t_us), _ORDER_IMU, _header(msg, opts)


def _attitude_messages(log: DataFlashLog, opts: AdapterOptions):
    for t_us, roll, pitch, yaw in log.att.tolist():
        msg = m.MAVLink_attitude_message(int(t_us // 1000), math.radians(roll), math.radians(pitch),
                                         math.radians(yaw), 0.0, 0.0, 0.0)
        yield int(t_us), _ORDER_ATTITUDE, _header(msg, opts)


def _whole_seconds_ms(span_us: tuple[float, float]) -> range:
    return range(int(span_us[0] // 1_000_000) * 1000, int(span_us[1] // 1000) + 1, 1000)


def _system_time_messages(span_us, tb: TimeBase, opts: AdapterOptions):
    """SYSTEM_TIME once a second, exact: the UTC of a whole boot millisecond (no quantisation)."""
    for t_ms in _whole_seconds_ms(span_us):
        t_unix_us = round(gps_to_unix_s(tb.to_gps(t_ms * 1e-3), opts.leap_seconds) * 1e6)
        yield t_ms * 1000, _ORDER_SYSTEM_TIME, _header(m.MAVLink_system_time_message(t_unix_us, t_ms), opts)


def vehicle_type(log: DataFlashLog) -> int:
    """MAV_TYPE from the firmware name in the log's messages (ArduCopter, ArduPlane, Rover, ArduSub);
    a Rover with FRAME_CLASS 2 is a boat."""
    fw = log.firmware
    if "Rover" in fw:
        return m.MAV_TYPE_SURFACE_BOAT if log.params.get("FRAME_CLASS") == 2 else m.MAV_TYPE_GROUND_ROVER
    if "Plane" in fw:
        return m.MAV_TYPE_FIXED_WING
    if "Sub" in fw:
        return m.MAV_TYPE_SUBMARINE
    return m.MAV_TYPE_QUADROTOR


def _heartbeat_messages(log: DataFlashLog, span_us, opts: AdapterOptions):
    """HEARTBEAT once a second with the armed state of the ARM records; before the first one the
    log was armed unless that record is an arming (ArduPilot logs from arming unless LOG_DISARMED)."""
    arm = sorted(log.arm)
    armed = not arm[0][1] if arm else True
    vt = vehicle_type(log)
    j = 0
    for t_ms in _whole_seconds_ms(span_us):
        while j < len(arm) and arm[j][0] <= t_ms * 1000:
            armed = arm[j][1]
            j += 1
        hb = m.MAVLink_heartbeat_message(vt, m.MAV_AUTOPILOT_ARDUPILOTMEGA, m.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0,
                                         0, m.MAV_STATE_ACTIVE if armed else m.MAV_STATE_STANDBY, 3)
        yield t_ms * 1000, _ORDER_HEARTBEAT, _header(hb, opts)


def _mm(x: float, scale: float = 1e3) -> int:
    return int(round(x * scale))


def _gps_messages(log: DataFlashLog, tb: TimeBase, opts: AdapterOptions):
    """GPS (+ the newest GPA of the same instance, if under 0.5 s old) -> GPS_RAW_INT stamped with
    the fix's own GPS time (UNIX us), fed at the record's TimeUS."""
    gps = log.gps.get(opts.gps_instance, np.zeros((0, 13)))
    gpa = log.gpa.get(opts.gps_instance, np.zeros((0, 6)))
    ja = np.searchsorted(gpa[:, 0], gps[:, 0], side="right") - 1 if len(gpa) else np.full(len(gps), -1)
    shift = tb.latency_s if tb.gms_is_delivery else 0.0
    for k, (t_us, status, gms, gwk, nsats, hdop, lat, lng, alt, spd, gcrs, _vz, _yaw) in enumerate(gps.tolist()):
        if gwk <= 0:
            continue
        t_gps = gwk * SECONDS_PER_WEEK + gms * 1e-3 - shift
        vdop = hacc = vacc = sacc = ael = 0.0
        j = int(ja[k])
        if j >= 0 and t_us - gpa[j, 0] < 0.5e6:
            _, vdop, hacc, vacc, sacc, ael = gpa[j].tolist()
        vel, cog = (_mm(spd, 100), _mm(gcrs % 360.0, 100)) if opts.gps_velocity else (65535, 65535)
        msg = m.MAVLink_gps_raw_int_message(
            round(gps_to_unix_s(t_gps, opts.leap_seconds) * 1e6), int(status), _mm(lat, 1e7), _mm(lng, 1e7),
            _mm(alt), min(_mm(hdop, 100), 65535), min(_mm(vdop, 100), 65535) if vdop > 0 else 65535, vel, cog,
            int(nsats), _mm(ael), _mm(hacc), _mm(vacc), _mm(sacc), 0, 0)
        yield int(t_us), _ORDER_GPS, _header(msg, opts)


# ties at one TimeUS: the clock first, then attitude and state, the IMU sample, the fix
_ORDER_SYSTEM_TIME, _ORDER_ATTITUDE, _ORDER_HEARTBEAT, _ORDER_IMU, _ORDER_GPS = range(5)


def iter_mavlink_messages(log: DataFlashLog, opts: AdapterOptions = AdapterOptions(),
                          tb: TimeBase | None = None) -> Iterator[tuple[int, object]]:
    """``(t_boot_us, message)`` in boot-time order, lazily (a long log's messages are never all in
    memory): what the autopilot would have sent the companion, built from the log's records (see
    the module docstring).  Each source is in time order (:func:`read_dataflash` sorts them); ties
    go the clock first, then attitude and state, the IMU sample, the fix."""
    tb = tb or time_base(log, opts)
    imu = log.imu.get(opts.imu_instance, np.zeros((0, 7)))
    gps = log.gps.get(opts.gps_instance, np.zeros((0, 13)))
    span = (imu[0, 0], imu[-1, 0]) if len(imu) else (0.0, -1.0)
    earth = log.sitl if opts.earth_rate is None else bool(opts.earth_rate)
    lat0 = math.radians(float(gps[0, 6])) if len(gps) else 0.0
    sources = [_imu_messages(log, opts, earth, lat0), _attitude_messages(log, opts),
               _heartbeat_messages(log, span, opts)]
    if tb is not None:
        sources += [_system_time_messages(span, tb, opts), _gps_messages(log, tb, opts)]
    for t, _, msg in heapq.merge(*sources, key=lambda x: (x[0], x[1])):
        yield t, msg


def mavlink_messages(log: DataFlashLog, opts: AdapterOptions = AdapterOptions(),
                     tb: TimeBase | None = None) -> list[tuple[int, object]]:
    """:func:`iter_mavlink_messages` as a list."""
    return list(iter_mavlink_messages(log, opts, tb))


def lever_arm_from_params(log: DataFlashLog, gps_instance: int = 0, imu_instance: int = 0):
    """Antenna minus IMU position in body FRD (m) from GPS_POS{n}_X/Y/Z and INS_POS{n}_X/Y/Z, or None
    when the log has neither."""
    n, i = gps_instance + 1, imu_instance + 1
    g = [log.params.get(f"GPS_POS{n}_{a}", log.params.get(f"GPS{n}_POS_{a}")) for a in "XYZ"]
    s = [log.params.get(f"INS_POS{i}_{a}") for a in "XYZ"]
    if all(v is None for v in g + s):
        return None
    return tuple(float(g[k] or 0.0) - float(s[k] or 0.0) for k in range(3))


__all__ = ["is_dataflash", "read_dataflash", "DataFlashLog", "AdapterOptions", "TimeBase", "time_base",
           "gps_latency_s", "mavlink_messages", "iter_mavlink_messages", "lever_arm_from_params", "vehicle_type", "DATAFLASH_MAGIC"]
