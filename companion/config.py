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
    [nmea]         NMEA GGA/RMC/GST to UDP or a serial port
    [status_page]  the live status page (HTTP, loopback by default)

Every number has a range (``companion.toml: log.fsync_interval_s: must be <= 60.0, got 1e+300``);
NaN and infinity are refused; an unknown key gets a suggestion (``did you mean ...?``); a directory,
an unreadable or a binary file is a :class:`ConfigError` like any other, never a traceback.

Secrets (``secret=True`` fields: ``corrections.ntrip.password``) never leave in clear:
:func:`redacted` and ``Config.to_toml(redact=True)`` write them as ``***`` (the field log's copy);
:func:`secrets_readable_by_others` warns when the file that holds one is not private.

This module imports nothing heavy (standard library only), so ``companion config check`` and a
start-up with a bad file answer before numpy, scipy or pymavlink are loaded.

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

from .io.imu_streams import IMU_CLUSTER_STREAMS, IMU_MESSAGES      # plain names, no pymavlink

REDACTED = "***"


class ConfigError(ValueError):
    """A configuration file is invalid; the message names the file and the key."""


def _f(default, *, choices=None, min=None, max=None, min_exclusive=False, norm=None, secret=False, doc=""):
    """A dataclass field with validation metadata and a one-line doc for the example.

    ``min``/``max`` bound a number, or every element of a vector; ``norm = (lo, hi)`` bounds a
    vector's length; ``secret`` fields are replaced by ``***`` in :func:`redacted` and in logs."""
    md = {"choices": choices, "min": min, "max": max, "min_exclusive": min_exclusive, "norm": norm,
          "secret": secret, "doc": doc}
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
    imu_message: str = _f("auto", choices=("auto",) + IMU_MESSAGES,
                          doc="IMU stream to fuse; 'auto' locks onto the first one that arrives")
    imu_rate_hz: float = _f(200.0, min=1.0, max=2000.0, doc="requested IMU message rate")
    imu_accel_full_scale_mps2: float = _f(0.0, min=0.0, max=2000.0,
                                          doc="accelerometer full scale for clip detection; 0 = per "
                                          "message type (16 g: PX4 HIGHRES_IMU, ArduPilot RAW_IMU/SCALED_IMU*)")
    imu_gyro_full_scale_radps: float = _f(0.0, min=0.0, max=200.0,
                                          doc="gyro full scale for clip detection; 0 = per message type "
                                          "(2000 deg/s HIGHRES_IMU, 32.767 rad/s int16 mrad/s fields)")
    autopilot_heading_on_ground: bool = _f(False, doc="on the ground, keep the heading on the autopilot's "
                                           "ATTITUDE yaw (5 deg, followed ten times a second): only where that yaw is its compass "
                                           "(EK3_SRC1_YAW 1), never when it is ours (ExternalNav); a wrong "
                                           "compass is then trusted too (deploy/ turns it on for ArduPilot)")
    # a compass heading on a drone is good to a few degrees when it is right (calibrated, away from
    # the motor currents), and can be wrong by anything when it is not (a steel deck, a magnet, a
    # bad calibration); 5 deg describes the good case, the Gaussian-sum yaw estimator
    # (companion.nav.yaw_gsf) catches the bad one and the ATTITUDE yaw is dropped for the run
    attitude_yaw_sigma_deg: float = _f(5.0, min=0.0, max=180.0, min_exclusive=True,
                                       doc="1-sigma of the autopilot's ATTITUDE yaw (its compass) when it "
                                           "initialises our heading; checked against the yaw from motion")
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
    rx_pacing: bool = _f(True, doc="between reads the link sleeps until shortly before the IMU sample that "
                         "opens the next output slot and reads what came meanwhile in one go: the same "
                         "estimates at the same latency with fewer wake-ups (companion.io.rx_pacing; "
                         "`sitl fly`: 19-24 % less CPU); false = every datagram on arrival")
    rx_pacing_margin_s: float = _f(0.004, min=0.0, max=0.1, doc="how early the reader wakes before that "
                                   "sample is due (the stream's jitter)")
    signing_key_file: str = _f("", doc="MAVLink 2 signing key file (mode 0600): 64 hex characters = the "
                               "32-byte key of SETUP_SIGNING, other text = a passphrase, key = its SHA-256 "
                               "(MAVProxy 'signing setup'); `companion signing setup --key-file F` makes one; "
                               "empty = no signing")
    parameters: bool = _f(True, doc="answer the MAVLink parameter protocol on our component (CC_* "
                          "parameters: lever arm, moving baseline, output mode, rate and thresholds; "
                          "companion.io.mavlink_params), so Mission Planner / QGC can read and set them")
    parameters_persist: bool = _f(True, doc="write a parameter the ground station set into this file "
                                  "(rewritten as `companion config example` writes it: your own comments go; "
                                  "the file before the first change is kept as FILE.bak)")
    signing_required: bool = _f(False, doc="with a key: drop (and count) unsigned input; false = accept it "
                                "(an autopilot without signing, e.g. PX4 v1.15), still signing ours. Badly "
                                "signed input is always dropped")


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
    serial_control_claim: str = _f("detect", choices=("detect", "always"),
                                   doc="'detect': lock the autopilot's GPS port only for short probes and keep "
                                   "it only while RXM-RAWX arrives (its GPS driver has it otherwise); "
                                   "'always': lock it from the start (a port with GPSn_TYPE 0 only)")
    serial_control_probe_s: float = _f(3.0, min=0.5, max=30.0,
                                       doc="probe window; ArduPilot re-detects its GPS (~9 s without) "
                                       "after a lock longer than 4 s")
    serial_control_release_after_s: float = _f(10.0, min=1.0, max=600.0,
                                               doc="no RXM-RAWX epoch for this long = give the port back")
    serial_control_retry_max_s: float = _f(600.0, min=5.0, max=86400.0,
                                           doc="longest wait between probes (back-off from 5 s, doubling); "
                                           "each probe freezes the autopilot's GPS for the probe window")
    serial_control_probe_armed: bool = _f(False, doc="probe while the vehicle is armed (interrupts the "
                                          "autopilot's GPS for the probe window in flight)")
    serial_control_enable_sfrbx: bool = _f(True, doc="once claimed, switch UBX RXM-SFRBX on (volatile "
                                           "CFG-MSG; ArduPilot's driver disables frames it does not parse)")
    serial: SerialPortConfig = field(default_factory=SerialPortConfig)
    lever_arm_b_m: tuple[float, float, float] = _f((0.0, 0.0, 0.0), min=-20.0, max=20.0,
                                                   doc="IMU to antenna phase centre, body FRD, m")
    moving_baseline_b_m: tuple[float, float, float] | None = _f(
        None, min=-100.0, max=100.0, norm=(0.05, 100.0),
        doc="dual-antenna heading: body FRD vector (m) from the moving-base antenna to the antenna "
            "of the receiver that outputs UBX NAV-RELPOSNED; unset = NAV-RELPOSNED not used")
    baseline_length_tol_m: float = _f(0.03, min=0.0, max=10.0,
                                      doc="a NAV-RELPOSNED length further than this (+3 sigma) "
                                      "from the installed one is a wrong carrier fix and is rejected")
    gps_raw_latency_s: float = _f(0.0, min=0.0, max=1.0,
                                  doc="receiver output latency taken off GPS_RAW_INT time_usec (ArduPilot "
                                  "stamps the fix when its driver got it; u-blox: 0.05-0.1 s)")
    broadcast_klobuchar: bool = _f(True, doc="use the Klobuchar coefficients of the navigation message "
                                   "(subframe 4 page 18) in the standalone pseudorange models")
    gps_raw_yaw_sigma_deg: float = _f(1.0, min=0.0, max=90.0,
                                      doc="1-sigma of the GPS yaw in GPS_RAW_INT (an autopilot "
                                      "with a dual-antenna GPS fills it); 0 = do not fuse it")
    leap_seconds: int = _f(18, min=0, max=100, doc="GPS - UTC (18 s since 2017-01-01)")
    max_rate_bps: float = _f(256000.0, min=1000.0, max=1e8,
                             doc="UBX from a local serial port beyond this byte rate is dropped (counted)")


@dataclass(frozen=True, slots=True)
class NtripConfig:
    host: str = _f("127.0.0.1")
    port: int = _f(2101, min=1, max=65535)
    mountpoint: str = _f("")
    user: str = _f("")
    password: str = _f("", secret=True, doc="NTRIP caster password (never written to logs)")
    version: int = _f(2, choices=(1, 2), doc="NTRIP revision: 1 (ICY 200 OK) or 2 (HTTP/1.1, chunked)")
    gga_interval_s: float = _f(0.0, min=0.0, max=600.0, doc="upload GGA this often (network RTK); 0 = never")
    timeout_s: float = _f(10.0, min=0.5, max=300.0, doc="no data for this long = reconnect")
    header_timeout_s: float = _f(10.0, min=0.5, max=300.0,
                                 doc="the caster's whole response header must arrive within this")
    max_rate_bps: float = _f(64000.0, min=1000.0, max=1e7,
                             doc="read the caster at most this fast (a flooding caster is throttled)")


@dataclass(frozen=True, slots=True)
class CorrectionsMqttConfig:
    host: str = _f("127.0.0.1")
    port: int = _f(1883, min=1, max=65535)
    topic: str = _f("rtcm/base")


@dataclass(frozen=True, slots=True)
class CorrectionsFileConfig:
    path: str = _f("")
    realtime: bool = _f(True, doc="replay at the recording's pace (rate_bps) or as fast as possible")
    rate_bps: float = _f(2000.0, min=1.0, max=10e6, doc="replay rate in bytes per second when realtime")
    loop: bool = _f(False)


@dataclass(frozen=True, slots=True)
class CorrectionsConfig:
    source: str = _f("none", choices=("ntrip", "serial", "mqtt", "file", "none"))
    forward_to_autopilot: bool = _f(False, doc="also send the RTCM frames to the autopilot as GPS_RTCM_DATA")
    base_position_ecef_m: tuple[float, float, float] | None = _f(
        None, min=-6.5e6, max=6.5e6, norm=(6.3e6, 6.45e6),
        doc="override the base station position (ECEF, m); default: from RTCM 1005/1006")
    base_max_spp_diff_m: float = _f(
        100.0, min=30.0, max=1e7,
        doc="a base position (1005/1006 or the override) further than this from the base's own single-point "
            "solution is not believed, and base epochs this far from the believed position are not used "
            "(the single-point solution is 5-10 m off on real bases). Raise it only for a base whose "
            "coordinates are deliberately in another frame than its code's (a local datum): the rover's "
            "position then follows them")
    ntrip: NtripConfig = field(default_factory=NtripConfig)
    serial: SerialPortConfig = field(default_factory=lambda: SerialPortConfig("/dev/ttyUSB1", 57600))
    mqtt: CorrectionsMqttConfig = field(default_factory=CorrectionsMqttConfig)
    file: CorrectionsFileConfig = field(default_factory=CorrectionsFileConfig)
    max_rate_bps: float = _f(64000.0, min=1000.0, max=1e7,
                             doc="correction chunks beyond this byte rate are dropped (counted) before logging")
    max_bytes_per_turn: int = _f(512, min=64, max=65536,
                                 doc="correction bytes decoded per event-loop turn (the IMU path goes between)")


@dataclass(frozen=True, slots=True)
class OutputConfig:
    mode: str = _f("vision", choices=("vision", "odometry", "gps_input"),
                   doc="VISION_POSITION_ESTIMATE, ODOMETRY (EK3_SRC ExternalNav) or GPS_INPUT (GPS_TYPE=14)")
    rate_hz: float = _f(10.0, min=0.1, max=50.0)
    set_ekf_origin: bool = _f(True, doc="send SET_GPS_GLOBAL_ORIGIN before the first vision/odometry output")
    max_sigma_h_m: float = _f(5.0, min=0.0, max=100.0, min_exclusive=True,
                              doc="do not inject worse than this (1-sigma)")
    max_sigma_v_m: float = _f(10.0, min=0.0, max=100.0, min_exclusive=True)
    # 10 deg turns a 0.2-m horizontal lever arm by 3.5 cm (0.5 m: 9 cm): centimetres
    max_sigma_yaw_deg: float = _f(10.0, min=0.0, max=180.0, min_exclusive=True,
                                  doc="do not inject while our heading is worse than this (1-sigma) unless the "
                                      "yaw from motion or a dual-antenna heading confirms it")
    resume_sigma_fraction: float = _f(0.8, min=0.1, max=1.0,
                                      doc="after a stop on sigma, inject again only below this fraction "
                                      "of max_sigma_h_m / max_sigma_v_m (no flapping at the threshold)")
    geoid_undulation_m: float = _f(0.0, min=-150.0, max=150.0,
                                   doc="N = ellipsoid - MSL height at the site, for GPS_INPUT's MSL altitude")
    gps_input_id: int = _f(0, min=0, max=1)
    named_value_rate_hz: float = _f(1.0, min=0.0, max=10.0,
                                    doc="NAMED_VALUE_FLOAT CC_* to the ground station (status, sigmas); 0 = off")
    max_hpl_m: float = _f(5.0, min=0.0, max=1000.0, min_exclusive=True,
                          doc="do not inject when the horizontal protection level (companion.nav.protection, "
                          "filter.hpl_integrity_risk) exceeds this. 5 m passes DGPS-grade output (sigma_h "
                          "0.3-0.7 m gives an HPL of 1-3.5 m) and blocks what the autopilot's own GPS would "
                          "give (a standalone fix of 1.5-2.5 m sigma: an HPL of 7-12 m); in the simulated "
                          "GNSS outages it stops injection before the true error reaches 2 m")
    resume_hpl_fraction: float = _f(0.8, min=0.1, max=1.0,
                                    doc="after a stop on the protection level, inject again only below this "
                                    "fraction of max_hpl_m (no flapping at the threshold)")


@dataclass(frozen=True, slots=True)
class FilterConfig:
    """Maps onto :class:`companion.nav.filter.ProcessNoise` and :class:`companion.nav.engine.EngineConfig`.

    Defaults are MEMS flight-controller class (ICM-4xxxx): starting points, not tuning."""
    gyro_arw_rad_per_sqrt_s: float = _f(3.0e-4, min=0.0, max=0.1, min_exclusive=True)
    accel_vrw_mps_per_sqrt_s: float = _f(3.0e-3, min=0.0, max=1.0, min_exclusive=True)
    gyro_bias_rw_radps_per_sqrt_s: float = _f(1.0e-5, min=0.0, max=0.01)
    accel_bias_rw_mps2_per_sqrt_s: float = _f(1.0e-4, min=0.0, max=0.1)
    clock_bias_psd_m2ps: float = _f(0.1, min=0.0, max=1e6)
    clock_drift_psd_m2ps3: float = _f(0.01, min=0.0, max=1e6)
    # IMU time-tag offset (companion.nav.filter dt_imu: GPS time of an IMU sample = its mapped boot
    # time + dt_imu).  ArduPilot's SYSTEM_TIME is its GPS fix time plus the time since the fix
    # *arrived* (AP_GPS::time_epoch_usec), so it lags GPS time by the receiver's output latency:
    # tens of ms for a u-blox M8/F9 at 5-10 Hz (ArduPilot budgets 0.12 s of GPS lag for them, 0.22 s
    # for older ones), ~0 with a PPS line.  PX4 sets its clock from the fix time as the GPS message
    # is parsed, so it lags the same way; a driver that sets it only once leaves the mapping to
    # drift with the board's crystal (tens of ppm, ~0.1 s per hour): raise the random walk there.
    # Mean 0 (the sign and size depend on the installation; a real stream was off by 0.265 s);
    # sigma 0.1 s covers that at 2.7 sigma and 0.2 s at 2 (the model is linear in the offset: 0.1 s
    # is 1 m at 10 m/s); the random walk (1 ms per 100 s) follows a latency that wanders slowly.
    imu_time_offset_s: float = _f(0.0, min=-1.0, max=1.0,
                                  doc="prior mean of the IMU time-tag offset (GPS time = IMU tag + this), s")
    imu_time_offset_sigma_s: float = _f(0.1, min=0.0, max=1.0,
                                        doc="its prior 1-sigma (0 = not estimated: the mean is used as is)")
    imu_time_offset_rw_s_per_sqrt_s: float = _f(1e-4, min=0.0, max=0.1,
                                                doc="random walk of the IMU time-tag offset")
    use_pseudorange: bool = _f(True)
    use_dgps: bool = _f(True)
    use_tdcp: bool = _f(True)
    use_doppler: bool = _f(False)
    use_loose: bool = _f(False)
    elevation_mask_deg: float = _f(10.0, min=0.0, max=90.0)
    systems: tuple[str, ...] = _f(("G", "E", "C", "J"), choices=("G", "R", "E", "C", "J"),
                                  doc="constellations fused: G GPS, R GLONASS, E Galileo, C BeiDou, J QZSS (one "
                                  "receiver clock plus a bias state per other system). GLONASS only when named: its "
                                  "code carries receiver inter-channel biases (its code sigma x1.5) and its RTK "
                                  "ambiguities stay float (FDMA: the receivers' inter-channel phase biases) unless "
                                  "rtk_glonass_integers. "
                                  "With rtk_enabled, the systems double-differenced too, each within itself "
                                  "(a reference satellite per system and signal, no inter-system bias)")
    pseudorange_signal: str = _f("L1C", choices=("L1C", "IF"),
                                 doc="'L1C': each system's single-frequency code (GPS/QZSS L1 C/A, Galileo E1, "
                                 "BeiDou B1I; Klobuchar when standalone); 'IF': the dual-frequency iono-free pair "
                                 "(standalone with a dual-frequency receiver: no ionosphere error, 3x the noise)")
    gate_probability: float = _f(0.999, min=0.5, max=1.0,
                                 doc="chi-square gate of every update (1 = never reject)")
    sigma_doppler_mps: float = _f(0.1, min=0.0, max=100.0, min_exclusive=True)
    sigma_phase_m: float = _f(0.005, min=0.0, max=1.0, min_exclusive=True)
    sigma_tdcp_floor_mps: float = _f(0.01, min=0.0, max=10.0)
    sigma_pseudorange_floor_m: float = _f(0.0, min=0.0, max=1000.0)
    tdcp_max_interval_s: float = _f(1.5, min=0.0, max=60.0, min_exclusive=True)
    tdcp_base_correction: str = _f("auto", choices=("auto", "off"))
    history_s: float = _f(2.0, min=0.1, max=60.0)
    coasting_after_s: float = _f(3.0, min=0.1, max=3600.0)
    untrusted_sigma_h_m: float = _f(50.0, min=0.0, max=1e4, min_exclusive=True)
    clock_jump_sigmas: float = _f(8.0, min=0.0, max=1000.0, min_exclusive=True,
                                  doc="common pseudorange step, in clock sigmas, that re-seeds the clock")
    clock_jump_min_m: float = _f(30.0, min=0.0, max=1e7)
    sigma_phase_elevation_scaling: bool = _f(False, doc="carrier noise x 1/sin(elevation)")
    pseudorange_correlation_time_s: float = _f(
        5.0, min=0.0, max=3600.0,
        doc="correlation time of the code noise and multipath (0 = white): seconds on a moving antenna, "
            "tens of seconds on a static one; the variance is inflated by 1 + 2 tau / T so that averaging "
            "epochs does not shrink the covariance below what correlated errors allow")
    slow_error_floor: bool = _f(True, doc="keep the position covariance above one epoch of the slow "
                                "pseudorange errors alone: a bias is not averaged away (companion.nav.slow_errors)")
    zupt_enabled: bool = _f(True, doc="zero velocity and zero angular rate (ZUPT/ZARU) whenever the IMU shows "
                            "the vehicle at rest: without them the heading is unobservable on the ground and "
                            "runs away within minutes")
    zupt_window_s: float = _f(0.5, min=0.0, max=60.0, min_exclusive=True)
    zupt_accel_std_mps2: float = _f(0.05, min=0.0, max=10.0, min_exclusive=True)
    zupt_gyro_std_radps: float = _f(0.005, min=0.0, max=1.0, min_exclusive=True)
    zupt_max_speed_mps: float = _f(0.5, min=0.0, max=10.0, min_exclusive=True)
    zupt_sigma_mps: float = _f(0.02, min=0.0, max=10.0, min_exclusive=True)
    zaru_sigma_floor_radps: float = _f(2e-4, min=0.0, max=1.0)
    nhc_enabled: bool = _f(False, doc="non-holonomic constraint (seed 002) while on the ground: a rover or "
                           "boat always, an aircraft when landed (EXTENDED_SYS_STATE) or disarmed")
    nhc_sigma_lateral_mps: float = _f(0.1, min=0.0, max=10.0, min_exclusive=True)
    nhc_sigma_vertical_mps: float = _f(0.1, min=0.0, max=10.0, min_exclusive=True)
    nhc_min_speed_mps: float = _f(1.0, min=0.0, max=100.0)
    course_alignment_enabled: bool = _f(False, doc="on the ground, take the heading from the GNSS course over "
                                        "ground once driving straight at speed (a rover or car without a usable "
                                        "compass; never for a boat or anything that crabs)")
    course_alignment_min_speed_mps: float = _f(3.0, min=0.5, max=100.0)
    course_alignment_max_yaw_rate_radps: float = _f(0.05, min=0.0, max=10.0, min_exclusive=True)
    course_alignment_slip_sigma_rad: float = _f(0.0175, min=0.0, max=1.0, doc="side-slip while driving straight (1-sigma)")
    course_alignment_reset_above_rad: float = _f(0.26, min=0.0, max=math.pi, min_exclusive=True,
                                                 doc="heading uncertainty or disagreement beyond which the "
                                                 "heading is reset to the course instead of fused")
    course_alignment_epochs: int = _f(5, min=1, max=100)
    imu_screen_enabled: bool = _f(True, doc="screen IMU samples (clip, implausible jump) before integration")
    imu_clip_fraction: float = _f(0.98, min=0.5, max=1.0, doc="fraction of full scale counted as clipped")
    imu_accel_jump_mps2: float = _f(60.0, min=1.0, max=2000.0,
                                    doc="largest specific-force jump from the running median in one sample")
    imu_gyro_jump_radps: float = _f(10.0, min=0.1, max=200.0,
                                    doc="largest angular-rate jump from the running median in one sample")
    imu_median_window: int = _f(9, min=3, max=101)
    integrity_enabled: bool = _f(True, doc="divergence detection from the GNSS innovations")
    integrity_window_s: float = _f(5.0, min=1.0, max=60.0)
    integrity_min_updates: int = _f(3, min=1, max=100)
    integrity_min_rows: int = _f(10, min=1, max=1000)
    integrity_max_rejected_fraction: float = _f(0.5, min=0.05, max=1.0)
    integrity_max_nis_mean: float = _f(4.0, min=1.0, max=100.0,
                                       doc="mean NIS of the fused rows of a window above which the filter "
                                       "is inconsistent (1 expected)")
    integrity_probation_max_rejected_fraction: float = _f(0.2, min=0.0, max=1.0)
    hpl_integrity_risk: float = _f(1e-5, min=1e-12, max=0.1,
                                   doc="probability that the true horizontal error exceeds the protection "
                                   "level's fault-free bound (K = sqrt(chi2_ppf(1 - p, 2)): 1e-5 gives 4.8 x "
                                   "the error ellipse's major axis)")
    hpl_missed_detection: float = _f(1e-3, min=1e-12, max=0.5,
                                     doc="missed-detection probability of the solution-separation (one faulty "
                                     "satellite) part of the protection level")
    gravity_gradient_refresh_m: float = _f(200.0, min=0.0, max=1e6, min_exclusive=True)
    compiled_kernels: str = _f("auto", choices=("auto", "on", "off"),
                               doc="numba-compiled IMU-rate and LAMBDA kernels (same results as the pure-Python "
                               "path): 'auto' = with rtk_enabled, where they halve an RTK epoch's CPU; "
                               "without RTK they save no measurable CPU in the service and cost ~100 MB")
    # carrier-phase RTK (companion.nav.rtk_update).  Off by default: it changes what an existing
    # DGPS installation gets (DD code and phase replace the DGPS pseudoranges and TDCP whenever a
    # base epoch is near), it needs a base within ~10 km sending carrier phase (MSM4/5/7 or 1004,
    # best dual-frequency), and its simulated figures still miss the 2-cm RMS after the
    # first fix (the float seconds after an outage); turning it on is a decision about the base.
    rtk_enabled: bool = _f(False, doc="carrier-phase RTK against the correction stream's base (double-"
                           "differenced phase and code of every system in filter.systems on its own signals: GPS/QZSS "
                           "L1 C/A, L2C, L2 P(Y), L5; Galileo E1, E5a, E5b; BeiDou B1I, B3I, B2I, B1C, B2a; integer "
                           "ambiguities; "
                           "GPS_INPUT fix type 5/6). Needs corrections with carrier phase from a base "
                           "within ~10 km. Off by default: DD code and phase then replace the DGPS "
                           "pseudoranges and TDCP whenever a base epoch is near")
    rtk_ratio_threshold: float = _f(3.0, min=1.0, max=100.0,
                                    doc="LAMBDA ratio test: second-best / best squared norm at least this")
    rtk_sigma_phase_a_m: float = _f(0.003, min=0.0, max=0.1, min_exclusive=True,
                                    doc="carrier noise per receiver, elevation-independent part (RTKLIB's "
                                    "a in a^2 + b^2 / sin^2 el)")
    rtk_sigma_phase_b_m: float = _f(0.003, min=0.0, max=0.1,
                                    doc="carrier noise per receiver, part growing as 1/sin(elevation)")
    rtk_code_phase_ratio: float = _f(100.0, min=1.0, max=10000.0,
                                     doc="code sigma / carrier sigma of the double-differenced rows")
    rtk_iono_states: bool = _f(True, doc="estimate the ionosphere's difference between rover and base, one "
                               "state per satellite (dual-frequency RTK: without it a few millimetres of it "
                               "bias the float ambiguities and delay the first fix)")
    rtk_iono_sigma_zenith_m: float = _f(0.001, min=0.0, max=1.0,
                                        doc="its zenith sigma at zero baseline (m)")
    rtk_iono_sigma_ppm: float = _f(1.0, min=0.0, max=1000.0,
                                   doc="... plus this per metre of baseline, x 1e-6 (RTKLIB: 3 ppm; on a real "
                                       "5.3-km car 3 ppm delayed the first fix by 82 s, 1 ppm fixed at once)")
    rtk_glonass_integers: bool = _f(False, doc="with R in filter.systems: fix GLONASS's ambiguities too (RTKLIB's "
                                    "gloarmode on). Only when the base is the rover's receiver model (two ZED-F9P): "
                                    "each make has its own GLONASS inter-channel phase biases, which cancel only "
                                    "between two receivers of one model; otherwise GLONASS stays float")
    rtk_antennas: str = _f("", doc="receiver antenna calibrations for RTK: an IGS ANTEX (igs20.atx) or NGS "
                           "ant_info (ngs_abs.pcv) file, a path as the service is started (empty: each antenna's "
                           "phase centres at its reference point, which puts the difference of the two antennas' "
                           "offsets, centimetres, into the height)")
    rtk_rover_antenna: str = _f("", doc="with rtk_antennas: the rover antenna's IGS type and radome, e.g. "
                                "'TRM59800.00 SCIS' (empty: uncalibrated)")
    rtk_base_antenna: str = _f("", doc="with rtk_antennas: the base antenna's IGS type (empty: the one its RTCM "
                               "1007/1008/1033 names, when the file has it)")

    def process_noise(self):
        from .nav.filter import ProcessNoise
        return ProcessNoise(
            gyro_arw_rad_per_sqrt_s=self.gyro_arw_rad_per_sqrt_s,
            accel_vrw_mps_per_sqrt_s=self.accel_vrw_mps_per_sqrt_s,
            gyro_bias_rw_radps_per_sqrt_s=self.gyro_bias_rw_radps_per_sqrt_s,
            accel_bias_rw_mps2_per_sqrt_s=self.accel_bias_rw_mps2_per_sqrt_s,
            clock_bias_psd_m2ps=self.clock_bias_psd_m2ps,
            clock_drift_psd_m2ps3=self.clock_drift_psd_m2ps3,
            # without the state (sigma 0) it has no noise either: P stays exactly zero there
            imu_time_offset_rw_s_per_sqrt_s=self.imu_time_offset_rw_s_per_sqrt_s if self.imu_time_offset_sigma_s > 0
            else 0.0)

    def engine_config(self, lever_arm_b_m=(0.0, 0.0, 0.0)):
        """The engine configuration.  Keys the engine does not (or no longer) know are left out
        with a warning rather than breaking start-up (tests/test_config.py flags the drift)."""
        import logging
        from .nav.engine import EngineConfig
        known = {f.name for f in dataclasses.fields(EngineConfig)}
        kw = {}
        for f in dataclasses.fields(self):
            if f.name in _NOISE_FIELDS or f.name in FILTER_SERVICE_FIELDS:
                continue
            if f.name == "systems":
                kw["systems"] = "".join(self.systems)       # the engine takes RINEX letters as one string
            elif f.name in known:
                kw[f.name] = getattr(self, f.name)
            else:
                logging.getLogger(__name__).warning("filter.%s is not an EngineConfig field; ignored", f.name)
        return EngineConfig(noise=self.process_noise(), lever_arm_b_m=tuple(lever_arm_b_m), **kw)


_NOISE_FIELDS = {"gyro_arw_rad_per_sqrt_s", "accel_vrw_mps_per_sqrt_s", "gyro_bias_rw_radps_per_sqrt_s",
                 "accel_bias_rw_mps2_per_sqrt_s", "clock_bias_psd_m2ps", "clock_drift_psd_m2ps3",
                 "imu_time_offset_rw_s_per_sqrt_s"}
#: [filter] keys the service reads itself (how the engine runs, not what it computes)
FILTER_SERVICE_FIELDS = frozenset({"compiled_kernels"})


@dataclass(frozen=True, slots=True)
class LogConfig:
    enabled: bool = _f(True)
    dir: str = _f("logs")
    max_bytes: int = _f(64 * 1024 * 1024, min=4096, max=2 ** 40, doc="rotate the field log at this size")
    fsync_interval_s: float = _f(1.0, min=0.0, max=60.0,
                                doc="flush to the card this often: at most this much is lost at a power cut")
    max_total_bytes: int = _f(1 << 30, min=16384, max=2 ** 40,
                              doc="the log directory's total size; the oldest files are deleted first")
    aid_status_rate_hz: float = _f(2.0, min=0.0, max=10.0,
                                   doc="per aid source status records (kind 'aid_status': innovations, test "
                                   "ratios, protection level) in the field log and on MQTT <prefix>/aid_status; "
                                   "0 = off")


@dataclass(frozen=True, slots=True)
class TelemetryConfig:
    enabled: bool = _f(False)
    host: str = _f("127.0.0.1")
    port: int = _f(1883, min=1, max=65535)
    topic_prefix: str = _f("companion", doc="topics <prefix>/solution and <prefix>/health")
    rate_hz: float = _f(1.0, min=0.01, max=50.0)


@dataclass(frozen=True, slots=True)
class NmeaConfig:
    enabled: bool = _f(False)
    destination: str = _f("udp:127.0.0.1:10110",
                          doc="udp:HOST:PORT (one datagram per epoch) or DEVICE,BAUD (serial port)")
    rate_hz: float = _f(1.0, min=0.1, max=20.0)
    talker: str = _f("GN", choices=("GN", "GP"))
    sentences: tuple[str, ...] = _f(("GGA", "RMC", "GST"), choices=("GGA", "RMC", "GST"))


@dataclass(frozen=True, slots=True)
class StatusPageConfig:
    # it shows where the vehicle is: loopback unless the board's network is trusted
    enabled: bool = _f(True, doc="a live status page (health, fix, satellites and test ratios, sigma and "
                       "protection-level plot, events) at http://ADDRESS:PORT/; a port in use is "
                       "reported and the service goes on without the page")
    address: str = _f("127.0.0.1", doc="'0.0.0.0' to reach it from the board's Wi-Fi")
    port: int = _f(8765, min=1, max=65535)


@dataclass(frozen=True, slots=True)
class Config:
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    gnss: GnssConfig = field(default_factory=GnssConfig)
    corrections: CorrectionsConfig = field(default_factory=CorrectionsConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    filter: FilterConfig = field(default_factory=FilterConfig)
    log: LogConfig = field(default_factory=LogConfig)
    telemetry: TelemetryConfig = field(default_factory=TelemetryConfig)
    nmea: NmeaConfig = field(default_factory=NmeaConfig)
    status_page: StatusPageConfig = field(default_factory=StatusPageConfig)
    source_path: str = field(default="", compare=False, metadata={"internal": True})

    def engine_config(self):
        """The nav engine configuration (filter section + the GNSS installation)."""
        g = self.gnss
        from .rtk_signals import RTK_SIGNALS
        return dataclasses.replace(self.filter.engine_config(g.lever_arm_b_m),
                                   moving_baseline_b_m=g.moving_baseline_b_m,
                                   baseline_length_tol_m=g.baseline_length_tol_m,
                                   base_max_spp_diff_m=self.corrections.base_max_spp_diff_m,
                                   # the canonical tracking families the pipeline renames to
                                   **({"rtk_signals": RTK_SIGNALS} if self.filter.rtk_enabled else {}))

    def to_toml(self, comments: bool = True, redact: bool = False) -> str:
        """TOML that :func:`loads_config` reads back; ``redact`` writes secrets as ``***``."""
        return _to_toml(self, comments, redact)


# ---------------------------------------------------------------------------------------------
# building and validation

def _is_dataclass_type(tp) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _check_range(value, key: str, md: dict, err) -> None:
    lo, hi = md.get("min"), md.get("max")
    if lo is not None:
        if md.get("min_exclusive") and not value > lo:
            err(f"must be > {lo}, got {value!r}")
        if value < lo:
            err(f"must be >= {lo}, got {value!r}")
    if hi is not None and value > hi:
        err(f"must be <= {hi}, got {value!r}")


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
    if origin is tuple:                                                   # a fixed-size vector
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            err(f"expected an array of {len(args)} numbers, got {value!r}")
        element_md = {k: md.get(k) for k in ("min", "max")}
        out = tuple(_check_value(v, a, f"{key}[{i}]", where, element_md)
                    for i, (v, a) in enumerate(zip(value, args)))
        if md.get("norm"):
            lo, hi = md["norm"]
            length = math.sqrt(sum(x * x for x in out))
            if not lo <= length <= hi:
                err(f"length must be between {lo} and {hi} m, got {length:.6g} m")
        return out
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
            err(f"must be a finite number, got {value!r}")
    elif tp is str:
        if not isinstance(value, str):
            err(f"expected a string, got {value!r}")
    choices = md.get("choices")
    if choices is not None and value not in choices:
        err(f"must be one of {', '.join(map(str, choices))}, got {value!r}")
    if tp in (int, float):
        _check_range(value, key, md, err)
    return value


def _unknown_keys_error(unknown: list[str], known, prefix: str, where: str) -> ConfigError:
    import difflib
    parts, guessed = [], True
    for u in unknown:
        close = difflib.get_close_matches(u, list(known), n=1, cutoff=0.6)
        parts.append(prefix + u + (f" (did you mean {prefix}{close[0]}?)" if close else ""))
        guessed = guessed and bool(close)
    msg = f"{where}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(parts)}"
    if not guessed:                      # no close match: list what the section does hold
        section = f"[{prefix.rstrip('.')}]" if prefix else "the top level"
        msg += f"; keys of {section}: {', '.join(known)} (all of them: `companion config example`)"
    return ConfigError(msg)


def _build(cls, table: dict, prefix: str, where: str):
    if not isinstance(table, dict):
        raise ConfigError(f"{where}: {prefix.rstrip('.') or '<root>'}: expected a table")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if not f.metadata.get("internal")}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise _unknown_keys_error(unknown, fields, prefix, where)
    kw = {}
    for name, f in fields.items():
        if name not in table:
            continue
        tp = hints[name]
        if _is_dataclass_type(tp):
            kw[name] = _build(tp, table[name], f"{prefix}{name}.", where)
        else:
            kw[name] = _check_value(table[name], tp, prefix + name, where, dict(f.metadata))
    return cls(**kw)


def _cross_checks(cfg: Config, where: str) -> None:
    if cfg.mavlink.signing_required and not cfg.mavlink.signing_key_file:
        raise ConfigError(f"{where}: mavlink.signing_required: needs mavlink.signing_key_file")
    c = cfg.corrections
    if c.source == "ntrip" and not c.ntrip.mountpoint:
        raise ConfigError(f"{where}: corrections.ntrip.mountpoint: required when corrections.source = 'ntrip'")
    if c.source == "file" and not c.file.path:
        raise ConfigError(f"{where}: corrections.file.path: required when corrections.source = 'file'")
    if cfg.filter.rtk_enabled:
        if c.source == "none":
            raise ConfigError(f"{where}: filter.rtk_enabled: needs a base station: set corrections.source "
                              f"(ntrip, serial, mqtt or file) to a stream with carrier phase (RTCM MSM4/5/7 or 1004)")
        if cfg.gnss.source == "none":
            raise ConfigError(f"{where}: filter.rtk_enabled: needs the rover's raw observations (carrier "
                              f"phase): gnss.source = 'none' gives GPS_RAW_INT fixes only")
        if cfg.filter.use_loose:
            raise ConfigError(f"{where}: filter.rtk_enabled: cannot be combined with filter.use_loose = true "
                              f"(loose coupling fuses receiver fixes, not carrier phase)")
    f = cfg.filter
    if (f.rtk_rover_antenna or f.rtk_base_antenna) and not f.rtk_antennas:
        raise ConfigError(f"{where}: filter.rtk_rover_antenna / rtk_base_antenna: name types in a calibration "
                          f"file: set filter.rtk_antennas (ANTEX or NGS ant_info)")
    if f.rtk_antennas and not f.rtk_enabled:
        raise ConfigError(f"{where}: filter.rtk_antennas: applies to RTK (filter.rtk_enabled = true)")
    if not cfg.filter.systems:
        raise ConfigError(f"{where}: filter.systems: at least one constellation (e.g. [\"G\"])")
    if c.source == "serial" and cfg.gnss.source == "serial" and c.serial.port == cfg.gnss.serial.port:
        raise ConfigError(f"{where}: corrections.serial.port: {c.serial.port!r} is also gnss.serial.port; "
                          f"one serial port cannot carry both")


def config_from_dict(data: dict, where: str = "<config>") -> Config:
    """Build and validate a :class:`Config` from an already parsed TOML document."""
    cfg = _build(Config, data, "", where)
    _cross_checks(cfg, where)
    return dataclasses.replace(cfg, source_path=where)


def load_config(path: str | Path) -> Config:
    """Read, parse and validate a TOML configuration file; every failure is a :class:`ConfigError`."""
    p = Path(path)
    if p.is_dir():
        raise ConfigError(f"{p}: is a directory, not a configuration file "
                          f"(give the TOML file, e.g. {p / 'companion.toml'})")
    try:
        with p.open("rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{p}: configuration file not found") from None
    except PermissionError:
        raise ConfigError(f"{p}: configuration file not readable (permission denied)") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not a text file (not UTF-8 at byte {exc.start})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{p}: not valid TOML: {exc}") from None
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the configuration file: {exc.strerror or exc}") from None
    return config_from_dict(data, str(p))


def loads_config(text: str, where: str = "<string>") -> Config:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{where}: not valid TOML: {exc}") from None
    return config_from_dict(data, where)


# ---------------------------------------------------------------------------------------------
# what a configuration needs from its surroundings

def missing_extras(cfg: Config) -> list[str]:
    """One message per optional dependency this configuration needs and the machine lacks."""
    from .extras import available, install_hint
    out = []
    if not available("aiomqtt"):
        for key, used in (("telemetry.enabled = true", cfg.telemetry.enabled),
                          ("corrections.source = 'mqtt'", cfg.corrections.source == "mqtt")):
            if used:
                out.append(f"{cfg.source_path}: {key} needs aiomqtt, which is not installed: "
                           f"{install_hint('aiomqtt')}")
    return out


def secrets_readable_by_others(cfg: Config) -> str | None:
    """A warning when the file holds a secret and other users can read it (it should be 0600)."""
    import os
    import stat
    if not any(v for _, v in _secret_values(cfg)) or not cfg.source_path:
        return None
    try:
        mode = os.stat(cfg.source_path).st_mode
    except OSError:
        return None
    if mode & (stat.S_IROTH | stat.S_IRGRP):
        keys = ", ".join(k for k, v in _secret_values(cfg) if v)
        return (f"{cfg.source_path}: holds {keys} but is readable by other users "
                f"(mode {stat.S_IMODE(mode):04o}); chmod 600 {cfg.source_path}")
    return None


# ---------------------------------------------------------------------------------------------
# secrets

def secret_keys(cls=Config, prefix: str = "") -> tuple[str, ...]:
    """Dotted keys of every secret field (``corrections.ntrip.password``)."""
    hints = typing.get_type_hints(cls)
    out: list[str] = []
    for f in dataclasses.fields(cls):
        if _is_dataclass_type(hints[f.name]):
            out += secret_keys(hints[f.name], f"{prefix}{f.name}.")
        elif f.metadata.get("secret"):
            out.append(prefix + f.name)
    return tuple(out)


def _secret_values(cfg: Config):
    for key in secret_keys():
        obj = cfg
        for part in key.split("."):
            obj = getattr(obj, part)
        yield key, obj


def _as_dict(obj, redact: bool) -> dict[str, Any]:
    hints = typing.get_type_hints(type(obj))
    out: dict[str, Any] = {}
    for f in dataclasses.fields(obj):
        if f.metadata.get("internal"):
            continue
        v = getattr(obj, f.name)
        if _is_dataclass_type(hints[f.name]):
            out[f.name] = _as_dict(v, redact)
        elif v is None:
            continue                                      # TOML has no null: an unset optional is absent
        elif redact and f.metadata.get("secret") and v:
            out[f.name] = REDACTED
        else:
            out[f.name] = list(v) if isinstance(v, tuple) else v
    return out


def redacted(cfg: Config) -> dict[str, Any]:
    """The configuration as a TOML-shaped dict (sections as dicts, vectors as lists, unset optionals
    absent) with every non-empty secret (:func:`secret_keys`) replaced by ``"***"``.  Safe to log or
    to copy into a field log; ``config_from_dict(redacted(cfg))`` is valid."""
    return _as_dict(cfg, redact=True)


# ---------------------------------------------------------------------------------------------
# writing

_TOML_ESCAPES = {"\\": "\\\\", '"': '\\"', "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f", "\r": "\\r"}


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        r = repr(v)
        return r if ("." in r or "e" in r or "inf" in r or "nan" in r) else r + ".0"
    if isinstance(v, str):
        # a TOML basic string: backslash, quote and every control character escaped (a raw
        # newline or tab from a multi-line string would make the field log's copy unreadable)
        return '"' + "".join(_TOML_ESCAPES.get(c) or (f"\\u{ord(c):04x}" if ord(c) < 0x20 or ord(c) == 0x7F else c)
                             for c in v) + '"'
    if isinstance(v, (tuple, list)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def _allowed(md: dict, is_list: bool = False) -> str:
    """'allowed: 0.0 < x <= 100.0' or 'one of: a, b' from a field's metadata ('' if it has none)."""
    lo, hi, norm, choices = md.get("min"), md.get("max"), md.get("norm"), md.get("choices")
    if choices:
        return f"{'entries' if is_list else 'one'} of: {', '.join(map(str, choices))}"
    if lo is None and hi is None:
        return ""
    left = "" if lo is None else f"{lo} {'<' if md.get('min_exclusive') else '<='} "
    right = "" if hi is None else f" <= {hi}"
    text = f"allowed: {left}x{right}"
    return text + (f", length {norm[0]} to {norm[1]}" if norm else "")


def _to_toml(obj, comments: bool, redact: bool = False) -> str:
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
            if comments:
                is_list = "tuple[str" in str(hints[f.name])
                doc = "; ".join(x for x in (f.metadata.get("doc", ""), _allowed(f.metadata, is_list)) if x)
                if doc:
                    lines.append(f"# {doc}")
            if redact and f.metadata.get("secret") and v:
                v = REDACTED
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
    """A complete configuration file with every key at its default, commented
    (``companion config example``; ``deploy/companion.toml`` holds the same keys and values)."""
    head = ("# companion configuration (TOML).  Every key is optional; shown are the defaults.\n"
            "# Units are in the key names.  Unknown keys are errors.  Check a file with\n"
            "# `companion config check FILE`; keep it private (chmod 600) when it holds a password.\n\n")
    return head + Config().to_toml(comments=True)


__all__ = ["Config", "ConfigError", "MavlinkConfig", "GnssConfig", "SerialPortConfig", "NtripConfig",
           "CorrectionsConfig", "CorrectionsMqttConfig", "CorrectionsFileConfig", "OutputConfig",
           "FilterConfig", "LogConfig", "TelemetryConfig", "REDACTED", "load_config", "loads_config",
           "config_from_dict", "example_config_toml", "missing_extras", "redacted", "secret_keys",
           "secrets_readable_by_others"]
