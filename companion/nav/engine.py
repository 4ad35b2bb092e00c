"""The fusion engine: IMU-rate mechanization and covariance propagation, GPS-time interpolation of
the INS to each GNSS epoch, measurement selection, gating, closed-loop feedback, solution status.

Pure and synchronous: messages in, solutions out, no clocks, sockets or asyncio.  The same
sequence of inputs gives the same outputs bit for bit.

This module is the streaming loop (propagate, update, feedback, solution) and the raw-epoch
measurement selection; the engine's other jobs are mixins beside it: receiver solutions, GNSS
attitude/baselines and vehicle constraints (:mod:`.engine_aiding`), the course alignment and heading
resets (:mod:`.engine_heading`), clock and inter-system-bias seeding (:mod:`.engine_clock`); the
carrier bookkeeping of TDCP is :mod:`companion.gnss.phase`, the stillness test :mod:`.stillness`.

Timing.  A GNSS epoch is tagged with its GPS time ``t_gps``, which falls between IMU samples.  The
engine keeps a short history of the INS state at every IMU sample and evaluates the measurement
model at the INS state *linearly interpolated to t_gps* (seed 000 eqs 31-32), never at the nearest
sample.  An epoch that arrives before the IMU has passed its time waits in a queue; one that
arrives late (the usual case in the field: receivers report 20-100 ms after the epoch) is
interpolated from the history.  The correction is applied at the current IMU time: the epoch's rows
are referred across the latency with the error dynamics (velocity <- tilt x specific force and
accelerometer bias, position <- velocity, ...; :class:`.measurements.LatencyTransition`), and the
next TDCP interval starts from the correction referred back to the epoch.  Taking the errors as
constant over the latency cost nothing with a well-known attitude, but after an initialisation
in flight it was several TDCP sigmas and turned the heading the wrong way.

The IMU's time tags are the autopilot's boot time mapped to GPS time by SYSTEM_TIME, which lags by
the receiver latency; the filter estimates that offset (state ``dt_imu``, :mod:`.filter`).  The INS
and its history stay on the IMU's tags (``t_gps`` of the engine and of its solutions); a message
time-tagged by the receiver (raw epochs, NAV-RELPOSNED, SPP of an epoch) is looked up at
``t_gps - imu_time_offset_s`` (:meth:`NavEngine.imu_time_of`), one tagged on the autopilot's clock
(``autopilot_clock``: GPS_RAW_INT, ATTITUDE) at its own tag.  Shifting the look-up rather than the
IMU tags leaves the history, the IMU intervals and the shell's time comparisons untouched when the
estimate moves; the solution of an IMU sample is the vehicle at that sample's GPS time (tag +
offset), which is what the autopilot, stamping it with the sample's boot time, needs.
"""
from __future__ import annotations

import bisect
import dataclasses
import logging
import math
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np

from ..gnss.antenna_calibration import largest_change_m
from ..gnss.ephemeris_store import EphemerisStore
from ..gnss.phase import BaseCarrierBook, RoverCarrierBook
from ..gnss.prepare import prepare_epoch
from ..gnss.spp import spp_epoch
from ..gnss.glonass import GlonassEphemeris
from ..gnss.signals import clock_group
from ..rtk_signals import signals_for_system
from ..messages import (SPEED_OF_LIGHT_MPS, BaseStationPosition, GnssAttitude, GnssBaseline, GnssEpoch, GnssFix, GpsEphemeris,
                        ImuSample, NavSolution)
from .earth import OMEGA_IE_RADPS, C_n_e, ecef_to_geodetic, gravity_ecef, rotation_from_rotvec
from .slow_errors import raise_to_floor, slow_error_position_floor
from .filter import ErrorStateKalmanFilter, MeasurementBatch, ProcessNoise, UpdateReport
from .state_layout import DEFAULT_LAYOUT, REFERENCE_SYSTEM, StateLayout, isb_block_name
from .measurements import (InsPoint, LatencyTransition, antenna_state, doppler_batch, pseudorange_batch,
                           single_difference, tdcp_batch)
from .aid_status import AidSourceBook
from .base_check import ADOPT, BASE_POSITION_MAX_SPP_DIFF_M, SKIP, BaseStationCheck
from .imu_screen import ImuScreen
from .stillness import StillnessDetector
from .integrity import POSITION_SOURCES, IntegrityLimits, IntegrityMonitor, IntegrityState
from .chi2 import chi2_ppf
from .protection import ProtectionLevel
from .rtk_update import FIX_FIXED, FIX_FLOAT, FIX_NONE, RtkUpdate, RtkUpdateConfig
from .engine_aiding import ReceiverAiding
from .engine_clock import ClockSeeding
from .engine_heading import HeadingAlignment
from .engine_imu import ImuPath

log = logging.getLogger(__name__)


FLOOR_MAX_HEADING_SIGMA_RAD = math.radians(10.0)   # slow-error floor only once the heading is known
# a base position (RTCM 1005/1006: 0.1-mm resolution) or antenna model that moves by less is the same
BASE_MODEL_CHANGE_MIN_M = 0.001


@dataclass
class EngineConfig:
    """Everything that tunes the engine.  Units in the names."""

    noise: ProcessNoise
    lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    # which measurements
    use_pseudorange: bool = True
    use_dgps: bool = True            # pseudoranges need a DGPS correction (else standalone models)
    use_tdcp: bool = True
    use_doppler: bool = False
    use_loose: bool = False          # position/velocity from the receiver's own (SPP) fix instead
    elevation_mask_deg: float = 10.0
    gate_probability: float = 0.999
    # measurement noise
    sigma_doppler_mps: float = 0.1
    sigma_phase_m: float = 0.005
    sigma_phase_elevation_scaling: bool = False   # carrier noise x 1/sin(elevation)
    sigma_tdcp_floor_mps: float = 0.01
    sigma_pseudorange_floor_m: float = 0.0
    tdcp_max_interval_s: float = 1.5
    # 'auto': difference TDCP against the base station's own TDCP when the base has carrier phase
    # at both epochs (removes satellite clock dither, orbit and atmosphere rates); 'off': never
    tdcp_base_correction: str = "auto"
    # bookkeeping
    history_s: float = 2.0
    coasting_after_s: float = 3.0
    untrusted_sigma_h_m: float = 50.0
    clock_jump_sigmas: float = 8.0           # common pseudorange step, in sigmas of the clock, that re-seeds it
    clock_jump_min_m: float = 30.0
    # time-correlated pseudorange errors (multipath): weight as if one independent sample per
    # (1 + 2 tau / T) epochs, the Gauss-Markov effective-sample rule, so P does not shrink below
    # what averaging correlated errors can deliver
    pseudorange_correlation_time_s: float = 0.0
    slow_error_floor: bool = True            # P_pos >= one epoch of the slow errors alone
    # zero-velocity / zero-rate updates while the IMU shows the vehicle at rest (ground phases)
    zupt_enabled: bool = False
    zupt_window_s: float = 0.5
    zupt_accel_std_mps2: float = 0.05       # max std of each specific-force axis over the window
    zupt_gyro_std_radps: float = 0.005      # max std of each gyro axis over the window
    zupt_max_speed_mps: float = 0.5         # the INS must agree that it is (nearly) still
    zupt_sigma_mps: float = 0.02
    zaru_sigma_floor_radps: float = 2e-4
    # non-holonomic constraint for ground vehicles (seed 002); suspended after repeated rejections
    nhc_enabled: bool = False
    nhc_rate_hz: float = 10.0
    nhc_sigma_lateral_mps: float = 0.1
    nhc_sigma_vertical_mps: float = 0.1
    nhc_min_speed_mps: float = 1.0
    nhc_suspend_after_rejections: int = 3
    nhc_suspend_s: float = 5.0
    # in-motion heading alignment from the GNSS course over ground, on the ground only (see
    # companion.nav.course_alignment): the first epochs at speed, driving straight, give the heading
    course_alignment_enabled: bool = False
    course_alignment_min_speed_mps: float = 3.0
    course_alignment_max_yaw_rate_radps: float = 0.05
    course_alignment_slip_sigma_rad: float = 0.0175          # 1 deg
    course_alignment_reset_above_rad: float = 0.26           # 15 deg
    course_alignment_epochs: int = 5
    # 'undifferenced' or 'single_difference' (between satellites, seed 004: no clock states needed)
    measurement_form: str = "undifferenced"
    # measurement kinds gated leave-one-out (their rows share the clock; see filter.gate)
    leave_one_out_kinds: tuple = ("tdcp", "pseudorange")
    gravity_gradient_refresh_m: float = 200.0
    klobuchar: tuple | None = None
    # IMU time-tag offset dt_imu (GPS time of an IMU sample = its tag + dt_imu): prior mean and
    # 1-sigma; sigma 0 = not estimated (held at the mean).  Its random walk is in ProcessNoise.
    imu_time_offset_s: float = 0.0
    imu_time_offset_sigma_s: float = 0.0
    # constellations fused (RINEX letters among G, E, C, J: GPS, Galileo, BeiDou, QZSS); every
    # one's pseudoranges, carrier and Doppler are used, satellites of others are left out
    systems: str = "G"
    # pseudorange of each system: its single-frequency code ('L1C': GPS/QZSS L1 C/A, Galileo E1,
    # BeiDou B1I, with Klobuchar standalone) or the dual-frequency iono-free pair ('IF', per system
    # as companion.gnss.signals; x3 the code noise, no ionosphere model error)
    pseudorange_signal: str = "L1C"
    # a base position further than this from the base's own single-point solution is not believed
    # (companion.nav.base_check); the simulator's Selective Availability era needs kilometres
    base_max_spp_diff_m: float = BASE_POSITION_MAX_SPP_DIFF_M
    # inter-system bias blocks (companion.nav.state_layout): systems among E, C, J whose
    # pseudoranges carry their clock minus GPS's as a state, with this prior 1-sigma; its random
    # walk is in ProcessNoise.  Empty: one per clock group of ``systems`` after the first
    # (QZSS shares GPS's clock, as RTKLIB): see :meth:`bias_systems`.
    inter_system_biases: tuple[str, ...] = ()
    inter_system_bias_sigma_m: float = 100.0
    # dual-antenna moving baseline (NAV-RELPOSNED): body FRD vector from the moving-base antenna to
    # the rover antenna (None = not installed); a measured length further than the tolerance (plus
    # 3 sigma) from it is a wrong carrier fix and is rejected; float solutions are not used
    moving_baseline_b_m: tuple[float, float, float] | None = None
    baseline_length_tol_m: float = 0.03
    # IMU screening before integration (companion.nav.imu_screen): an axis at clip_fraction of the
    # stream's full scale, or further from the running median of the last imu_median_window samples
    # than the jump limits, is bridged with the last good sample and its covariance inflated
    imu_screen_enabled: bool = True
    imu_clip_fraction: float = 0.98
    imu_accel_jump_mps2: float = 60.0
    imu_gyro_jump_radps: float = 10.0
    imu_median_window: int = 9
    # divergence detection (companion.nav.integrity) over a sliding window of each GNSS source
    integrity_enabled: bool = True
    integrity_window_s: float = 5.0
    integrity_min_updates: int = 3
    integrity_min_rows: int = 10
    integrity_max_rejected_fraction: float = 0.5
    integrity_max_nis_mean: float = 4.0
    integrity_probation_max_rejected_fraction: float = 0.2
    # horizontal protection level (companion.nav.protection): the probability that the true error
    # exceeds the fault-free bound, and the missed-detection probability of a one-satellite fault
    hpl_integrity_risk: float = 1e-5
    hpl_missed_detection: float = 1e-3
    # carrier-phase RTK (companion.nav.rtk_update): DD phase and code against the base's epochs
    # with float ambiguity blocks and integer fixing, instead of the DGPS pseudoranges and TDCP,
    # whenever a base epoch (and its station position) is at hand; off so that the seed
    # experiments stay as published (not in the service's configuration yet: python -m sitl rtk)
    rtk_enabled: bool = False
    rtk_signals: tuple[str, ...] = ("L1C", "L2W")
    rtk_sigma_phase_a_m: float = 0.003
    rtk_sigma_phase_b_m: float = 0.003
    rtk_code_phase_ratio: float = 100.0
    rtk_max_base_age_s: float = 1.5
    rtk_ratio_threshold: float = 3.0
    rtk_min_fix_ambiguities: int = 4
    rtk_hold_sigma_cycles: float = 0.01
    rtk_iono_states: bool = True
    rtk_iono_sigma_zenith_m: float = 0.001
    rtk_iono_sigma_ppm: float = 1.0
    rtk_glonass_integers: bool = False        # GLONASS fixed too: one receiver model at both ends
    # receiver antenna calibrations (companion.nav.rtk_antennas): an ANTEX / NGS file, the rover's
    # type, the base's (empty: what the base's RTCM 1007/1008/1033 names)
    rtk_antennas: str = ""
    rtk_rover_antenna: str = ""
    rtk_base_antenna: str = ""

    def bias_systems(self) -> tuple[str, ...]:
        """Systems with an inter-system bias state: the configured ones, else every clock group
        of :attr:`systems` but the reference (GPS's when GPS is fused, else the first)."""
        if self.inter_system_biases:
            return tuple(self.inter_system_biases)
        groups = list(dict.fromkeys(clock_group(s) for s in self.systems))
        ref = REFERENCE_SYSTEM if REFERENCE_SYSTEM in groups else groups[0] if groups else REFERENCE_SYSTEM
        return tuple(g for g in groups if g != ref)

    def rtk_config(self) -> RtkUpdateConfig:
        return RtkUpdateConfig(signals=tuple(self.rtk_signals), systems=self.systems,  # DDs within each system
                               elevation_mask_deg=self.elevation_mask_deg,
                               sigma_phase_a_m=self.rtk_sigma_phase_a_m, sigma_phase_b_m=self.rtk_sigma_phase_b_m,
                               code_phase_ratio=self.rtk_code_phase_ratio, max_base_age_s=self.rtk_max_base_age_s,
                               ratio_threshold=self.rtk_ratio_threshold,
                               min_fix_ambiguities=self.rtk_min_fix_ambiguities,
                               hold_sigma_cycles=self.rtk_hold_sigma_cycles, gate_probability=self.gate_probability,
                               iono_states=self.rtk_iono_states, iono_sigma_zenith_m=self.rtk_iono_sigma_zenith_m,
                               iono_sigma_ppm=self.rtk_iono_sigma_ppm,
                               float_only_systems="" if self.rtk_glonass_integers else "R")


@dataclass
class EpochReport:
    """The outcome of one GNSS epoch."""

    t_gps: float
    reports: list[UpdateReport] = field(default_factory=list)
    rejected: dict = field(default_factory=dict)
    dx: np.ndarray | None = None
    applied: bool = False
    fix_state: str = FIX_NONE         # carrier-phase RTK: 'none', 'float' or 'fixed'
    fix_ratio: float = math.nan       # LAMBDA ratio of a fixed epoch
    n_fixed: int = 0                  # DD ambiguities fixed
    sats_by_system: dict = field(default_factory=dict)   # satellites with a fused row, per system letter


class NavEngine(ImuPath, ReceiverAiding, HeadingAlignment, ClockSeeding):
    """Tightly coupled INS/GNSS fusion.  Feed it with :meth:`process` (any message) in arrival order."""

    def __init__(self, config: EngineConfig):
        self.cfg = config
        self._init_imu_state()            # the packed nominal state and history (companion.nav.engine_imu)
        self.lever_arm_b = np.asarray(config.lever_arm_b_m, float)
        self.ephemerides = EphemerisStore()
        self.dgps = None
        self.base: BaseStationPosition | None = None
        self.counters: Counter = Counter()
        self.base_check = BaseStationCheck(self.counters, config.base_max_spp_diff_m)   # against the base's code
        self.base_station_changes = 0                    # another station took over (_base_station_changed)
        self.initialized = False
        self.kf: ErrorStateKalmanFilter | None = None
        self.t_gps = math.nan
        self.r_e = self.v_e = self.C_b_e = None
        self.b_a = np.zeros(3)
        self.b_g = np.zeros(3)
        self.clock_bias_m = 0.0
        self.clock_drift_mps = 0.0
        self.clock_initialized = False
        self.imu_time_offset_s = float(config.imu_time_offset_s)
        self.block_states: dict[str, np.ndarray] = {}    # nominal values of the layout's extra blocks
        self._pending: list = []           # GNSS messages waiting for the IMU to pass their time
        self.carrier = RoverCarrierBook(self.counters)   # the rover's carrier at its last epoch (TDCP)
        self._prev_epoch_v: tuple[float, np.ndarray] | None = None   # (t_gps, corrected v_e) of the last epoch
        self.base_carrier = BaseCarrierBook()            # the base's recent carrier (base-corrected TDCP)
        self._still = StillnessDetector(config.zupt_window_s, config.zupt_gyro_std_radps,
                                        config.zupt_accel_std_mps2) if config.zupt_enabled else None
        self.imu_screen = ImuScreen(clip_fraction=config.imu_clip_fraction, accel_jump_mps2=config.imu_accel_jump_mps2,
                                    gyro_jump_radps=config.imu_gyro_jump_radps, window=config.imu_median_window,
                                    counters=self.counters) if config.imu_screen_enabled else None
        self.aid = AidSourceBook(config.integrity_window_s)
        self.protection = ProtectionLevel(config.hpl_integrity_risk, config.hpl_missed_detection,
                                          math.sqrt(chi2_ppf(config.gate_probability, 1)))
        self.integrity = IntegrityMonitor(IntegrityLimits(
            window_s=config.integrity_window_s, min_updates=config.integrity_min_updates,
            min_rows=config.integrity_min_rows, max_rejected_fraction=config.integrity_max_rejected_fraction,
            max_nis_mean=config.integrity_max_nis_mean,
            probation_max_rejected_fraction=config.integrity_probation_max_rejected_fraction), counters=self.counters)
        self.ground_mode = True           # NHC, ZUPT and ZARU apply only on the ground (the shell may say otherwise)
        self._nhc_countdown_s = 0.0
        self._nhc_rejections = 0
        self._nhc_suspended_until = -math.inf
        self.course_epochs_fused = 0
        self.course_alignment_t_gps = math.nan     # GPS time of the first course alignment
        self._last_epoch_t = math.nan
        self.last_gnss_update_t = math.nan
        self.reset_counter = 0
        self.epoch_reports: deque = deque(maxlen=16)
        self.on_epoch = None  # optional callback(EpochReport)
        self.smoother = None  # optional companion.nav.smoother.SmootherRecorder (post-flight RTS)
        self.rtk = RtkUpdate(config.rtk_config(), self.counters) if config.rtk_enabled else None
        self.rtk_antennas = None
        if self.rtk is not None and config.rtk_antennas:
            from .rtk_antennas import RtkAntennas
            self.rtk_antennas = RtkAntennas(config.rtk_antennas, config.rtk_rover_antenna, config.rtk_base_antenna)
            self.rtk.rover_antenna = self.rtk_antennas.rover
            self.rtk.set_base_antenna(self.rtk_antennas.base)

    # ------------------------------------------------------------------ set-up
    def initialize(self, t_gps: float, r_e, v_e, C_b_e, P0_sigmas: dict, *,
                   clock_bias_m: float | None = None, clock_drift_mps: float = 0.0,
                   b_a=None, b_g=None, probation: bool = False, imu_time_offset_s: float | None = None) -> None:
        """Start (or restart) navigating from a known state; bumps ``reset_counter``.  With
        ``probation`` (a restart after a divergence) the solution status is ``converging`` until
        the integrity monitor has seen one consistent window of GNSS.

        ``P0_sigmas`` (1-sigma): tilt_rad and heading_rad (or att_rad for both), pos_m, vel_mps,
        ba_mps2, bg_radps, and optionally clk_m, drift_mps, and pos_cov_e_m2 (a 3x3 ECEF position
        covariance, floored at pos_m on every axis).  Without ``clock_bias_m`` the clock is
        taken from the first epoch's pseudoranges.  ``imu_time_offset_s``: the prior mean of the
        IMU time-tag offset (default: the configured one), with the configured sigma."""
        L = StateLayout.standard(self.cfg.bias_systems())
        d = np.zeros(L.n)
        d[L.pos] = P0_sigmas["pos_m"] ** 2
        d[L.vel] = P0_sigmas["vel_mps"] ** 2
        d[L.ba] = P0_sigmas["ba_mps2"] ** 2
        d[L.bg] = P0_sigmas["bg_radps"] ** 2
        d[L.clk] = P0_sigmas.get("clk_m", 1e3) ** 2
        d[L.drift] = P0_sigmas.get("drift_mps", 10.0) ** 2
        d[L.toff] = self.cfg.imu_time_offset_sigma_s ** 2
        for system in self.cfg.bias_systems():
            d[L.index(isb_block_name(system))] = self.cfg.inter_system_bias_sigma_m ** 2
        P0 = np.diag(d)
        cov = P0_sigmas.get("pos_cov_e_m2")
        if cov is not None and np.all(np.isfinite(cov)):
            # the fix's own covariance (e.g. SPP geometry: a poor VDOP means a poor height), never
            # tighter than pos_m along any axis
            w, V = np.linalg.eigh(0.5 * (np.asarray(cov, float) + np.asarray(cov, float).T))
            P0[L.pos, L.pos] = (V * np.maximum(w, P0_sigmas["pos_m"] ** 2)) @ V.T
        # attitude: tilt and heading uncertainties usually differ by an order of magnitude
        # (levelling vs compass); given in local NED, rotated to the ECEF error axes
        tilt = P0_sigmas.get("tilt_rad", P0_sigmas.get("att_rad"))
        heading = P0_sigmas.get("heading_rad", P0_sigmas.get("att_rad"))
        lat, lon, _ = ecef_to_geodetic(r_e)
        Cne = C_n_e(lat, lon)
        P0[L.att, L.att] = Cne @ np.diag([tilt ** 2, tilt ** 2, heading ** 2]) @ Cne.T
        self.kf = ErrorStateKalmanFilter(P0, self.cfg.noise, self.cfg.gate_probability, layout=L)
        self.block_states = {b.name: np.zeros(b.size) for b in L.extra_blocks()}
        self.t_gps = float(t_gps)
        self.r_e = np.array(r_e, float)
        self.v_e = np.array(v_e, float)
        self.C_b_e = np.array(C_b_e, float)
        self.b_a = np.zeros(3) if b_a is None else np.array(b_a, float)
        self.b_g = np.zeros(3) if b_g is None else np.array(b_g, float)
        self.clock_initialized = clock_bias_m is not None
        self.clock_bias_m = float(clock_bias_m or 0.0)
        self.clock_drift_mps = float(clock_drift_mps)
        self.imu_time_offset_s = float(self.cfg.imu_time_offset_s if imu_time_offset_s is None else imu_time_offset_s)
        self._hist.clear()
        self._push_history()
        self._select_imu_path()
        self.carrier.clear()
        self._prev_epoch_v = None
        self._pending.clear()
        if self.rtk is not None:
            self.rtk.reset()
        self._last_epoch_t = math.nan
        self.course_epochs_fused = 0
        self.course_alignment_t_gps = math.nan
        self.aid.clear_windows()
        self.protection.reset()
        self.integrity.restart(t_gps, probation and self.cfg.integrity_enabled)
        self.initialized = True
        self.reset_counter += 1
        if self.smoother is not None:
            self.smoother.start(self)

    @property
    def layout(self) -> StateLayout:
        """The filter's state layout (the standard one before the first initialisation)."""
        return self.kf.layout if self.kf is not None else DEFAULT_LAYOUT

    def add_state_block(self, name: str, size: int, initial_sigma, random_walk_psd: float = 0.0,
                        value=0.0) -> None:
        """Add an identity block to the error state (e.g. a float ambiguity per satellite and
        signal) with its nominal value; the covariance of every other block is kept.  Initialising
        again drops it (the layout is rebuilt from the configuration)."""
        self.kf.add_block(name, size, initial_sigma, random_walk_psd)
        self.block_states[name] = np.broadcast_to(np.asarray(value, float), (size,)).copy()
        if self.smoother is not None:
            self.smoother.layout_changed(self)

    def remove_state_block(self, name: str) -> None:
        """Remove a block added with :meth:`add_state_block` (a satellite set or slipped)."""
        self.kf.remove_block(name)
        del self.block_states[name]
        if self.smoother is not None:
            self.smoother.layout_changed(self)

    def process(self, msg):
        """Dispatch any core message.  Returns an EpochReport for GNSS epochs, else None."""
        if isinstance(msg, ImuSample):
            return self.process_imu(msg)
        if isinstance(msg, GnssEpoch):
            return self.process_base(msg) if msg.source == "base" else self.process_gnss(msg)
        if isinstance(msg, (GpsEphemeris, GlonassEphemeris)):
            self.ephemerides.add(msg)
            return None
        if isinstance(msg, BaseStationPosition):
            if self.base_check.announced(msg):
                self._adopt_base(msg)
            return None
        if isinstance(msg, GnssFix):
            return self.process_fix(msg)
        if isinstance(msg, GnssAttitude):
            return self.process_attitude(msg)
        if isinstance(msg, GnssBaseline):
            return self.process_baseline(msg)
        self.counters["unknown message"] += 1
        return None

    def name_base_antenna(self, name: str) -> None:
        """The base named its antenna (RTCM 1007/1008/1033): its calibration, if the configured
        file has it, from the next epoch on (counted when it changes)."""
        if self.rtk_antennas is not None:
            before = self.rtk_antennas.base
            if self.rtk_antennas.base_named(name):
                self.rtk.set_base_antenna(self.rtk_antennas.base)
                self.counters["rtk base antenna calibration changes"] += 1
                self._base_model_changed(largest_change_m(before, self.rtk_antennas.base, self._rtk_bands()))

    def _rtk_bands(self) -> dict[str, str]:
        """system -> the bands ('1', '2', '5' ...) its RTK rows use: where an antenna model counts."""
        out = {}
        for system in self.cfg.systems:
            bands = "".join(dict.fromkeys(sig[1] for sig in signals_for_system(system, self.cfg.rtk_signals)))
            if bands:
                out[system] = bands
        return out

    def _base_model_changed(self, shift_m: float) -> None:
        """The base's position or antenna model moved by up to ``shift_m``: the differential
        solutions move with it at once, the INS position does not, so its variance is widened by
        that much (else the held fix drops for an epoch and the position creeps over a minute:
        measured 62 -> 98 mm in 40 s, a 100-mm base antenna named mid-drive on the real car)."""
        if shift_m < BASE_MODEL_CHANGE_MIN_M or not self.initialized or self.kf is None:
            return
        pos = self.layout.pos
        self.kf.P[pos, pos] += np.eye(3) * shift_m ** 2
        self.counters["base moved (position or antenna): position variance widened"] += 1

    def _adopt_base(self, msg: BaseStationPosition, elsewhere: bool = False) -> None:
        """A believed base position.  Another station, the rover staying where it is: its epochs
        agree with it and not with the last position (``elsewhere``), or it lies further from the
        last one than the base's code can resolve.  Else the same place re-surveyed (every
        differential solution moves with it: the INS position's variance widened by the move) or
        a receiver beside it, whose other integers the slip tests see."""
        if self.base is not None:
            shift_m = float(np.linalg.norm(msg.r_e - self.base.r_e))
            if elsewhere or shift_m > self.base_check.max_diff_m:
                self._base_station_changed(shift_m)
            else:
                self._base_model_changed(shift_m)
        self.base = msg

    def _base_station_changed(self, shift_m: float) -> None:
        """Another station: its carriers have other integers, so every DD ambiguity and the base's
        carrier history go; its DGPS corrections start from its own first epoch."""
        self.base_station_changes += 1
        self.counters["base station changed: ambiguities and corrections restarted"] += 1
        log.warning("base station changed (%.0f m away): RTK ambiguities and DGPS corrections restarted", shift_m)
        if self.rtk is not None:
            self.rtk.base_changed(self)
        self.dgps = None
        self.base_carrier = BaseCarrierBook()

    def _base_spp_r_e(self, epoch: GnssEpoch):
        """The base's single-point position from its own code (None: too few satellites yet)."""
        near = self.base_check.spp_r_e
        if near is None:
            near = (self.base or self.base_check.candidate).r_e
        cfg = self.cfg
        sol = spp_epoch(epoch, self.ephemerides, klobuchar=cfg.klobuchar, r_init_e=near, systems=cfg.systems,
                        signal=cfg.pseudorange_signal)
        return None if sol is None else sol.r_e

    def process_base(self, epoch: GnssEpoch):
        if self.base is None and self.base_check.candidate is None:
            self.counters["base epoch without station position"] += 1
            return None
        verdict = self.base_check.judge_epoch(self._base_spp_r_e(epoch), self.base)
        if verdict == SKIP:
            return None
        if verdict == ADOPT:
            self._adopt_base(self.base_check.candidate, elsewhere=True)
            self.base_check.candidate = None
        if self.base is None:
            self.counters["base epoch without station position"] += 1
            return None
        if self.dgps is None:
            from ..gnss.dgps import DgpsCorrector
            self.dgps = DgpsCorrector(systems=self.cfg.systems, signal=self.cfg.pseudorange_signal)
        self.dgps.update_base(epoch, self.base, self.ephemerides)
        self.counters["base epochs"] += 1
        if self.rtk is not None:
            self.rtk.add_base(epoch)
        if self.cfg.use_tdcp and self.cfg.tdcp_base_correction != "off" and self.dgps.last_prepared is not None:
            self.base_carrier.remember(self.dgps.last_prepared, self.base.r_e)
        return None

    def _release_pending(self) -> None:
        """The GNSS messages the IMU has now passed (called after an IMU step)."""
        if self.imu_time_of(self._pending[0]) > self.t_gps:
            return
        ready = [e for e in self._pending if self.imu_time_of(e) <= self.t_gps]
        self._pending = [e for e in self._pending if self.imu_time_of(e) > self.t_gps]
        for e in ready:
            if isinstance(e, GnssFix):
                self._process_fix(e)
            elif isinstance(e, GnssAttitude):
                self._process_attitude(e)
            elif isinstance(e, GnssBaseline):
                self._process_baseline(e)
            else:
                self._process_epoch(e)

    def set_installation(self, lever_arm_b_m, moving_baseline_b_m) -> None:
        """A new lever arm (IMU to antenna, body FRD) and moving baseline while running (a ground
        station set them): used from the next measurement on."""
        self.cfg = dataclasses.replace(self.cfg, lever_arm_b_m=tuple(float(x) for x in lever_arm_b_m),
                                       moving_baseline_b_m=moving_baseline_b_m)
        self.lever_arm_b = np.asarray(self.cfg.lever_arm_b_m, float)

    def set_ground_mode(self, on_ground: bool) -> None:
        """The shell tells the engine whether the vehicle is on the ground (e.g. MAVLink
        EXTENDED_SYS_STATE.landed_state); the non-holonomic constraint is off in flight."""
        if on_ground != self.ground_mode:
            self.counters["ground mode on" if on_ground else "ground mode off (flight)"] += 1
        self.ground_mode = on_ground

    def imu_time_of(self, msg) -> float:
        """The IMU tag at which a message's measurement is predicted: its own ``t_gps`` if it is
        tagged on the autopilot's clock, else (receiver time) ``t_gps - imu_time_offset_s``."""
        t = msg.t_gps
        return t if getattr(msg, "autopilot_clock", False) else t - self.imu_time_offset_s

    # ------------------------------------------------------------------ GNSS
    def process_gnss(self, epoch: GnssEpoch):
        if not self.initialized:
            self.counters["gnss before init"] += 1
            return None
        if self.imu_time_of(epoch) > self.t_gps:
            self._wait_for_imu(epoch)
            return None
        return self._process_epoch(epoch)

    def _wait_for_imu(self, msg) -> None:
        """Hold a GNSS message whose time the IMU has not reached yet (time-ordered queue)."""
        if self.imu_time_of(msg) > self.t_gps + self.cfg.history_s:
            self.counters["gnss message too far ahead of the IMU (dropped)"] += 1
            return
        bisect.insort(self._pending, msg, key=self.imu_time_of)
        if len(self._pending) > 20:
            self._pending.pop(0)
            self.counters["gnss message dropped: waiting queue full"] += 1

    def _process_epoch(self, epoch: GnssEpoch) -> EpochReport:
        rep = EpochReport(epoch.t_gps)
        ins_tag = self.ins_at(self.imu_time_of(epoch))
        if ins_tag is None:
            self.counters["gnss epoch older than INS history"] += 1
            rep.rejected["epoch"] = "older than INS history"
            return rep
        self.counters["gnss epochs"] += 1
        ins = self._at_reception(ins_tag)
        r_ant, _, _ = antenna_state(ins, self.lever_arm_b)
        cfg = self.cfg
        prep = prepare_epoch(epoch, self.ephemerides, r_ant,
                             dgps=self.dgps if cfg.use_dgps else None,
                             elevation_mask_rad=math.radians(cfg.elevation_mask_deg),
                             klobuchar=cfg.klobuchar, systems=cfg.systems, signal=cfg.pseudorange_signal)
        if cfg.use_dgps and self.dgps is not None and prep.n < 4 and _stale_corrections(prep.rejected):
            # the corrections stopped (caster or radio outage): standalone models and their honest
            # variance keep the pseudoranges and the carrier (TDCP) instead of coasting on the INS
            prep = prepare_epoch(epoch, self.ephemerides, r_ant, dgps=None,
                                 elevation_mask_rad=math.radians(cfg.elevation_mask_deg), klobuchar=cfg.klobuchar,
                                 systems=cfg.systems, signal=cfg.pseudorange_signal)
            self.counters["epochs standalone: DGPS corrections too old"] += 1
        rep.rejected.update(prep.rejected)
        for reason in prep.rejected.values():
            self.counters[f"satellite rejected: {reason}"] += 1
        if cfg.use_dgps and self.dgps is None:
            self.counters["epoch without DGPS base"] += 1
        batches: list[MeasurementBatch] = []
        rtk_rows, rtk_batches, rtk_reports = None, [], []
        if self.rtk is not None and self.base is not None and not cfg.use_loose:
            # at the tag: the RTK rows take the antenna back by the bias of their own code
            r_ant, v_ant, l_e = antenna_state(ins_tag, self.lever_arm_b)
            rtk_rows = self.rtk.rows(self, ins_tag, epoch, r_ant, l_e, v_ant, self._correlation_inflation(epoch.t_gps))
            if rtk_rows is not None:
                rtk_latency = self._latency_transition(ins_tag)
                if rtk_latency is not None:
                    # in the errors of now, as every other row: an epoch applied 0.2 s late (1.2 s
                    # after a data gap) measured the position of then, not pos now (velocity x latency)
                    rtk_rows.H = rtk_latency.rows_of_now(rtk_rows.H, self.layout)
                rtk_rows.P_prior_pos = self.kf.P[self.layout.pos, self.layout.pos].copy()
                rtk_batches, rtk_reports = self.rtk.gate(self, rtk_rows)
                if not rtk_batches:
                    rtk_rows = None
        sol = None
        if cfg.use_loose or self._course_alignment_pending():
            sol = self._spp(ins, prep)
            if sol is not None and sol.v_e is not None:
                ins = self._course_alignment(ins, sol.v_e, self._spp_velocity_cov_e(sol))
        if cfg.use_loose:
            batches += self._loose_batches(ins, prep, sol)
        else:
            if cfg.use_pseudorange and len(prep.sats) and not rtk_batches:   # DD code replaces them
                pr = pseudorange_batch(ins, prep, self.lever_arm_b, layout=self.layout,
                                       sigma_floor_m=cfg.sigma_pseudorange_floor_m)
                pr.r_var = pr.r_var * self._correlation_inflation(epoch.t_gps)
                if len(pr):
                    self._check_clock(ins, pr)
                    batches.append(pr)
            if cfg.use_doppler and len(prep.sats):
                batches.append(doppler_batch(ins, prep, self.lever_arm_b, cfg.sigma_doppler_mps, layout=self.layout))
            if cfg.use_tdcp and rtk_batches:
                self.carrier.drop_slipped(prep)          # DD phase carries the carrier; keep the bookkeeping
            elif cfg.use_tdcp:
                self.carrier.drop_slipped(prep)
                corr = None
                if cfg.tdcp_base_correction != "off" and len(self.carrier):
                    corr = self.base_carrier.tdcp_corrections(self.carrier.last_time(), epoch.t_gps) or None
                    self.counters["tdcp base-corrected epochs" if corr else "tdcp uncorrected epochs"] += 1
                tdcp = tdcp_batch(ins, prep, self.carrier.records, self.lever_arm_b, cfg.sigma_phase_m,
                                  cfg.sigma_tdcp_floor_mps, cfg.tdcp_max_interval_s, layout=self.layout,
                                  phase_correction_m=corr,
                                  elevation_scaling=cfg.sigma_phase_elevation_scaling,
                                  specific_force_e=self._mean_specific_force_e(ins))
                if len(tdcp) and float(ins.v_e @ ins.v_e) < cfg.zupt_max_speed_mps ** 2:
                    # at rest the dt_imu column is the INS's own velocity-error growth along the
                    # line of sight: the offset is unobservable, and it walked 0 -> -0.30 s in 390 s
                    # at rest on ArduCopter SITL (then "diverged" on its prior)
                    tdcp.H[:, self.layout.toff] = 0.0
                batches.append(tdcp)
        batches = [b for b in batches if len(b)]
        latency = self._latency_transition(ins)      # rows in the errors of now (RTK rows: above)
        if latency is not None:
            for b in batches:
                b.H = latency.rows_of_now(b.H, self.layout)
        if cfg.measurement_form == "single_difference" and batches and len(prep.sats):
            # reference: the highest satellite that every GNSS batch contains
            common = set.intersection(*(set(b.labels) for b in batches))
            order = np.argsort(-prep.elevation_rad)
            ref = next((prep.sats[i] for i in order if prep.sats[i] in common), None)
            batches = [single_difference(b, ref) for b in batches] if ref else []
            batches = [b for b in batches if len(b)]
        reports = [self.kf.gate(b, leave_one_out=b.kind in cfg.leave_one_out_kinds) for b in batches]
        batches, reports = batches + rtk_batches, reports + rtk_reports
        for r in reports:
            self.counters[f"{r.kind} used"] += r.n_accepted
            for reason in r.rejected_reason.values():
                self.counters[f"{r.kind} rejected: {reason}"] += 1
        self._record(reports, epoch.t_gps)
        rep.reports = reports
        rep.sats_by_system = sats_by_system(reports)
        fused = self._held_back(reports)
        self._separation(ins, batches, fused, epoch.t_gps)
        dx = self.kf.update(batches, fused)
        if any(r.n_accepted for r in reports):
            self._feedback(dx)
            if any(r.n_accepted for r in reports if r.kind in ("pseudorange", "position")):
                self._floor_position_covariance(prep)
            rep.applied = True
            rep.dx = dx
            self.last_gnss_update_t = epoch.t_gps
        if self.rtk is not None:
            dx_total = dx
            if rtk_rows is not None:
                hold_before = self.counters["rtk fixed epochs"]
                st = self.rtk.resolve(self, rtk_rows, dx)
                if self.counters["rtk fixed epochs"] != hold_before:
                    dx_total = dx + self.rtk.last_hold_dx
                rep.fix_state, rep.fix_ratio, rep.n_fixed = st.fix_state, st.ratio, st.n_fixed
            self.rtk.finish(self, rtk_rows, dx_total if latency is None else latency.correction_then(dx_total, self.layout))
        self._remember_phase(ins, dx if latency is None else latency.correction_then(dx, self.layout), prep)
        self._last_epoch_t = epoch.t_gps
        self._check_integrity(epoch.t_gps)
        self.epoch_reports.append(rep)
        if self.on_epoch is not None:
            self.on_epoch(rep)
        return rep

    #: a receiver clock bias below this (s) moves a 30-m/s antenna by less than 0.3 mm: not worth
    #: an interpolation
    RECEPTION_SHIFT_MIN_S = 1e-5

    def _at_reception(self, ins_tag: InsPoint) -> InsPoint:
        """The INS at the epoch's reception in GPS time: the receiver's tag minus its clock bias
        (the satellite positions are at transmit times from the pseudoranges, which carry that
        bias, so the antenna must be where it was then).  A u-blox M8P tags x.987-x.992 s (bias
        -8 to -13 ms): 0.13-0.26 m along the track at 10-20 m/s if it were left at the tag."""
        if not self.clock_initialized:
            return ins_tag
        dt = self.clock_bias_m / SPEED_OF_LIGHT_MPS
        if abs(dt) < self.RECEPTION_SHIFT_MIN_S:
            return ins_tag
        at = self.ins_at(ins_tag.t_gps - dt)
        return ins_tag if at is None else at

    def _separation(self, ins: InsPoint, batches, reports, t_gps: float) -> None:
        """Solution separation (companion.nav.protection) of the pseudorange rows about to be fused,
        against the prior covariance they were gated with."""
        for b, r in zip(batches, reports):
            if b.kind != "pseudorange" or r.n_accepted < 2:
                continue
            lat, lon, _ = ecef_to_geodetic(ins.r_e)
            C_h = self.layout.zeros(2)
            C_h[:, self.layout.pos] = C_n_e(lat, lon).T[0:2]
            acc = r.accepted
            self.protection.epoch(b.H[acc], b.z[acc], b.r_var[acc], self.kf.P, C_h, t_gps,
                                  [lab for lab, a in zip(b.labels, acc) if a])
            return

    def _correlation_inflation(self, t_gps: float) -> float:
        """Variance factor for time-correlated pseudorange errors: 1 + 2 tau / T (T = epoch interval)."""
        tau = self.cfg.pseudorange_correlation_time_s
        if tau <= 0:
            return 1.0
        T = t_gps - self._last_epoch_t
        T = T if 0.0 < T < 30.0 else 1.0
        return 1.0 + 2.0 * tau / T

    def _floor_position_covariance(self, prep) -> None:
        """Keep the position covariance above what the slow pseudorange errors allow
        (companion.nav.slow_errors)."""
        if not self.cfg.slow_error_floor or len(prep.sigma_pseudorange_slow_m) != len(prep.sats):
            return
        if self.heading_and_sigma()[1] > FLOOR_MAX_HEADING_SIGMA_RAD:
            # heading unknown: the position rows see it only through the linearised lever arm,
            # which is meaningless for errors of tens of degrees; a position kept uncertain would
            # let those rows keep "measuring" the heading (a car started 179 deg off became
            # confidently wrong before it drove)
            return
        if np.any(np.isfinite(prep.dgps_age_s)):
            # DGPS: the slow part left (decorrelation over the baseline, ~0.2 m) is small beside the
            # multipath the weighting already inflates; as a floor it cost accuracy for no
            # consistency on the simulated flights (paper scenario TDCP + DGPS: 0.89 -> 1.02 m mean
            # 3-D error, NEES 7.6 -> 7.7)
            return
        r_ant = self.r_e + self.C_b_e @ self.lever_arm_b
        ok = np.isfinite(prep.pseudorange_m)
        slow = prep.sigma_pseudorange_slow_m[ok]
        white_var = prep.sigma_pseudorange_m[ok] ** 2 - slow ** 2
        slow = np.sqrt(np.maximum(slow ** 2, self.cfg.sigma_pseudorange_floor_m ** 2 - white_var))
        floor = slow_error_position_floor(r_ant, prep.r_sat_e[ok], slow)
        if floor is not None and raise_to_floor(self.kf.P, self.layout.pos, floor):
            self.counters["position covariance raised to the slow-error floor"] += 1

    def _update_with(self, batch: MeasurementBatch, what: str, used_counter: str) -> UpdateReport:
        """Gate one measurement batch, update, count accepted rows and rejections by reason."""
        rep = self.kf.gate(batch)
        self.counters[used_counter] += rep.n_accepted
        for reason in rep.rejected_reason.values():
            self.counters[f"{what} rejected: {reason}"] += 1
        self._record((rep,), self.t_gps)
        dx = self.kf.update([batch], [rep])
        if rep.n_accepted:
            self._feedback(dx)
        return rep

    def _held_back(self, reports):
        """In an integrity hold the position rows are tested and recorded, not fused (see
        companion.nav.integrity: the GNSS position disagrees with an INS the velocity confirms)."""
        if self.integrity.state != IntegrityState.HOLD:
            return reports
        out = []
        for r in reports:
            if r.kind in POSITION_SOURCES and r.n_accepted:
                self.counters[f"{r.kind} held back (integrity hold)"] += r.n_accepted
                r = dataclasses.replace(r, accepted=np.zeros_like(r.accepted))
            out.append(r)
        return out

    def _record(self, reports, t_gps: float) -> None:
        """Per aid source status (companion.nav.aid_status) of gated batches."""
        g = self.kf.gate_chi2_1dof
        for r in reports:
            self.aid.record(r, t_gps, g)

    IMU_TIME_OFFSET_MAX_SIGMAS = 3.0

    def _check_integrity(self, t_gps: float) -> None:
        """After a GNSS update: has the filter diverged, or has a probation window passed?  An IMU
        time-tag offset estimate beyond IMU_TIME_OFFSET_MAX_SIGMAS prior sigmas of the configured
        mean is a divergence too: in a steady turn a heading error and a time offset look alike
        (dv = dpsi x v against a dt = (w x v) dt), so a contradicting gyro can hide in it."""
        if not self.cfg.integrity_enabled:
            return
        sig = self.cfg.imu_time_offset_sigma_s
        off = self.imu_time_offset_s - self.cfg.imu_time_offset_s
        if sig > 0 and not abs(off) <= self.IMU_TIME_OFFSET_MAX_SIGMAS * sig:
            changed = self.integrity.implausible_state(
                t_gps, f"IMU time offset {self.imu_time_offset_s * 1e3:.0f} ms: {abs(off) / sig:.1f} sigma from its prior")
        else:
            changed = self.integrity.evaluate(self.aid, t_gps)
        if not changed:
            return
        state = self.integrity.state
        if state == IntegrityState.DIVERGED:
            log.warning("navigation diverged (%s)", self.integrity.reason)
        elif state == IntegrityState.HOLD:
            log.warning("GNSS position not fused (%s)", self.integrity.reason)
        elif state == IntegrityState.SUSPECT:        # counted; the shell stops injecting
            log.debug("navigation suspect (%s)", self.integrity.reason)

    def _feedback(self, dx: np.ndarray) -> None:
        """Closed loop: fold the estimated errors into the nominal state (error state back to zero)."""
        L = self.layout
        R = rotation_from_rotvec(dx[L.att])
        self.C_b_e = R @ self.C_b_e
        self.r_e = self.r_e + dx[L.pos]
        self.v_e = self.v_e + dx[L.vel]
        self.b_a = self.b_a + dx[L.ba]
        self.b_g = self.b_g + dx[L.bg]
        self.clock_bias_m += dx[L.clk]
        self.clock_drift_mps += dx[L.drift]
        self.imu_time_offset_s += dx[L.toff]
        bs = self.block_states
        if bs:                     # by the layout's blocks: no look-up by name per block (RTK: 60 of them)
            for blk in L.extra_blocks():
                v = bs.get(blk.name)
                if v is not None:
                    bs[blk.name] = v + dx[blk.start:blk.start + blk.size]
        # the newest history sample is "now": keep it consistent with the corrected state; the
        # older ones get the same correction, for an epoch that arrives right behind this one (a
        # burst after a data gap: 1.2 s late, the next 0.2 s) is predicted from them
        self._hist.correct(dx[L.pos], dx[L.vel], R)
        self._hist.set_last()

    LATENCY_MIN_S = 1e-3

    def _latency_transition(self, ins: InsPoint) -> LatencyTransition | None:
        """The error dynamics from the INS point a measurement was predicted at to now (the IMU
        sample the correction is applied at), with the mean specific force in between from the
        velocity change (the ECEF mechanisation, as :meth:`_mean_specific_force_e`); None when
        the measurement is (nearly) current."""
        d = self.t_gps - ins.t_gps
        if not d > self.LATENCY_MIN_S:
            return None
        f_e = (self.v_e - ins.v_e) / d - gravity_ecef(self.r_e) + _coriolis_e(self.v_e)
        return LatencyTransition(d, f_e, self.C_b_e)

    def _mean_specific_force_e(self, ins: InsPoint) -> np.ndarray | None:
        """Mean specific force (ECEF, m/s^2) since the last epoch, from the velocity change and the
        ECEF mechanisation (v' = f + g - 2 Omega x v); None without a recent previous epoch."""
        prev = self._prev_epoch_v
        if prev is None:
            return None
        T = ins.t_gps - prev[0]
        if not 0.0 < T <= self.cfg.tdcp_max_interval_s:
            return None
        return (ins.v_e - prev[1]) / T - gravity_ecef(ins.r_e) + _coriolis_e(ins.v_e)

    def _remember_phase(self, ins: InsPoint, dx: np.ndarray, prep) -> None:
        """The carrier records for the next epoch's TDCP, with ranges from the *corrected* INS
        state (companion.gnss.phase).  The records are tagged with the epoch's (receiver) time; a
        corrected time-tag offset moves the antenna along its path (the epoch is then predicted
        from dt_imu earlier on the IMU tags)."""
        if not self.cfg.use_tdcp:
            return
        L = self.layout
        C = rotation_from_rotvec(dx[L.att]) @ ins.C_b_e
        fixed = InsPoint(ins.t_gps, ins.r_e + dx[L.pos], ins.v_e + dx[L.vel], C, ins.omega_ib_b,
                         ins.clock_bias_m + dx[L.clk], ins.clock_drift_mps + dx[L.drift])
        r_ant, v_ant, _ = antenna_state(fixed, self.lever_arm_b)
        if dx[L.toff] != 0.0:
            r_ant = r_ant - v_ant * dx[L.toff]
        self._prev_epoch_v = (ins.t_gps, fixed.v_e.copy())
        self.carrier.remember(prep, r_ant, v_ant)

    # ------------------------------------------------------------------ output
    def solution(self) -> NavSolution:
        if not self.initialized:
            nan3 = np.full(3, np.nan)
            return NavSolution(math.nan, nan3, nan3, np.full((3, 3), np.nan), nan3, nan3, nan3, "init")
        L = self.layout
        lat, lon, _ = ecef_to_geodetic(self.r_e)
        Cen = C_n_e(lat, lon).T
        P = self.kf.P
        sig_r = np.sqrt(np.maximum(np.diag(Cen @ P[L.pos, L.pos] @ Cen.T), 0.0))
        sig_v = np.sqrt(np.maximum(np.diag(Cen @ P[L.vel, L.vel] @ Cen.T), 0.0))
        sig_a = np.sqrt(np.maximum(np.diag(P[L.att, L.att]), 0.0))
        healthy = bool(np.all(np.isfinite(self.r_e)) and np.all(np.isfinite(P)))
        Ch = Cen[0:2]
        pl = self.protection.levels(Ch @ P[L.pos, L.pos] @ Ch.T) if healthy else None
        integrity = self.integrity.state
        if not healthy or math.hypot(sig_r[0], sig_r[1]) > self.cfg.untrusted_sigma_h_m:
            status = "untrusted"
        elif integrity == IntegrityState.DIVERGED:
            status = "diverged"
        elif integrity == IntegrityState.PROBATION:
            status = "converging"
        elif integrity == IntegrityState.SUSPECT:
            status = "suspect"
        elif integrity == IntegrityState.HOLD:
            # the GNSS position is not fused; which side is wrong is unknown, so nothing is injected
            status = "suspect"
        elif not (self.t_gps - self.last_gnss_update_t <= self.cfg.coasting_after_s):
            status = "coasting"
        else:
            status = "nav"
        fix_state, fix_ratio = FIX_NONE, math.nan
        rtk = self.rtk.status if self.rtk is not None else None
        if rtk is not None and self.t_gps - rtk.t_gps <= self.cfg.coasting_after_s:
            fix_state, fix_ratio = rtk.fix_state, rtk.ratio
            if fix_state == FIX_FIXED and float(sig_r @ sig_r) > self.rtk.cfg.max_fixed_sigma_3d_m ** 2:
                fix_state = FIX_FLOAT       # coasting since the fix (a late epoch): no longer RTK-grade
        sol = NavSolution(self.t_gps, self.r_e.copy(), self.v_e.copy(), self.C_b_e.copy(), sig_r, sig_v, sig_a,
                           status, self.last_gnss_update_t, self.reset_counter,
                           {"clock_bias_m": self.clock_bias_m, "clock_drift_mps": self.clock_drift_mps,
                            "b_a": self.b_a.copy(), "b_g": self.b_g.copy(), "integrity": integrity,
                            "integrity_reason": self.integrity.reason,
                            "hpl_m": pl.hpl_m if pl else math.nan, "hpl_cov_m": pl.hpl_cov_m if pl else math.nan,
                            "hpl_ss_m": pl.hpl_ss_m if pl else math.nan,
                            "imu_time_offset_s": self.imu_time_offset_s,
                            "imu_time_offset_sigma_s": math.sqrt(max(float(P[L.toff, L.toff]), 0.0))},
                           fix_state=fix_state, fix_ratio=fix_ratio)
        if self.smoother is not None:
            self.smoother.note_solution(sol)
        return sol


def sats_by_system(reports) -> dict[str, int]:
    """Satellites with at least one accepted row in ``reports``, counted per system letter (a row
    label starts with its satellite, 'G05', or with a double difference's pair, 'G05-G10 L1C phase')."""
    sats = {sat for r in reports for lab, a in zip(r.labels, r.accepted) if a
            for sat in lab.split(" ", 1)[0].split("-") if sat[:1].isalpha()}
    out: dict[str, int] = {}
    for sat in sorted(sats, key=lambda x: ("GECJ".find(x[0]) % 9, x)):     # GPS, Galileo, BeiDou, QZSS, others
        out[sat[0]] = out.get(sat[0], 0) + 1
    return out


def _coriolis_e(v_e: np.ndarray) -> np.ndarray:
    """2 W_ie x v (ECEF, m/s^2), the earth rate along z: np.cross's numbers without its ~15 us."""
    w = OMEGA_IE_RADPS
    return 2.0 * np.array([-(w * v_e[1]), w * v_e[0], 0.0])


def _stale_corrections(rejected: dict[str, str]) -> bool:
    """Most satellites of the epoch were refused for want of a recent DGPS correction."""
    stale = sum(1 for r in rejected.values() if r in ("DGPS correction too old", "no DGPS correction"))
    return stale >= 4
