"""The navigation pipeline: logged bytes -> decoders -> core messages -> engine -> solutions.

:class:`NavPipeline` is synchronous and deterministic: its output is a pure function of the sequence
of ``feed(kind, t_rx_ns, data)`` calls, i.e. of the field log.  The live service
(:mod:`companion.service`) writes every input to the field log and hands the same record to the
pipeline, in the same order, with no ``await`` in between; ``companion replay`` feeds the logged
records to a fresh pipeline built from the logged configuration and gets the same solutions bit
for bit.  Nothing in here reads a clock, a socket or a random number generator; receive times
(``t_rx_ns``) are only used as data, and only to order/diagnose (never for navigation maths).

Kinds: ``mavlink`` (one MAVLink frame as received), ``ubx`` (receiver bytes from a local serial
port), ``rtcm`` (correction bytes), ``event`` (JSON: configuration, start/stop; ignored here),
``solution`` (our own outputs; ignored here).

What it does with the inputs
----------------------------
* IMU (HIGHRES_IMU / RAW_IMU / SCALED_IMU2/3) -> :class:`~companion.messages.ImuSample` via
  :class:`~companion.io.mavlink_decode.ImuDecoder`, GPS time from :class:`~companion.io.mavlink_time.BootToGpsTime`
  (SYSTEM_TIME; what it leaves, e.g. ArduPilot's receiver latency, is the filter's ``dt_imu`` state,
  ``filter.imu_time_offset_*``, reported as ``imu_time_offset_s`` in the solution extras and health).  With ``mavlink.imu_cluster`` set, every listed stream has its own decoder and
  the samples go through an :class:`~companion.nav.imu_cluster.ImuCluster` (unit = position in the
  list, the first is the primary whose time grid the fused samples keep); a unit dropped or
  re-admitted by its fault test is announced and counted (health ``imu_cluster``).
  A solution is produced at the first IMU sample of every ``1 / output.rate_hz`` slot of GPS
  time (slot = floor(t_gps * rate)): paced by the data's own time, not a timer, so it replays
  identically, and the output rate holds whatever IMU rate the autopilot actually delivers
  (ArduPilot may stream fewer than the ``mavlink.imu_rate_hz`` asked for); an IMU slower than the
  output rate gives one solution per sample.
* SERIAL_CONTROL replies from the autopilot's GPS port, or ``ubx`` records -> UBX decoder ->
  rover epochs (RXM-RAWX), ephemerides (RXM-SFRBX), receiver fixes (NAV-PVT, unused for fusion).
* ``rtcm`` -> RTCM decoder -> base epochs, base position (checked against the base's own code:
  :mod:`companion.nav.base_check`), ephemerides.
* GPS_RAW_INT -> :class:`~companion.messages.GnssFix`: the loosely coupled fallback when no raw
  observations arrived for ``raw_timeout_s`` of IMU time (or ``gnss.source = 'none'``).
* ATTITUDE -> initial attitude.  Ground mode (ZUPT/NHC, ``filter.nhc_enabled``): a rover or boat
  (HEARTBEAT ``type``) always, otherwise EXTENDED_SYS_STATE ``landed_state`` ON_GROUND when the
  autopilot reports it, else disarmed (HEARTBEAT ``system_status`` STANDBY).
* Dual-antenna heading: UBX NAV-RELPOSNED -> moving-baseline vector (needs
  ``gnss.moving_baseline_b_m``), and GPS_RAW_INT ``yaw`` (an autopilot with a moving-baseline
  GPS) -> heading with ``gnss.gps_raw_yaw_sigma_deg``; both fused once the filter runs.

Initialisation (status ``init`` until then, nothing injected): position and receiver clock from
SPP (DGPS-corrected when a base is there) of the first rover epoch with enough satellites, or the
GPS_RAW_INT fix in loose mode; attitude from the autopilot's latest ATTITUDE; velocity from the
epoch's Doppler (SPP), else zero when the autopilot is disarmed (on the ground), else GPS_RAW_INT.
The engine starts at the newest IMU sample; ``engine.reset_counter`` counts (re)initialisations.

Heading (companion.heading_watch, health ``yaw_gsf``): a yaw from motion runs beside the filter
from the first screened IMU sample on; it gives the initial heading when ATTITUDE's is missing or
contradicted, confirms ours, resets it when it runs away, and gates the injection on it.

Re-initialisation (logged, counted, announced): autopilot reboot, IMU time jump larger than
``REINIT_GAP_S`` in either direction (clock jump, long link loss), an untrusted solution, or a
diverged one (companion.nav.integrity: the GNSS innovations of a window say the filter is wrong).
After a re-initialisation other than a reboot the learnt sensor biases are kept when plausible;
after a divergence the new filter is on probation (status ``converging``, not injected) until
one consistent window has passed.

Injection rule (``solution.extras['inject']``): status ``nav`` or ``coasting`` (so not
``suspect``: the last epoch was inconsistent; nor ``diverged``/``converging``) and horizontal
1-sigma <= ``output.max_sigma_h_m`` and vertical <= ``output.max_sigma_v_m``, everything finite,
and the horizontal protection level (``extras['hpl_m']``, companion.nav.protection) <=
``output.max_hpl_m`` (after a stop on it, below ``output.resume_hpl_fraction`` of it).
After a stop on sigma, injection resumes below ``output.resume_sigma_fraction`` (0.8) of the
thresholds, so a sigma hovering at a threshold does not switch it (and announce it) every second.
IMU samples are screened before integration (companion.nav.imu_screen) with the full scale of
the stream's message type.  GPS_RAW_INT: ``gnss.gps_raw_latency_s`` is taken off its time tag,
and only its horizontal velocity is fused (it has no vertical one).
A coasting filter (no GNSS update for ``filter.coasting_after_s``) is still injected while its
own covariance says it is good enough: the autopilot gets the growing sigma with every estimate
and the injection stops when the thresholds are crossed.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import os
from collections import Counter
from dataclasses import dataclass

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink.dialects.v20 import ardupilotmega as mavlink2  # noqa: E402

from .gnss.glonass import GlonassEphemeris  # noqa: E402
from .gnss.spp import spp_epoch  # noqa: E402
from .heading_watch import HeadingWatch  # noqa: E402
from .io.mavlink_time import BootToGpsTime  # noqa: E402
from .io.mavlink_decode import ImuDecoder, gps_fix_from_gps_raw_int, parse_imu_stream  # noqa: E402
from .io.mavlink_fast import DatagramParser  # noqa: E402
from .io.rtcm import RtcmDecoder  # noqa: E402
from .io.ubx import UbxDecoder  # noqa: E402
from .messages import (BaseStationPosition, GnssAttitude, GnssBaseline, GnssEpoch, GnssFix,  # noqa: E402
                       GpsEphemeris, ImuSample, NavSolution)
from .nav.engine import NavEngine  # noqa: E402
from .nav.rtk_update import FIX_FIXED  # noqa: E402
from .nav.imu_cluster import ClusterConfig, ImuCluster, UnitNoise  # noqa: E402
from .nav.imu_screen import FULL_SCALE_BY_MESSAGE, ImuFullScale  # noqa: E402
from .rtk_signals import RTK_SYSTEMS, rtk_epoch  # noqa: E402

log = logging.getLogger(__name__)
m = mavlink2
GROUND_VEHICLE_TYPES = (m.MAV_TYPE_GROUND_ROVER, m.MAV_TYPE_SURFACE_BOAT)

REINIT_GAP_S = 1.0            # IMU time step (either direction) that restarts the filter
CLUSTER_OUTPUT_ID = 100       # imu_id of the fused samples of an IMU cluster
RAW_TIMEOUT_S = 3.0           # no RXM-RAWX for this long (IMU time) -> loose GPS_RAW_INT fusion
# the autopilot's GPS_RAW_INT fixes came back after at least this long without one while the last
# raw epoch was RTK-fixed: the sky came back for both receivers, so raw observations get
# RAW_TIMEOUT_S again before loose fusion (the port is re-claimed in ~1-2 s and re-fixes within
# seconds; 1-2 s of loose 1-m fixes after the rtk flights' 30-s outage were injected up to 1 m off
# where the re-fix gives centimetres).  Without RTK the loose fixes are as good as the DGPS path:
# waiting would only withhold the output longer.
GPS_FIX_GAP_S = 2.0
ATTITUDE_MAX_AGE_S = 1.0      # ATTITUDE older than this (boot time) is not used to initialise
BASE_WAIT_S = 0.8             # hold a rover epoch (IMU time) until the base epoch of the same time
                              # arrived (DGPS without extrapolation, base-corrected TDCP), at most this


@dataclass(frozen=True)
class InitSigmas:
    """Initial 1-sigma uncertainties (the [filter] section has no keys for them yet)."""
    att_rad: float = 0.02            # the autopilot's own EKF attitude (ATTITUDE), ~1 deg
    pos_dgps_m: float = 1.5
    pos_standalone_m: float = 5.0
    vel_doppler_mps: float = 0.3
    vel_ground_mps: float = 0.1
    vel_gps_raw_mps: float = 1.5     # GPS_RAW_INT has no vertical velocity
    ba_mps2: float = 0.15            # MEMS turn-on accelerometer bias
    bg_radps: float = 0.006          # MEMS turn-on gyro bias (~0.35 deg/s)
    clk_m: float = 100.0
    drift_mps: float = 5.0


#: a new RTK fix state is announced (STATUSTEXT) only once it has held this long (GPS time): a fix
#: lost for one epoch and regained, or a float epoch between fixed ones, is not a change to announce
FIX_ANNOUNCE_HOLD_S = 3.0


class NavPipeline:
    """Synchronous, deterministic: ``feed(kind, t_rx_ns, data) -> list[NavSolution]``."""

    def __init__(self, config, init_sigmas: InitSigmas = InitSigmas()):
        self.cfg = config
        self.init_sigmas = init_sigmas
        mc = config.mavlink
        self.target = (mc.target_system, mc.target_component)
        self.time_map = BootToGpsTime(leap_seconds=config.gnss.leap_seconds)
        self.imu_dec = ImuDecoder(mc.imu_message, rate_hz=mc.imu_rate_hz, leap_seconds=config.gnss.leap_seconds)
        # IMU cluster: (message type, id or None, decoder) per unit, unit number = list position
        self.cluster_streams = [(*parse_imu_stream(name), ImuDecoder(
            parse_imu_stream(name)[0], rate_hz=mc.imu_rate_hz, leap_seconds=config.gnss.leap_seconds,
            imu_id=parse_imu_stream(name)[1])) for name in mc.imu_cluster]
        self.cluster: ImuCluster | None = self._new_cluster() if self.cluster_streams else None
        self._primary_boot_us: dict[float, int] = {}   # primary sample t_gps -> its boot time stamp
        self.parser = mavlink2.MAVLink(None)
        self.parser.robust_parsing = True
        # logged frames (replay): the high-rate ones through the lean decoder the live link uses
        self.frame_parser = DatagramParser(self.parser, on_error=self._mavlink_parse_error)
        self.ubx = UbxDecoder(week_hint=self._t_ref)
        self.rtcm = RtcmDecoder(week_hint=self._t_ref, leap_seconds=config.gnss.leap_seconds)
        self.engine = NavEngine(config.engine_config())
        self.lever_b = np.asarray(config.gnss.lever_arm_b_m, float)
        self.output_rate_hz = float(config.output.rate_hz)
        self._last_output_slot: int | None = None     # floor(t_gps * output rate) of the last solution
        self.serial_device = m.SERIAL_CONTROL_DEV_GPS1 if config.gnss.serial_control_device == "GPS1" \
            else m.SERIAL_CONTROL_DEV_GPS2
        self.raw_expected = config.gnss.source != "none"
        self.counters: Counter = Counter()
        self.events: list[tuple[int, str]] = []   # (MAV_SEVERITY, text): state changes to announce
        self.imu_count = 0
        self.last_imu: ImuSample | None = None
        self.last_imu_boot_us: int | None = None
        self.last_raw_t: float = -math.inf        # GPS time (IMU clock) of the last rover epoch
        self._last_fix_t: float = -math.inf       # GPS time of the last GPS_RAW_INT fix
        self.attitude = None                      # (time_boot_ms, roll, pitch, yaw)
        self._last_ap_heading_boot_s = -1e9       # last autopilot heading fused on the ground
        self.on_ground = False
        self.engine.ground_mode = False            # no NHC until the autopilot says we are on the ground
        self.vehicle_type: int | None = None       # HEARTBEAT type (MAV_TYPE)
        self.disarmed = False
        self.landed_state: int | None = None      # EXTENDED_SYS_STATE (MAV_LANDED_STATE)
        self.last_fix: GnssFix | None = None
        self._last_fix_key = None
        self._boot_epoch = 0
        self.mode = "none"
        self.output_state = "init"
        self.last_solution: NavSolution | None = None
        self.last_init_reason = ""
        self.base_seen = False
        self._base_override_sent = False
        self._base_check_state = (False, False, 0)   # (candidate waiting, epochs unused, station changes) announced
        self._held: list[GnssEpoch] = []          # rover epochs waiting for their base epoch
        self._base_times: list[float] = []        # recent base epoch times
        self.wait_for_base = config.corrections.source != "none" and config.filter.use_dgps
        # carrier-phase RTK: tracking families renamed alike on both sides (companion.rtk_signals)
        self.rtk_enabled = bool(getattr(config.filter, "rtk_enabled", False))
        if self.rtk_enabled:
            self.wait_for_base = config.corrections.source != "none"
        self._fix_announced = "none"              # RTK fix state last announced
        self._fix_candidate: tuple[str, float] | None = None   # (new state, GPS time it started)
        self._probation_next = False              # the next initialisation follows a divergence
        self._position_hold = False               # the engine holds the GNSS position back
        self._keep_biases_next = False            # ... follows a re-init of the same IMU in flight
        self._sigma_hold = False                  # injection stopped on sigma: resume below the hysteresis
        self._hpl_hold = False                    # ... on the protection level (its own hysteresis)
        self._imu_full_scale_for: str | None = None
        # GPS_RAW_INT time_usec is when the autopilot got the fix: the receiver's output latency later
        self.gps_raw_latency_s = float(getattr(config.gnss, "gps_raw_latency_s", 0.0))
        # injection resumes after a sigma stop only below this fraction of the thresholds (no flapping)
        self.resume_sigma_fraction = float(getattr(config.output, "resume_sigma_fraction", 0.8))
        self.max_hpl_m = float(getattr(config.output, "max_hpl_m", math.inf))
        self.resume_hpl_fraction = float(getattr(config.output, "resume_hpl_fraction", 0.8))
        # the yaw from motion watching our heading (companion.heading_watch)
        self.heading = HeadingWatch(self.engine, counters=self.counters, event=self._event, gap_s=REINIT_GAP_S,
                                    elevation_mask_deg=config.filter.elevation_mask_deg,
                                    attitude_yaw_sigma_deg=float(getattr(mc, "attitude_yaw_sigma_deg", 5.0)),
                                    max_sigma_yaw_deg=float(getattr(config.output, "max_sigma_yaw_deg", 10.0)),
                                    lever_b_m=self.lever_b, on_attitude_yaw_distrusted=self._biases_not_to_keep)
        if self.cluster_streams:
            self._set_imu_full_scale(tuple(t for t, _, _ in self.cluster_streams))

    # ------------------------------------------------------------------ helpers
    def _t_ref(self):
        """Current GPS time estimate from the data (week resolution for the decoders)."""
        if self.engine.initialized:
            return self.engine.t_gps
        if self.last_imu is not None:
            return self.last_imu.t_gps
        return None

    def _event(self, severity: int, text: str) -> None:
        self.events.append((severity, text))
        (log.warning if severity <= m.MAV_SEVERITY_WARNING else log.info)("%s", text)

    def _reinit(self, reason: str, detail: str = "") -> None:
        """``reason`` is a stable counter key; ``detail`` only goes into the announcement."""
        if self.engine.initialized:
            self.engine.initialized = False
            self._held.clear()
            # same IMU, same flight: the learnt biases are a better prior than zero (not after a
            # reboot, which may have re-initialised the sensors)
            self._keep_biases_next = reason != "autopilot reboot"
            self.counters[f"re-init: {reason}"] += 1
            self.heading.note_trouble(self.engine.t_gps)
            self._event(m.MAV_SEVERITY_WARNING, f"nav re-init: {reason}" + (f" ({detail})" if detail else ""))

    # ------------------------------------------------------------------ input
    def apply_settings(self, cfg) -> None:
        """A configuration changed while running (ground-station parameters, companion.io.mavlink_params;
        replayed from the field log's ``config_change`` events): the output thresholds and rate
        (read from ``self.cfg`` at every solution), the lever arm and the moving baseline (the
        engine's too) follow from the next record on; the rest keeps its start-up value."""
        self.cfg = cfg
        self.lever_b = np.asarray(cfg.gnss.lever_arm_b_m, float)
        self.heading.lever_b = self.lever_b
        self.engine.set_installation(cfg.gnss.lever_arm_b_m, cfg.gnss.moving_baseline_b_m)

    def feed_decoded(self, t_rx_ns: int, msgs) -> list[NavSolution]:
        """Already decoded GNSS messages (GnssEpoch, GpsEphemeris, BaseStationPosition), as the UBX
        and RTCM decoders give them: post-processing of RINEX observations (companion.replay_receiver)."""
        return self._poll_rtcm(t_rx_ns) + self._feed_messages(list(msgs))

    def feed(self, kind: str, t_rx_ns: int, data: bytes) -> list[NavSolution]:
        self.counters[f"records {kind}"] += 1
        try:
            return self._feed(kind, t_rx_ns, data)
        except Exception:
            self._exception(kind)
            return []

    def _exception(self, kind: str) -> None:
        """A bug or an input nobody foresaw must not stop the service: count, log (the first ten
        with a traceback), carry on.  Deterministic: replay takes the same path."""
        self.counters[f"pipeline exceptions ({kind})"] += 1
        n = sum(v for k, v in self.counters.items() if k.startswith("pipeline exceptions"))
        if n <= 10:
            log.exception("pipeline error on a %s record (%d so far)", kind, n)

    def _feed(self, kind: str, t_rx_ns: int, data: bytes) -> list[NavSolution]:
        if kind == "mavlink":
            try:
                msgs = self.frame_parser.feed(bytes(data))
            except Exception:
                self.counters["mavlink parse errors"] += 1
                return []
            out: list[NavSolution] = []
            for msg in msgs:
                try:
                    out += self.feed_mavlink(t_rx_ns, msg)
                except Exception:
                    self._exception("mavlink")
            return out
        if kind == "ubx":
            return self._poll_rtcm(t_rx_ns) + self._feed_messages(self.ubx.feed(bytes(data)))
        if kind == "rtcm":
            # the receive time closes a base epoch whose last MSM frame was lost (0.3-s timeout)
            return self._feed_rtcm_messages(self.rtcm.feed(bytes(data), t_rx_ns * 1e-9))
        return []

    def _mavlink_parse_error(self, exc) -> None:
        self.counters["mavlink parse errors"] += 1

    def _poll_rtcm(self, t_rx_ns: int) -> list[NavSolution]:
        """A base epoch left open by a lost last frame closes on time even while no RTCM arrives."""
        msgs = self.rtcm.poll(t_rx_ns * 1e-9)
        return self._feed_rtcm_messages(msgs) if msgs else []

    def _feed_rtcm_messages(self, msgs) -> list[NavSolution]:
        ov = self.cfg.corrections.base_position_ecef_m
        if ov is not None:
            # surveyed coordinates from the configuration replace the caster's 1005/1006
            if not self._base_override_sent:
                msgs = [BaseStationPosition(0, np.asarray(ov, float))] + msgs
                self._base_override_sent = True
            msgs = [BaseStationPosition(x.station_id, np.asarray(ov, float), x.antenna_height_m)
                    if isinstance(x, BaseStationPosition) else x for x in msgs]
        desc = self.rtcm.base_descriptor
        if desc is not None and desc.antenna:
            self.engine.name_base_antenna(desc.antenna)     # for [filter] rtk_antennas
        return self._feed_messages(msgs)

    def feed_mavlink_record(self, t_rx_ns: int, msg) -> list[NavSolution]:
        """Live path: the link already parsed the frame that is logged; same result as
        ``feed('mavlink', t, msg.get_msgbuf())``."""
        self.counters["records mavlink"] += 1
        try:
            return self.feed_mavlink(t_rx_ns, msg)
        except Exception:
            self._exception("mavlink")
            return []

    def feed_mavlink(self, t_rx_ns: int, msg) -> list[NavSolution]:
        """One parsed MAVLink message (the live service passes the link's parsed object; replay
        parses the logged frame: the same bytes give the same fields)."""
        mt = msg.get_type()
        if mt == "BAD_DATA" or mt.startswith("UNKNOWN"):
            self.counters["mavlink bad data"] += 1
            return []
        if (msg.get_srcSystem(), msg.get_srcComponent()) != self.target:
            self.counters["mavlink from other components"] += 1
            return []
        out: list[NavSolution] = self._poll_rtcm(t_rx_ns)
        if mt in ("HIGHRES_IMU", "RAW_IMU", "SCALED_IMU2", "SCALED_IMU3"):
            out += self._imu(msg)
        elif mt == "SYSTEM_TIME":
            self.time_map.update_from_message(msg)
            self._check_reboot()
        elif mt == "ATTITUDE":
            self.time_map.update_from_message(msg)
            self._check_reboot()
            vals = (msg.roll, msg.pitch, msg.yaw)
            if all(math.isfinite(v) for v in vals):
                self.attitude = (int(msg.time_boot_ms), *vals)
                self._ground_heading(msg)
            else:
                self.counters["attitude not finite"] += 1
        elif mt == "SERIAL_CONTROL":
            if msg.flags & m.SERIAL_CONTROL_FLAG_REPLY and msg.device == self.serial_device:
                n = max(0, min(int(msg.count), 70))
                if n:
                    out += self._feed_messages(self.ubx.feed(bytes(msg.data[:n])))
        elif mt == "GPS_RAW_INT":
            out += self._gps_raw(msg)
        elif mt == "HEARTBEAT":
            self.vehicle_type = int(msg.type)
            self.disarmed = msg.system_status == m.MAV_STATE_STANDBY
            self._update_ground_mode()
        elif mt == "EXTENDED_SYS_STATE":
            self.landed_state = int(msg.landed_state)
            self._update_ground_mode()
        return out

    def _update_ground_mode(self) -> None:
        """On the ground = a ground vehicle (rover, boat) always; otherwise the autopilot's landed
        state when it reports one (ON_GROUND also covers a taxiing aircraft), else disarmed.
        ZUPT/NHC follow it (the engine's NHC is off in flight)."""
        if self.vehicle_type in GROUND_VEHICLE_TYPES:
            on_ground = True
        elif self.landed_state not in (None, m.MAV_LANDED_STATE_UNDEFINED):
            on_ground = self.landed_state == m.MAV_LANDED_STATE_ON_GROUND
        else:
            on_ground = self.disarmed
        if on_ground != self.on_ground:
            self.counters["ground mode on" if on_ground else "ground mode off (airborne)"] += 1
        self.on_ground = on_ground
        self.engine.set_ground_mode(on_ground)

    def _check_reboot(self) -> None:
        if self.time_map.boot_epoch != self._boot_epoch:
            self._boot_epoch = self.time_map.boot_epoch
            self.counters["autopilot reboots"] += 1
            self.attitude = None
            self.last_imu = None
            self.heading.restart()
            if self.cluster is not None:
                self._restart_cluster()
            self._reinit("autopilot reboot")

    def _adopt_broadcast_klobuchar(self) -> None:
        """Klobuchar coefficients from the navigation message (subframe 4 page 18, once the UBX
        decoder's LNAV assembler exposes them as ``klobuchar``) for the standalone pseudorange
        models, unless the configuration gave its own (``filter.klobuchar``) or
        ``gnss.broadcast_klobuchar`` is false.  DGPS-corrected ranges never use it."""
        self.adopt_klobuchar(getattr(getattr(self.ubx, "ephemerides", None), "klobuchar", None),
                             "the navigation message")

    def adopt_klobuchar(self, klob, source: str) -> None:
        """Klobuchar coefficients ``(alpha[4], beta[4])`` from ``source`` (the navigation message, a
        RINEX navigation header in post-processing) for the standalone pseudorange models, unless
        the configuration gave its own or ``gnss.broadcast_klobuchar`` is false."""
        eng = self.engine
        if klob is None or not getattr(self.cfg.gnss, "broadcast_klobuchar", True):
            return
        klob = tuple(tuple(float(x) for x in part) for part in klob)
        if klob == eng.cfg.klobuchar or getattr(self.cfg.filter, "klobuchar", None) is not None:
            return
        eng.cfg = dataclasses.replace(eng.cfg, klobuchar=klob)
        self.counters[f"klobuchar from {source}"] += 1
        log.info("ionosphere: Klobuchar coefficients from %s", source)

    def _feed_messages(self, msgs) -> list[NavSolution]:
        if msgs:
            self._adopt_broadcast_klobuchar()
        for msg in msgs:
            if isinstance(msg, GnssEpoch):
                if self.rtk_enabled:
                    msg = self._rtk_epoch(msg)
                if msg.source == "base":
                    self.engine.process(msg)       # counts an epoch it cannot use yet
                    self._announce_base_check()
                    if self.engine.base is None:
                        # joining a running caster: observations before the station position
                        # (1005/1006) are not corrections yet; taking them for a base flipped the
                        # mode tight/loose/tight and the filter diverged (sitl attack, slow header)
                        continue
                    self.base_seen = True
                    self._base_times = (self._base_times + [msg.t_gps])[-10:]
                    self._release_held()
                else:
                    self._rover_epoch(msg)
            elif isinstance(msg, (GpsEphemeris, GlonassEphemeris, BaseStationPosition)):
                self.engine.process(msg)
                if isinstance(msg, BaseStationPosition):
                    self._announce_base_check()
            elif isinstance(msg, GnssFix):
                self.counters["receiver fixes (NAV-PVT, not fused)"] += 1
            elif isinstance(msg, GnssBaseline):
                self.counters["moving baselines (NAV-RELPOSNED)"] += 1
                if self.engine.initialized:
                    self.engine.process(msg)
                    if msg.carrier_fixed and self.cfg.gnss.moving_baseline_b_m is not None:
                        self.heading.trusted_heading_fused(msg.t_gps)
        return []

    def _announce_base_check(self) -> None:
        """One event when the base's position stops being believed, its epochs stop being used,
        or another station takes over (companion.nav.base_check): not one per 1005 or epoch."""
        chk = self.engine.base_check
        now = (chk.candidate is not None, chk.skipping, self.engine.base_station_changes)
        before, self._base_check_state = self._base_check_state, now
        if now[0] and not before[0]:
            self._event(m.MAV_SEVERITY_WARNING, "base position far from its own code: not believed")
        if now[1] and not before[1]:
            self._event(m.MAV_SEVERITY_WARNING, "base epochs far from base position: unused")
        if now[2] > before[2]:
            self._event(m.MAV_SEVERITY_WARNING, "base station changed: RTK restarts")

    def _rtk_epoch(self, epoch: GnssEpoch) -> GnssEpoch:
        """With RTK on: GPS tracking families renamed to one code on both receivers (a u-blox
        rover's L2L pairs with a base's 2X; with its 2W only when the base has no 2X, in a group of
        its own: companion.rtk_signals), and a base epoch cut to the systems the engine positions
        with (``[filter] systems``; each is double-differenced within itself)."""
        out = rtk_epoch(epoch)
        if out is not epoch:
            self.counters[f"rtk: {epoch.source} epochs with signals renamed to their family"] += 1
        if out.source == "base":
            systems = self.engine.cfg.systems
            kept = tuple(o for o in out.observations if o.sat[:1] in RTK_SYSTEMS and o.sat[:1] in systems)
            if len(kept) != len(out.observations):
                out = dataclasses.replace(out, observations=kept)
        return out

    # ------------------------------------------------------------------ IMU
    def _new_cluster(self) -> ImuCluster:
        """Every unit with the filter's IMU noise densities (units of one autopilot are alike)."""
        f = self.cfg.filter
        return ImuCluster(ClusterConfig(noise={}, primary_id=0, output_id=CLUSTER_OUTPUT_ID,
                                        default_noise=UnitNoise(f.gyro_arw_rad_per_sqrt_s,
                                                                f.accel_vrw_mps_per_sqrt_s)))

    def _restart_cluster(self) -> None:
        """After a reboot or a time jump the units' time histories are void: start over (the old
        cluster's counters are kept in the pipeline counters as 'imu cluster before restart: ...')."""
        old = self.cluster
        for k, v in old.counters.items():
            self.counters[f"imu cluster before restart: {k}"] += v
        self.cluster = self._new_cluster()
        self._primary_boot_us.clear()

    def _imu(self, msg) -> list[NavSolution]:
        if self.cluster is not None:
            return self._imu_cluster(msg)
        s = self.imu_dec.decode(msg, self.time_map)
        self._check_reboot()
        if s is None:
            return []
        if self.imu_dec.message != self._imu_full_scale_for:
            self._set_imu_full_scale((self.imu_dec.message,))
        if not self._imu_finite(s):
            return []
        boot_us = int(getattr(msg, "time_usec", getattr(msg, "time_boot_ms", 0) * 1000))
        return self._imu_sample(s, boot_us)

    def _set_imu_full_scale(self, message_types) -> None:
        """The screen's clip limits: the smallest full scale of the streams in use, per message type
        (companion.nav.imu_screen), unless ``mavlink.imu_accel_full_scale_mps2`` /
        ``imu_gyro_full_scale_radps`` say otherwise (0 = per message type)."""
        scr = self.engine.imu_screen
        self._imu_full_scale_for = message_types[0] if len(message_types) == 1 else None
        if scr is None:
            return
        fs = [FULL_SCALE_BY_MESSAGE.get(t, FULL_SCALE_BY_MESSAGE["HIGHRES_IMU"]) for t in message_types]
        acc = float(getattr(self.cfg.mavlink, "imu_accel_full_scale_mps2", 0.0) or min(f.accel_mps2 for f in fs))
        gyro = float(getattr(self.cfg.mavlink, "imu_gyro_full_scale_radps", 0.0) or min(f.gyro_radps for f in fs))
        scr.set_full_scale(ImuFullScale(acc, gyro))
        self.heading.set_full_scale(ImuFullScale(acc, gyro))

    def _imu_finite(self, s: ImuSample, unit: str = "") -> bool:
        if all(math.isfinite(x) for x in (*s.dtheta_b.tolist(), *s.dv_b.tolist())):
            return True
        self.counters[f"imu{unit} sample not finite (dropped)"] += 1
        return False

    def _imu_cluster(self, msg) -> list[NavSolution]:
        """One message of one cluster unit: decode, push; process the fused samples that are ready."""
        mt = msg.get_type()
        msg_id = int(getattr(msg, "id", 0))
        match = [u for u, (t, i, _) in enumerate(self.cluster_streams) if t == mt and i == msg_id] or \
                [u for u, (t, i, _) in enumerate(self.cluster_streams) if t == mt and i is None]
        if not match:
            self.counters[f"imu stream not in the cluster: {mt}"] += 1
            return []
        unit = match[0]
        s = self.cluster_streams[unit][2].decode(msg, self.time_map)
        self._check_reboot()
        if s is None or not self._imu_finite(s, f" {unit}"):
            return []
        newest = max((u.t_mid[-1] for u in self.cluster.units.values() if u.t_mid), default=None)
        if newest is not None and abs(s.t_gps - newest) > REINIT_GAP_S:
            self._restart_cluster()     # time jump: start the histories over; the engine re-initialises
            self.counters["imu cluster restarts: time jump"] += 1      # on the fused stream's own jump
        if unit == 0:
            self._primary_boot_us[s.t_gps] = int(getattr(msg, "time_usec", getattr(msg, "time_boot_ms", 0) * 1000))
        n_events = len(self.cluster.events)
        fused = self.cluster.push(ImuSample(s.t_gps, s.dt_s, s.dtheta_b, s.dv_b, unit))
        for t, uid, what, detail in self.cluster.events[n_events:]:
            name = "" if uid is None else f" {uid} ({self.cfg.mavlink.imu_cluster[uid]})"
            sev = m.MAV_SEVERITY_INFO if what == "readmitted" else m.MAV_SEVERITY_WARNING
            self._event(sev, f"IMU{name} {what}: {detail}")
        out: list[NavSolution] = []
        for f in fused:
            out += self._imu_sample(f, self._primary_boot_us.pop(f.t_gps, -1))
        if len(self._primary_boot_us) > 1000:      # primary samples the cluster never emitted
            for t in sorted(self._primary_boot_us)[:-100]:
                del self._primary_boot_us[t]
        return out

    def _imu_sample(self, s: ImuSample, boot_us: int) -> list[NavSolution]:
        """One IMU sample (of the single stream or fused) into the engine; a solution at the first
        sample of each output slot."""
        self.imu_count += 1
        self.heading.imu(s)
        eng = self.engine
        if eng.initialized:
            step = s.t_gps - eng.t_gps
            if abs(step) > REINIT_GAP_S:
                self._reinit("IMU time jump", f"{step:+.1f} s")
                # the boot-to-GPS mapping is in doubt until SYSTEM_TIME confirms it: no loose
                # (GPS_RAW_INT) initialisation for another RAW_TIMEOUT_S
                self.last_raw_t = s.t_gps
        elif self.last_imu is None and self.raw_expected:
            self.last_raw_t = s.t_gps        # start (or reboot): give raw observations a chance
        self.last_imu = s
        self.last_imu_boot_us = boot_us
        if not eng.initialized:
            if not self.raw_expected or s.t_gps - self.last_raw_t > RAW_TIMEOUT_S:
                self._try_init_loose()
            return []
        eng.process(s)
        if self._held:
            self._release_held(s.t_gps)
        slot = math.floor(s.t_gps * self.output_rate_hz)
        if slot == self._last_output_slot:
            return []
        self._last_output_slot = slot
        sol = eng.solution()
        if sol.status == "untrusted":
            self._reinit("solution untrusted")
        elif sol.status == "diverged":
            # injection stops with this solution; start over from GNSS, on probation
            self._reinit("diverged", sol.extras.get("integrity_reason", ""))
            self._probation_next = True
        self._announce_hold(sol.extras.get("integrity"))
        return [self._finish(sol)]

    def next_output_t_gps(self) -> float | None:
        """The GPS time that opens the next output slot: its first IMU sample brings the next
        solution (None before the first solution or while not initialised)."""
        if self._last_output_slot is None or not self.engine.initialized:
            return None
        return (self._last_output_slot + 1) / self.output_rate_hz

    AP_HEADING_PERIOD_S = 0.1
    AP_HEADING_SIGMA_RAD = math.radians(5.0)

    def _ground_heading(self, msg) -> None:
        """At rest with one antenna our heading is unobservable (ZARU holds it, nothing corrects
        it): keep it on the autopilot's compass heading, ten readings a second, instead of the copy
        taken at initialisation, which can predate the autopilot's own convergence (ArduCopter
        SITL: 10 deg off; PX4 SIH: a 13-deg yaw reset a few seconds after ours starts).  Off with
        ``mavlink.autopilot_heading_on_ground`` or a dual-antenna heading."""
        eng = self.engine
        if not (eng.initialized and self.on_ground and self.cfg.mavlink.autopilot_heading_on_ground) \
                or self.cfg.gnss.moving_baseline_b_m is not None or not self.heading.attitude_yaw_trusted:
            return
        t_boot = msg.time_boot_ms * 1e-3
        if t_boot - self._last_ap_heading_boot_s < self.AP_HEADING_PERIOD_S:
            return
        t_gps = self.time_map.to_gps(t_boot)
        if t_gps is None:
            return
        self._last_ap_heading_boot_s = t_boot
        # follow_heading: the compass error is the same from one reading to the next (a wandering
        # or reset autopilot yaw): averaging the readings would claim a certainty they do not have
        # and lag the autopilot by seconds (PX4 SIH: yaw resets of 2-13 deg)
        eng.process(GnssAttitude(t_gps, heading_rad=float(msg.yaw), sigma_heading_rad=self.AP_HEADING_SIGMA_RAD,
                                 autopilot_clock=True, follow_heading=True))
        self.counters["autopilot heading fused (on the ground)"] += 1

    def _announce_hold(self, integrity: str | None) -> None:
        """One event when the GNSS position starts / stops being held back (companion.nav.integrity)."""
        holding = integrity == "hold"
        if holding != self._position_hold:
            self._position_hold = holding
            if holding:
                self.counters["integrity: position hold"] += 1
                self._event(m.MAV_SEVERITY_WARNING, "GNSS position rejected: disagrees with INS (spoofed?)")
            else:
                self._event(m.MAV_SEVERITY_INFO, "GNSS position agrees with INS again")

    def _finish(self, sol: NavSolution) -> NavSolution:
        o = self.cfg.output
        sr = sol.sigma_r_n_m
        sig_h, sig_v = math.hypot(sr[0], sr[1]), float(sr[2])
        # after a stop on sigma, resume only below a fraction of the thresholds: a sigma hovering
        # at the threshold (coasting growth against GNSS updates) must not switch every second
        k = self.resume_sigma_fraction if self._sigma_hold else 1.0
        sigma_ok = sig_h <= k * o.max_sigma_h_m and sig_v <= k * o.max_sigma_v_m
        good = (sol.status in ("nav", "coasting") and bool(np.all(np.isfinite(sol.r_e)))
                and bool(np.all(np.isfinite(sr))))
        inject = bool(good and sigma_ok)
        heading_gate = ""                             # why the heading gate withheld this one (STATUSTEXT)
        if inject and not self.heading.gate():         # companion.heading_watch
            inject, heading_gate = False, self.heading.gate_reason
        if good and not sigma_ok and self.output_state == "injecting":
            self._sigma_hold = True       # stopped on sigma (not the first convergence after an init)
        elif inject:
            self._sigma_hold = False
        # protection level gate (companion.nav.protection, output.max_hpl_m), own hysteresis
        hpl_ok = self._hpl_ok(sol)
        if good and not hpl_ok and self.output_state == "injecting":
            self._hpl_hold = True
        inject = inject and hpl_ok
        if inject:
            self._hpl_hold = False
        sol.extras.update({"inject": inject, "mode": self.mode, "imu_count": self.imu_count,
                           "t_boot_us": self.last_imu_boot_us})
        sol = self._with_fix(sol)
        state = "injecting" if inject else f"not injecting ({sol.status})"
        if sol.status == "suspect":
            state = self.output_state     # a pause of one epoch or two is not a change to announce
        if state != self.output_state:
            if inject:
                self._event(m.MAV_SEVERITY_INFO, f"nav OK {self.mode}: sigma_h {sig_h:.2f} m")
            elif sol.status not in ("diverged", "converging") and (
                    self.output_state in ("init", "injecting")):     # not every change of the reason
                if heading_gate:       # the position is good: say what held it back
                    self._event(m.MAV_SEVERITY_WARNING, f"nav not injected: {heading_gate}")
                else:
                    self._event(m.MAV_SEVERITY_WARNING, f"nav not injected: {sol.status} sigma_h {sig_h:.1f} m"
                                + ("" if hpl_ok else f" HPL {float(sol.extras.get('hpl_m', math.nan)):.1f} m"))
            self.output_state = state
        self.counters["solutions"] += 1
        self.counters["solutions injectable" if inject else "solutions withheld"] += 1
        self.last_solution = sol
        return sol

    def _with_fix(self, sol: NavSolution) -> NavSolution:
        """The solution with the number of fixed DD ambiguities of its fix, and the fix state
        announced on a change that held FIX_ANNOUNCE_HOLD_S (no STATUSTEXT per flapping epoch)."""
        rtk = getattr(self.engine, "rtk", None)
        if sol.fix_state == "fixed" and rtk is not None:
            sol = dataclasses.replace(sol, n_fixed=int(rtk.status.n_fixed))
        self._announce_fix(sol)
        return sol

    def _announce_fix(self, sol: NavSolution) -> None:
        state = sol.fix_state
        if not self.rtk_enabled:
            return
        if state == self._fix_announced:
            self._fix_candidate = None
            return
        if self._fix_candidate is None or self._fix_candidate[0] != state:
            self._fix_candidate = (state, sol.t_gps)
        if sol.t_gps - self._fix_candidate[1] < FIX_ANNOUNCE_HOLD_S:
            return
        before, self._fix_announced, self._fix_candidate = self._fix_announced, state, None
        self.counters[f"rtk fix state announced: {state}"] += 1
        if state == "fixed":
            self._event(m.MAV_SEVERITY_INFO, f"RTK fixed: {sol.n_fixed} amb, ratio {sol.fix_ratio:.1f}")
        elif state == "float":
            self._event(m.MAV_SEVERITY_INFO if before == "none" else m.MAV_SEVERITY_WARNING,
                        "RTK float" + (" (fix lost)" if before == "fixed" else ""))
        else:
            self._event(m.MAV_SEVERITY_WARNING, f"RTK none (was {before})")

    def _hpl_ok(self, sol: NavSolution) -> bool:
        """HPL within output.max_hpl_m (below resume_hpl_fraction of it after a stop on it).  The
        engine's solutions always carry one (NaN = not computable: not injected); a solution
        without the key (not from the engine) is not gated on it."""
        if "hpl_m" not in sol.extras:
            return True
        hpl = float(sol.extras["hpl_m"])
        k = self.resume_hpl_fraction if self._hpl_hold else 1.0
        return math.isfinite(hpl) and hpl <= k * self.max_hpl_m

    # ------------------------------------------------------------------ GNSS
    def _rover_epoch(self, epoch: GnssEpoch) -> None:
        self.counters["rover epochs"] += 1
        usable = self._usable(epoch)
        if not usable:
            self.counters["rover epochs without ephemerides"] += 1
        if self.last_imu is not None and usable:
            self.last_raw_t = self.last_imu.t_gps    # raw observations are usable: no loose fallback
        if usable:
            self.heading.epoch_velocity(epoch, self._t_imu())
        if self.wait_for_base and self.base_seen and self.engine.initialized:
            self._held.append(epoch)
            self._release_held()
            return
        self._use_rover_epoch(epoch)

    def _release_held(self, t_now: float | None = None) -> None:
        """Process held rover epochs whose base epoch arrived, or that waited BASE_WAIT_S."""
        if not self._held:
            return
        if t_now is None:
            t_now = self.last_imu.t_gps if self.last_imu is not None else -math.inf
        keep = []
        for ep in self._held:
            have_base = any(abs(tb - ep.t_gps) < 0.05 for tb in self._base_times)
            if have_base:
                self._use_rover_epoch(ep)
            elif t_now - ep.t_gps > BASE_WAIT_S:
                self.counters["rover epoch used without its base epoch"] += 1
                self._use_rover_epoch(ep)
            else:
                keep.append(ep)
        self._held = keep

    def _usable(self, epoch: GnssEpoch) -> bool:
        """At least four satellites of the engine's systems with ephemerides: the epoch can position
        the filter.  Satellites, not signals (a dual-frequency receiver reports two per satellite),
        and only the systems the engine uses: Galileo/BeiDou/QZSS ephemerides from SFRBX or RTCM
        must not make an epoch with three GPS satellites look usable."""
        have = set(self.engine.ephemerides.sats)
        systems = self.engine.cfg.systems
        return len({o.sat for o in epoch.observations if o.sat in have and o.sat[0] in systems}) >= 4

    def _use_rover_epoch(self, epoch: GnssEpoch) -> None:
        if self.engine.initialized:
            # only an epoch that can be used switches to tight coupling: raw epochs without
            # ephemerides (no corrections stream) beside loose GPS_RAW_INT fusion made the mode
            # flap every second; back to loose happens after RAW_TIMEOUT_S without usable epochs
            if self.mode != "tight":
                if not self._usable(epoch):
                    self.counters["rover epochs not used (loose mode, no ephemerides)"] += 1
                    return
                self._event(m.MAV_SEVERITY_INFO, "nav: raw GNSS observations, tight coupling")
                self.mode = "tight"
            self.engine.process(epoch)
            return
        self._try_init_tight(epoch)

    def _fresh_attitude(self):
        """(roll, pitch, yaw) of a recent ATTITUDE, else None (counted)."""
        if self.attitude is None or self.last_imu_boot_us is None:
            self.counters["init: waiting for ATTITUDE"] += 1
            return None
        t_ms, roll, pitch, yaw = self.attitude
        if abs(self.last_imu_boot_us * 1e-3 - t_ms) > ATTITUDE_MAX_AGE_S * 1e3:
            self.counters["init: ATTITUDE too old"] += 1
            return None
        return roll, pitch, yaw

    def _initial_attitude(self, r_e):
        """(C_b_e, tilt sigma, heading sigma) to initialise with, or None (counted): the fresh
        ATTITUDE or the yaw from motion, as companion.heading_watch decides."""
        return self.heading.initial_attitude(r_e, self._fresh_attitude(), self.init_sigmas.att_rad)

    def _t_imu(self) -> float | None:
        """GPS time of the newest IMU sample (None before the first)."""
        return self.last_imu.t_gps if self.last_imu is not None else None

    def _biases_not_to_keep(self) -> None:
        """The ATTITUDE yaw proved wrong: biases a filter learnt on a wrong heading explain its
        errors, not the sensors; the next initialisation starts them from zero."""
        self._keep_biases_next = False

    def _try_init_tight(self, epoch: GnssEpoch) -> None:
        s = self.last_imu
        if s is None:
            self.counters["init: waiting for IMU"] += 1
            return
        if s.t_gps - epoch.t_gps > 0.5 or s.t_gps < epoch.t_gps - 0.5:
            self.counters["init: epoch and IMU times apart"] += 1
            return
        eng = self.engine
        use_dgps = self.cfg.filter.use_dgps and eng.dgps is not None
        sol = spp_epoch(epoch, eng.ephemerides, dgps=eng.dgps if use_dgps else None,
                        klobuchar=eng.cfg.klobuchar,
                        elevation_mask_rad=math.radians(self.cfg.filter.elevation_mask_deg),
                        systems=eng.cfg.systems, signal=eng.cfg.pseudorange_signal)
        if sol is None or not np.all(np.isfinite(sol.r_e)):
            self.counters["init: no SPP solution"] += 1
            return
        att = self._initial_attitude(sol.r_e)
        if att is None:
            return
        C, att_sigmas = att[0], att[1:]
        sig = self.init_sigmas
        # the newest IMU sample is at GPS time tag + dt_imu (the epoch is on the receiver's time)
        dt = s.t_gps + self._imu_time_offset_prior() - epoch.t_gps
        if sol.v_e is not None and np.all(np.isfinite(sol.v_e)):
            v, sv = np.asarray(sol.v_e, float), sig.vel_doppler_mps
        elif self.disarmed:                 # disarmed: not moving (a ground vehicle may drive)
            v, sv = np.zeros(3), sig.vel_ground_mps
        elif self.last_fix is not None and self.last_fix.v_e is not None:
            v, sv = np.asarray(self.last_fix.v_e, float), sig.vel_gps_raw_mps
        else:
            self.counters["init: no velocity"] += 1
            return
        r_imu = sol.r_e - C @ self.lever_b + v * dt
        self._initialize(s.t_gps, r_imu, v, C, sig.pos_dgps_m if use_dgps else sig.pos_standalone_m, sv,
                         pos_cov_e_m2=sol.cov_r_e,
                         clock_bias_m=sol.clock_bias_m + sol.clock_drift_mps * dt,
                         clock_drift_mps=sol.clock_drift_mps if math.isfinite(sol.clock_drift_mps) else 0.0,
                         how=f"SPP {'DGPS' if use_dgps else 'standalone'} {sol.n_sats} sats", att_sigmas=att_sigmas)
        self.mode = "tight"

    def _rtk_fixed_last(self) -> bool:
        """The last raw epoch the RTK update saw was fixed (its status outlives a gap)."""
        rtk = self.engine.rtk if self.rtk_enabled else None
        return rtk is not None and rtk.status is not None and rtk.status.fix_state == FIX_FIXED

    def _gps_raw(self, msg) -> list[NavSolution]:
        fix = gps_fix_from_gps_raw_int(msg, self.time_map, leap_seconds=self.cfg.gnss.leap_seconds,
                                       latency_s=self.gps_raw_latency_s)
        if fix is None:
            self.counters["GPS_RAW_INT without fix/time"] += 1
            return []
        fix = dataclasses.replace(fix, vertical_velocity_valid=False)   # speed and course only
        key = int(msg.time_usec)
        if key == self._last_fix_key:
            return []                       # the same fix repeated at the stream rate
        self._last_fix_key = key
        self.last_fix = fix
        self.counters["GPS_RAW_INT fixes"] += 1
        if fix.t_gps - self._last_fix_t > GPS_FIX_GAP_S and self._rtk_fixed_last() and self.last_imu is not None \
                and self.last_imu.t_gps - self.last_raw_t > RAW_TIMEOUT_S:
            self.last_raw_t = self.last_imu.t_gps
            self.counters["GPS_RAW_INT back after a gap: raw observations awaited first"] += 1
        self._last_fix_t = fix.t_gps
        eng = self.engine
        # GPS yaw (dual-antenna GPS on the autopilot): cdeg, 0 = not provided, 65535 = unavailable
        yaw_cdeg = int(getattr(msg, "yaw", 0) or 0)
        sig_yaw = self.cfg.gnss.gps_raw_yaw_sigma_deg
        if 0 < yaw_cdeg <= 36000 and sig_yaw > 0:
            self.counters["GPS_RAW_INT yaw"] += 1
            if eng.initialized:
                eng.process(GnssAttitude(fix.t_gps, heading_rad=math.radians((yaw_cdeg % 36000) / 100.0),
                                         sigma_heading_rad=math.radians(sig_yaw), autopilot_clock=True))
                self.heading.trusted_heading_fused(fix.t_gps)
        s = self.last_imu
        loose = not self.raw_expected or (s is not None and s.t_gps - self.last_raw_t > RAW_TIMEOUT_S)
        if not loose:
            return []
        if fix.v_e is not None:
            self.heading.velocity(fix.t_gps, fix.r_e, np.asarray(fix.v_e, float), fix.sigma_vel_mps, self._t_imu())
        if not eng.initialized:
            self._try_init_loose()
            return []
        if self.mode != "loose":
            self.mode = "loose"
            self._announce_loose()
        eng.process(fix)
        self.counters["loose fixes fused"] += 1
        return []

    def raw_missing_reason(self) -> tuple[str, str]:
        """Why the tight filter has no usable raw observations, naming the missing UBX message (a
        factory-default u-blox sends neither RXM-RAWX nor RXM-SFRBX; issue 15): (short text for a
        STATUSTEXT, which the service cuts at 50 bytes with its "CC: ", and the hint for the log)."""
        configure = "'companion gnss configure' switches RXM-RAWX and RXM-SFRBX on"
        if not self.raw_expected:
            return "gnss.source none", "gnss.source is 'none'"
        if self.counters["rover epochs"] == 0:
            if self.ubx.counters.get("frames", 0) == 0:
                g = self.cfg.gnss
                where = (f"{g.serial_control_device} (SERIAL_CONTROL)" if g.source == "mavlink_serial_control"
                         else g.serial.port)
                return "no UBX from receiver", f"no UBX frame from the receiver on {where}"
            return "UBX but no RXM-RAWX", f"UBX frames arrive but no RXM-RAWX: raw output is off; {configure}"
        if not self.engine.ephemerides.sats:
            return ("RXM-RAWX, no ephemeris (SFRBX)",
                    f"RXM-RAWX but no ephemerides: no RXM-SFRBX and no RTCM 1019; {configure}")
        return f"no usable RXM-RAWX for {RAW_TIMEOUT_S:g} s", f"no usable RXM-RAWX for {RAW_TIMEOUT_S:g} s"

    def _announce_loose(self) -> None:
        short, hint = self.raw_missing_reason()
        self._event(m.MAV_SEVERITY_WARNING, f"nav loose: {short}")
        log.warning("loose GPS_RAW_INT fusion: %s", hint)

    def _try_init_loose(self) -> None:
        fix, s = self.last_fix, self.last_imu
        if fix is None or s is None or fix.fix_type < 3 or abs(s.t_gps - fix.t_gps) > 1.5:
            return
        att = self._initial_attitude(fix.r_e)
        if att is None:
            return
        C, att_sigmas = att[0], att[1:]
        sig = self.init_sigmas
        if self.disarmed:
            v, sv = np.zeros(3), sig.vel_ground_mps
        elif fix.v_e is not None:
            v, sv = np.asarray(fix.v_e, float), sig.vel_gps_raw_mps
        else:
            return
        r_imu = fix.r_e - C @ self.lever_b + v * (s.t_gps - fix.t_gps)
        self._initialize(s.t_gps, r_imu, v, C, max(fix.sigma_h_m, fix.sigma_v_m, 1.0), sv, clock_bias_m=None,
                         clock_drift_mps=0.0, how="GPS_RAW_INT fix (loose)", att_sigmas=att_sigmas)
        self.mode = "loose"
        if self.raw_expected:        # raw observations were configured: say by name what is missing
            self._announce_loose()

    def _initialize(self, t_gps, r, v, C, sig_pos, sig_vel, *, clock_bias_m, clock_drift_mps, how,
                    pos_cov_e_m2=None, att_sigmas=None) -> None:
        sig = self.init_sigmas
        tilt, heading = att_sigmas if att_sigmas is not None else (sig.att_rad, sig.att_rad)
        p0 = {"tilt_rad": tilt, "heading_rad": heading, "pos_m": sig_pos, "vel_mps": sig_vel, "ba_mps2": sig.ba_mps2,
              "bg_radps": sig.bg_radps, "clk_m": sig.clk_m, "drift_mps": sig.drift_mps,
              "pos_cov_e_m2": pos_cov_e_m2}
        probation, self._probation_next = self._probation_next, False
        b_a, b_g = self._biases_to_keep() if self._keep_biases_next else (None, None)
        offset = self._imu_time_offset_prior()       # same rule as the biases: before the flag is cleared
        self._keep_biases_next = False
        self.engine.initialize(t_gps, r, v, C, p0, clock_bias_m=clock_bias_m, clock_drift_mps=clock_drift_mps,
                               probation=probation, b_a=b_a, b_g=b_g, imu_time_offset_s=offset)
        self.counters["initialisations"] += 1
        self.last_init_reason = how
        self.output_state = "init"
        self._sigma_hold = False
        self._hpl_hold = False
        self._event(m.MAV_SEVERITY_INFO, f"nav init #{self.engine.reset_counter}: {how}"
                    + ("; not injected until consistent" if probation else ""))

    def _imu_time_offset_prior(self) -> float:
        """Prior mean of the IMU time-tag offset for the next initialisation: after a re-init of the
        same IMU stream (not a reboot: the time mapping starts over) the offset the filter had
        learnt, when within 3 sigma of the configured prior; else the configured mean."""
        f = self.cfg.filter
        learnt = self.engine.imu_time_offset_s
        if (self._keep_biases_next and math.isfinite(learnt)
                and abs(learnt - f.imu_time_offset_s) <= 3.0 * f.imu_time_offset_sigma_s):
            return float(learnt)
        return float(f.imu_time_offset_s)

    def _biases_to_keep(self):
        """After a re-init in flight (same IMU): the sensor biases the filter had learnt, when
        they are within 3 sigma of the turn-on uncertainty, as the prior mean of the new filter (its
        uncertainty is the turn-on one again); else zero.  Zero is known to be wrong by the turn-on
        bias, and re-learning it in flight, without the rest phase, takes the new filter long."""
        eng, sig = self.engine, self.init_sigmas
        ba, bg = eng.b_a, eng.b_g
        if (np.all(np.isfinite(ba)) and np.all(np.isfinite(bg)) and float(np.max(np.abs(ba))) <= 3.0 * sig.ba_mps2
                and float(np.max(np.abs(bg))) <= 3.0 * sig.bg_radps):
            self.counters["re-init: sensor biases kept"] += 1
            return ba.copy(), bg.copy()
        return None, None

    # ------------------------------------------------------------------ reporting
    def drain_events(self) -> list[tuple[int, str]]:
        ev, self.events = self.events, []
        return ev

    def health(self) -> dict:
        sol = self.last_solution
        filt = {"initialized": self.engine.initialized, "mode": self.mode, "init": self.last_init_reason,
                "reset_counter": self.engine.reset_counter,
                "integrity": {"state": self.engine.integrity.state, "reason": self.engine.integrity.reason}}
        if sol is not None:
            filt.update({"status": sol.status, "t_gps": sol.t_gps,
                         "sigma_r_ned_m": [round(float(x), 3) for x in sol.sigma_r_n_m],
                         "sigma_v_ned_mps": [round(float(x), 3) for x in sol.sigma_v_n_mps],
                         "inject": sol.extras.get("inject"),
                         "protection_level": {k: _round_or_none(sol.extras.get(k)) for k in
                                              ("hpl_m", "hpl_cov_m", "hpl_ss_m")}})
            reports = self.engine.epoch_reports
            if reports:          # the last rover epoch: satellites fused per system, the systems' clock offsets
                filt["satellites_by_system"] = dict(reports[-1].sats_by_system)
                filt["inter_system_bias_m"] = {name[4:]: round(float(v[0]), 2) for name, v in
                                               self.engine.block_states.items() if name.startswith("isb_")}
            if self.rtk_enabled:
                rtk = getattr(self.engine, "rtk", None)
                st = rtk.status if rtk is not None else None
                filt["rtk"] = {"fix_state": sol.fix_state, "fix_ratio": _round_or_none(sol.fix_ratio, 2),
                               "n_fixed": int(sol.n_fixed),
                               "n_ambiguities": int(st.n_ambiguities) if st is not None else 0,
                               "success_rate": _round_or_none(st.success_rate, 6) if st is not None else None,
                               "fix_state_announced": self._fix_announced}
            if "imu_time_offset_s" in sol.extras:     # dt_imu: GPS time of an IMU sample = tag + this
                filt.update({"imu_time_offset_s": round(float(sol.extras["imu_time_offset_s"]), 5),
                             "imu_time_offset_sigma_s": round(float(sol.extras["imu_time_offset_sigma_s"]), 5)})
        engine_counters = dict(self.engine.counters)
        for why, n in self.engine.ephemerides.rejections.items():   # duplicates, implausible records
            engine_counters[f"ephemerides rejected: {why}"] = n
        return {"filter": filt, "pipeline": dict(self.counters), "engine": engine_counters,
                "aid_sources": self.engine.aid.snapshot(),
                "yaw_gsf": self.heading.snapshot(),
                "imu": dict(self.imu_dec.counters), "time_map": dict(self.time_map.counters),
                **({"imu_cluster": self.cluster_health()} if self.cluster is not None else {}),
                "ubx": dict(self.ubx.counters), "rtcm": dict(self.rtcm.counters),
                # what the base says it is (RTCM 1007 / 1008 / 1033), when it says
                **({"rtcm_base": self.rtcm.base_descriptor.as_dict()} if self.rtcm.base_descriptor else {}),
                **({"rtk_antennas": self.engine.rtk_antennas.status()} if self.engine.rtk_antennas else {})}


    def cluster_health(self) -> dict:
        c = self.cluster
        names = self.cfg.mavlink.imu_cluster
        return {"units": {names[uid]: {"healthy": u.healthy, "window_stat": round(float(u.last_stat), 3)}
                          for uid, u in sorted(c.units.items())},
                "ambiguous": c.ambiguous, "counters": dict(c.counters),
                "decoders": {names[u]: dict(d.counters) for u, (_, _, d) in enumerate(self.cluster_streams)}}


def _round_or_none(x, nd: int = 3):
    return round(float(x), nd) if x is not None and math.isfinite(float(x)) else None


__all__ = ["NavPipeline", "InitSigmas", "FIX_ANNOUNCE_HOLD_S", "REINIT_GAP_S", "RAW_TIMEOUT_S"]
