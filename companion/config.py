"""Typed configuration of the companion service, read from TOML.

Every section is a frozen dataclass; numbers carry their unit in the name.  :func:`load_config`
validates as it builds: unknown keys, wrong types, values outside their range or not among the
allowed choices raise :class:`ConfigError` naming the file and the dotted key
(``companion.toml: corrections.ntrip.version: must be one of 1, 2, got 3``).  Everything has a
default, so an empty file is a valid configuration (MAVLink on ``udpin:127.0.0.1:14550``, no
corrections, vision output).

Layout (see :func:`example_config_toml` for a complete commented file)::

    [mavlink]      link to the autopilot, stream rates, identity
    [gnss]         where raw GNSS comes from: tunnelled through the autopilot (SERIAL_CONTROL),
                   a serial port on the companion, or 'none' (GPS_RAW_INT, loosely coupled)
    [gnss.serial]  port, baud
    [corrections]  source of RTCM 3: ntrip | serial | mqtt | file | none, forwarding to the autopilot
    [corrections.ntrip] / [corrections.serial] / [corrections.mqtt] / [corrections.file]
    [output]       what is injected into the autopilot and when it is good enough to inject
    [filter]       noise densities, gates, which measurements (-> EngineConfig / ProcessNoise)
    [log]          field log directory, rotation size, fsync interval
    [telemetry]    MQTT telemetry (solution and health JSON)

TOML has no null: an optional value (``corrections.base_position_ecef_m``) is simply left out.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from .io.mavlink import IMU_CLUSTER_STREAMS


class ConfigError(ValueError):
    """A configuration file is invalid; the message names the file and the key."""


def _f(default, *, choices=None, min=None, max=None, min_exclusive=False, doc=""):
    """A dataclass field with validation metadata (choices, range) and a one-line doc for the example."""
    md = {"choices": choices, "min": min, "max": max, "min_exclusive": min_exclusive, "doc": doc}
    if isinstance(default, (list, dict)):
        raise TypeError("use tuples for sequence defaults")
    return field(default=default, metadata=md)


# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class MavlinkConfig:
    connection: str = _f("udpin:127.0.0.1:14550", doc="pymavlink/MAVProxy connection string: "
                         "'udpin:HOST:PORT', 'udpout:HOST:PORT', 'tcp:HOST:PORT', '/dev/ttyACM0,921600'")
    source_system: int = _f(1, min=1, max=255, doc="our MAVLink system id (the vehicle's, companions share it)")
    source_component: int = _f(191, min=1, max=255, doc="our component id: 191 = MAV_COMP_ID_ONBOARD_COMPUTER")
    target_system: int = _f(1, min=1, max=255, doc="the autopilot's system id")
    target_component: int = _f(1, min=1, max=255, doc="the autopilot's component id (1 = MAV_COMP_ID_AUTOPILOT1)")
    imu_message: str = _f("auto", choices=("auto", "HIGHRES_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3"),
                          doc="IMU stream to fuse; 'auto' locks onto the first one that arrives")
    imu_rate_hz: float = _f(200.0, min=1.0, max=2000.0, doc="requested IMU message rate")
    imu_cluster: tuple[str, ...] = _f((), choices=IMU_CLUSTER_STREAMS,
                                      doc="fuse several IMUs (first = primary, its time grid), dropping a "
                                          "faulty one, e.g. [\"RAW_IMU\", \"SCALED_IMU2\", \"SCALED_IMU3\"] "
                                          "(ArduPilot) or [\"HIGHRES_IMU:0\", \"HIGHRES_IMU:1\"]; empty = "
                                          "imu_message alone")
    system_time_rate_hz: float = _f(1.0, min=0.1, max=50.0)
    gps_raw_rate_hz: float = _f(5.0, min=0.0, max=50.0, doc="GPS_RAW_INT rate (0 = do not request)")
    attitude_rate_hz: float = _f(10.0, min=0.0, max=400.0, doc="ATTITUDE rate (0 = do not request)")
    extended_sys_state_rate_hz: float = _f(1.0, min=0.0, max=50.0,
                                           doc="EXTENDED_SYS_STATE rate (landed state, for ZUPT/NHC; 0 = do not request)")
    heartbeat_interval_s: float = _f(1.0, min=0.1, max=10.0)
    link_timeout_s: float = _f(3.0, min=0.5, max=60.0, doc="no autopilot HEARTBEAT for this long = link lost")
    timesync_interval_s: float = _f(1.0, min=0.0, max=60.0, doc="TIMESYNC requests (0 = only answer)")
    interval_retry_s: float = _f(1.0, min=0.1, max=30.0, doc="re-send an unacknowledged SET_MESSAGE_INTERVAL")


@dataclass(frozen=True, slots=True)
class SerialPortConfig:
    port: str = _f("/dev/ttyUSB0")
    baud: int = _f(115200, min=300, max=12_000_000)


@dataclass(frozen=True, slots=True)
class GnssConfig:
    source: str = _f("mavlink_serial_control", choices=("mavlink_serial_control", "serial", "none"),
                     doc="raw GNSS (UBX) through the autopilot's GPS port, a local serial port, "
                         "or 'none' = GPS_RAW_INT (loose coupling)")
    serial_control_device: str = _f("GPS1", choices=("GPS1", "GPS2"))
    serial_control_poll_interval_s: float = _f(0.02, min=0.002, max=1.0,
                                               doc="SERIAL_CONTROL poll period (ArduPilot only answers requests)")
    serial_control_baud: int = _f(0, min=0, max=12_000_000, doc="0 = leave the port's baud rate alone")
    serial: SerialPortConfig = field(default_factory=SerialPortConfig)
    lever_arm_b_m: tuple[float, float, float] = _f((0.0, 0.0, 0.0),
                                                   doc="IMU to antenna phase centre, body FRD, m")
    moving_baseline_b_m: tuple[float, float, float] | None = _f(
        None, doc="dual-antenna heading: body FRD vector (m) from the moving-base antenna to the antenna "
                  "of the receiver that outputs UBX NAV-RELPOSNED; unset = NAV-RELPOSNED not used")
    baseline_length_tol_m: float = _f(0.03, min=0.0, doc="a NAV-RELPOSNED length further than this (+3 sigma) "
                                      "from the installed one is a wrong carrier fix and is rejected")
    gps_raw_yaw_sigma_deg: float = _f(1.0, min=0.0, doc="1-sigma of the GPS yaw in GPS_RAW_INT (an autopilot "
                                      "with a dual-antenna GPS fills it); 0 = do not fuse it")
    leap_seconds: int = _f(18, min=0, max=100, doc="GPS - UTC (18 s since 2017-01-01)")


@dataclass(frozen=True, slots=True)
class NtripConfig:
    host: str = _f("127.0.0.1")
    port: int = _f(2101, min=1, max=65535)
    mountpoint: str = _f("")
    user: str = _f("")
    password: str = _f("")
    version: int = _f(2, choices=(1, 2), doc="NTRIP revision: 1 (ICY 200 OK) or 2 (HTTP/1.1, chunked)")
    gga_interval_s: float = _f(0.0, min=0.0, max=600.0, doc="upload GGA this often (network RTK); 0 = never")
    timeout_s: float = _f(10.0, min=0.5, max=300.0, doc="no data for this long = reconnect")


@dataclass(frozen=True, slots=True)
class CorrectionsMqttConfig:
    host: str = _f("127.0.0.1")
    port: int = _f(1883, min=1, max=65535)
    topic: str = _f("rtcm/base")


@dataclass(frozen=True, slots=True)
class CorrectionsFileConfig:
    path: str = _f("")
    realtime: bool = _f(True, doc="replay at the recording's pace (rate_bps) or as fast as possible")
    rate_bps: float = _f(2000.0, min=1.0, doc="replay rate in bytes per second when realtime")
    loop: bool = _f(False)


@dataclass(frozen=True, slots=True)
class CorrectionsConfig:
    source: str = _f("none", choices=("ntrip", "serial", "mqtt", "file", "none"))
    forward_to_autopilot: bool = _f(False, doc="also send the RTCM frames to the autopilot as GPS_RTCM_DATA")
    base_position_ecef_m: tuple[float, float, float] | None = _f(
        None, doc="override the base station position (ECEF, m); default: from RTCM 1005/1006")
    ntrip: NtripConfig = field(default_factory=NtripConfig)
    serial: SerialPortConfig = field(default_factory=lambda: SerialPortConfig("/dev/ttyUSB1", 57600))
    mqtt: CorrectionsMqttConfig = field(default_factory=CorrectionsMqttConfig)
    file: CorrectionsFileConfig = field(default_factory=CorrectionsFileConfig)


@dataclass(frozen=True, slots=True)
class OutputConfig:
    mode: str = _f("vision", choices=("vision", "odometry", "gps_input"),
                   doc="VISION_POSITION_ESTIMATE, ODOMETRY (EK3_SRC ExternalNav) or GPS_INPUT (GPS_TYPE=14)")
    rate_hz: float = _f(10.0, min=0.1, max=50.0)
    set_ekf_origin: bool = _f(True, doc="send SET_GPS_GLOBAL_ORIGIN before the first vision/odometry output")
    max_sigma_h_m: float = _f(5.0, min=0.0, min_exclusive=True, doc="do not inject worse than this (1-sigma)")
    max_sigma_v_m: float = _f(10.0, min=0.0, min_exclusive=True)
    geoid_undulation_m: float = _f(0.0, min=-150.0, max=150.0,
                                   doc="N = ellipsoid - MSL height at the site, for GPS_INPUT's MSL altitude")
    gps_input_id: int = _f(0, min=0, max=1)


@dataclass(frozen=True, slots=True)
class FilterConfig:
    """Maps onto :class:`companion.nav.filter.ProcessNoise` and :class:`companion.nav.engine.EngineConfig`.

    Defaults are MEMS flight-controller class (ICM-4xxxx): starting points, not tuning."""
    gyro_arw_rad_per_sqrt_s: float = _f(3.0e-4, min=0.0, min_exclusive=True)
    accel_vrw_mps_per_sqrt_s: float = _f(3.0e-3, min=0.0, min_exclusive=True)
    gyro_bias_rw_radps_per_sqrt_s: float = _f(1.0e-5, min=0.0)
    accel_bias_rw_mps2_per_sqrt_s: float = _f(1.0e-4, min=0.0)
    clock_bias_psd_m2ps: float = _f(0.1, min=0.0)
    clock_drift_psd_m2ps3: float = _f(0.01, min=0.0)
    use_pseudorange: bool = _f(True)
    use_dgps: bool = _f(True)
    use_tdcp: bool = _f(True)
    use_doppler: bool = _f(False)
    use_loose: bool = _f(False)
    elevation_mask_deg: float = _f(10.0, min=0.0, max=90.0)
    gate_probability: float = _f(0.999, min=0.5, max=1.0, min_exclusive=False)
    sigma_doppler_mps: float = _f(0.1, min=0.0, min_exclusive=True)
    sigma_phase_m: float = _f(0.005, min=0.0, min_exclusive=True)
    sigma_tdcp_floor_mps: float = _f(0.01, min=0.0)
    sigma_pseudorange_floor_m: float = _f(0.0, min=0.0)
    tdcp_max_interval_s: float = _f(1.5, min=0.0, min_exclusive=True)
    tdcp_base_correction: str = _f("auto", choices=("auto", "off"))
    history_s: float = _f(2.0, min=0.1, max=60.0)
    coasting_after_s: float = _f(3.0, min=0.1)
    untrusted_sigma_h_m: float = _f(50.0, min=0.0, min_exclusive=True)
    clock_jump_sigmas: float = _f(8.0, min=0.0, min_exclusive=True,
                                  doc="common pseudorange step, in clock sigmas, that re-seeds the clock")
    clock_jump_min_m: float = _f(30.0, min=0.0)
    sigma_phase_elevation_scaling: bool = _f(False, doc="carrier noise x 1/sin(elevation)")
    pseudorange_correlation_time_s: float = _f(0.0, min=0.0, doc="multipath correlation time (0 = white)")
    zupt_enabled: bool = _f(False)
    zupt_window_s: float = _f(0.5, min=0.0, min_exclusive=True)
    zupt_accel_std_mps2: float = _f(0.05, min=0.0, min_exclusive=True)
    zupt_gyro_std_radps: float = _f(0.005, min=0.0, min_exclusive=True)
    zupt_max_speed_mps: float = _f(0.5, min=0.0, min_exclusive=True)
    zupt_sigma_mps: float = _f(0.02, min=0.0, min_exclusive=True)
    zaru_sigma_floor_radps: float = _f(2e-4, min=0.0)
    nhc_enabled: bool = _f(False, doc="non-holonomic constraint (seed 002) while on the ground: a rover or "
                           "boat always, an aircraft when landed (EXTENDED_SYS_STATE) or disarmed")
    nhc_sigma_lateral_mps: float = _f(0.1, min=0.0, min_exclusive=True)
    nhc_sigma_vertical_mps: float = _f(0.1, min=0.0, min_exclusive=True)
    nhc_min_speed_mps: float = _f(1.0, min=0.0)
    course_alignment_enabled: bool = _f(False, doc="on the ground, take the heading from the GNSS course over "
                                        "ground once driving straight at speed (a rover or car without a usable "
                                        "compass; never for a boat or anything that crabs)")
    course_alignment_min_speed_mps: float = _f(3.0, min=0.5)
    course_alignment_max_yaw_rate_radps: float = _f(0.05, min=0.0, min_exclusive=True)
    course_alignment_slip_sigma_rad: float = _f(0.0175, min=0.0, doc="side-slip while driving straight (1-sigma)")
    course_alignment_reset_above_rad: float = _f(0.26, min=0.0, min_exclusive=True,
                                                 doc="heading uncertainty or disagreement beyond which the "
                                                 "heading is reset to the course instead of fused")
    course_alignment_epochs: int = _f(5, min=1, max=100)
    gravity_gradient_refresh_m: float = _f(200.0, min=0.0, min_exclusive=True)

    def process_noise(self):
        from .nav.filter import ProcessNoise
        return ProcessNoise(
            gyro_arw_rad_per_sqrt_s=self.gyro_arw_rad_per_sqrt_s,
            accel_vrw_mps_per_sqrt_s=self.accel_vrw_mps_per_sqrt_s,
            gyro_bias_rw_radps_per_sqrt_s=self.gyro_bias_rw_radps_per_sqrt_s,
            accel_bias_rw_mps2_per_sqrt_s=self.accel_bias_rw_mps2_per_sqrt_s,
            clock_bias_psd_m2ps=self.clock_bias_psd_m2ps,
            clock_drift_psd_m2ps3=self.clock_drift_psd_m2ps3)

    def engine_config(self, lever_arm_b_m=(0.0, 0.0, 0.0)):
        """The engine configuration.  Keys the engine does not (or no longer) know are left out
        with a warning rather than breaking start-up (tests/test_config.py flags the drift)."""
        import logging
        from .nav.engine import EngineConfig
        known = {f.name for f in dataclasses.fields(EngineConfig)}
        kw = {}
        for f in dataclasses.fields(self):
            if f.name in _NOISE_FIELDS:
                continue
            if f.name in known:
                kw[f.name] = getattr(self, f.name)
            else:
                logging.getLogger(__name__).warning("filter.%s is not an EngineConfig field; ignored", f.name)
        return EngineConfig(noise=self.process_noise(), lever_arm_b_m=tuple(lever_arm_b_m), **kw)


_NOISE_FIELDS = {"gyro_arw_rad_per_sqrt_s", "accel_vrw_mps_per_sqrt_s", "gyro_bias_rw_radps_per_sqrt_s",
                 "accel_bias_rw_mps2_per_sqrt_s", "clock_bias_psd_m2ps", "clock_drift_psd_m2ps3"}


@dataclass(frozen=True, slots=True)
class LogConfig:
    enabled: bool = _f(True)
    dir: str = _f("logs")
    max_bytes: int = _f(64 * 1024 * 1024, min=4096)
    fsync_interval_s: float = _f(1.0, min=0.0)


@dataclass(frozen=True, slots=True)
class TelemetryConfig:
    enabled: bool = _f(False)
    host: str = _f("127.0.0.1")
    port: int = _f(1883, min=1, max=65535)
    topic_prefix: str = _f("companion", doc="topics <prefix>/solution and <prefix>/health")
    rate_hz: float = _f(1.0, min=0.01, max=50.0)


@dataclass(frozen=True, slots=True)
class Config:
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    corrections: CorrectionsConfig = field(default_factory=CorrectionsConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    log: LogConfig = field(default_factory=LogConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    source_path: str = field(default="", compare=False, metadata={"internal": True})

    def engine_config(self):
        """The nav engine configuration (filter section + the GNSS installation)."""
        g = self.gnss
        return dataclasses.replace(self.filter.engine_config(g.lever_arm_b_m),
                                   moving_baseline_b_m=g.moving_baseline_b_m,
                                   baseline_length_tol_m=g.baseline_length_tol_m)

    def to_toml(self, comments: bool = True) -> str:
        return _to_toml(self, comments)


# ---------------------------------------------------------------------------------------------
# building and validation

def _is_dataclass_type(tp) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _check_value(value: Any, tp, key: str, where: str, md: dict):
    def err(msg):
        raise ConfigError(f"{where}: {key}: {msg}")

    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is typing.Union or (origin is not None and type(None) in args):
        inner = [a for a in args if a is not type(None)]
        if value is None:
            return None
        return _check_value(value, inner[0], key, where, md)
    if origin is tuple and len(args) == 2 and args[1] is Ellipsis:       # tuple[X, ...]: any length
        if not isinstance(value, (list, tuple)):
            err(f"expected an array, got {value!r}")
        out = tuple(_check_value(v, args[0], f"{key}[{i}]", where, md) for i, v in enumerate(value))
        if len(set(out)) != len(out):
            err(f"duplicate entries in {list(out)!r}")
        return out
    if origin is tuple:
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            err(f"expected an array of {len(args)} numbers, got {value!r}")
        return tuple(_check_value(v, a, f"{key}[{i}]", where, {}) for i, (v, a) in enumerate(zip(value, args)))
    if tp is bool:
        if not isinstance(value, bool):
            err(f"expected true or false, got {value!r}")
    elif tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            err(f"expected an integer, got {value!r}")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            err(f"expected a number, got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            err(f"must be finite, got {value!r}")
    elif tp is str:
        if not isinstance(value, str):
            err(f"expected a string, got {value!r}")
    choices = md.get("choices")
    if choices is not None and value not in choices:
        err(f"must be one of {', '.join(map(str, choices))}, got {value!r}")
    lo, hi = md.get("min"), md.get("max")
    if lo is not None:
        if md.get("min_exclusive") and not value > lo:
            err(f"must be > {lo}, got {value!r}")
        if value < lo:
            err(f"must be >= {lo}, got {value!r}")
    if hi is not None and value > hi:
        err(f"must be <= {hi}, got {value!r}")
    return value


def _build(cls, table: dict, prefix: str, where: str):
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: {prefix.rstrip('.') or '<root>'}: expected a table")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key{'s' if len(unknown) > 1 else ''} "
                          f"{', '.join(prefix + u for u in unknown)} "
                          f"(known: {', '.join(prefix + k for k in fields)})")
    kw = {}
    for name, f in fields.items():
        if name not in table:
            continue
        tp = hints[name]
        if _is_dataclass_type(tp):
            kw[name] = _build(tp, table[name], f"{prefix}{name}.", where)
        else:
            kw[name] = _check_value(table[name], tp, prefix + name, where, dict(f.metadata))
    obj = cls(**kw)
    # validate defaults too (a default outside a range is a bug here, not the user's)
    return obj


def _cross_checks(cfg: Config, where: str) -> None:
    c = cfg.corrections
    if c.source == "ntrip" and not c.ntrip.mountpoint:
        raise ConfigError(f"{where}: corrections.ntrip.mountpoint: required when corrections.source = 'ntrip'")
    if c.source == "file" and not c.file.path:
        raise ConfigError(f"{where}: corrections.file.path: required when corrections.source = 'file'")
    if cfg.output.rate_hz > 50.0:
        raise ConfigError(f"{where}: output.rate_hz: must be <= 50")


def config_from_dict(data: dict, where: str = "<config>") -> Config:
    """Build and validate a :class:`Config` from an already parsed TOML document."""
    cfg = _build(Config, data, "", where)
    _cross_checks(cfg, where)
    return dataclasses.replace(cfg, source_path=where)


def load_config(path: str | Path) -> Config:
    """Read, parse and validate a TOML configuration file."""
    p = Path(path)
    try:
        with p.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{p}: configuration file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    return config_from_dict(data, str(p))


def loads_config(text: str, where: str = "<string>") -> Config:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where}: not valid TOML: {exc}") from None
    return config_from_dict(data, where)


# ---------------------------------------------------------------------------------------------
# writing

def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        r = repr(v)
        return r if ("." in r or "e" in r or "inf" in r or "nan" in r) else r + ".0"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def _to_toml(obj, comments: bool) -> str:
    lines: list[str] = []

    def section(o, name: str):
        hints = typing.get_type_hints(type(o))
        scalars, tables = [], []
        for f in dataclasses.fields(o):
            if f.metadata.get("internal"):
                continue
            (tables if _is_dataclass_type(hints[f.name]) else scalars).append(f)
        if name:
            lines.append(f"[{name}]")
        for f in scalars:
            v = getattr(o, f.name)
            doc = f.metadata.get("doc", "")
            if comments and doc:
                lines.append(f"# {doc}")
            if v is None:
                lines.append(f"# {f.name} = ...   (optional, not set)")
            else:
                lines.append(f"{f.name} = {_toml_value(v)}")
        lines.append("")
        for f in tables:
            section(getattr(o, f.name), f"{name}.{f.name}" if name else f.name)

    section(obj, "")
    return "\n".join(lines).strip() + "\n"


def example_config_toml() -> str:
    """A complete configuration file with every key at its default, commented."""
    head = ("# companion configuration (TOML).  Every key is optional; shown are the defaults.\n"
            "# Units are in the key names.  Unknown keys are errors.\n\n")
    return head + Config().to_toml(comments=True)


__all__ = ["Config", "ConfigError", "MavlinkConfig", "GnssConfig", "SerialPortConfig", "NtripConfig",
           "CorrectionsConfig", "CorrectionsMqttConfig", "CorrectionsFileConfig", "OutputConfig",
           "FilterConfig", "LogConfig", "TelemetryConfig", "load_config", "loads_config",
           "config_from_dict", "example_config_toml"]
