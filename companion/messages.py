"""Typed messages between the asyncio shell and the pure navigation core.

Every message carries its own timestamp.  Inside the core there is one time base:
**GPS time as continuous seconds since the GPS epoch (1980-01-06 00:00:00 GPS)**, named
``t_gps``.  float64 resolves about 0.3 microseconds at today's values, far below anything
that matters for navigation (a satellite moves 1 mm in 0.3 us).

Units are SI; frames are in the field names (``_e`` ECEF, ``_n`` local NED, ``_b`` body FRD).
Arrays are numpy float64.  Messages are frozen: the core never mutates its inputs.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

SECONDS_PER_WEEK = 604800.0
SPEED_OF_LIGHT_MPS = 299792458.0
GPS_L1_HZ = 1575.42e6
GPS_L2_HZ = 1227.60e6
GPS_L1_WAVELENGTH_M = SPEED_OF_LIGHT_MPS / GPS_L1_HZ  # 0.19029367 m
GPS_L2_WAVELENGTH_M = SPEED_OF_LIGHT_MPS / GPS_L2_HZ


def gps_time(week: int, tow_s: float) -> float:
    """Continuous GPS seconds from a GPS week number (not rolled over) and time of week."""
    return week * SECONDS_PER_WEEK + tow_s


def gps_week_tow(t_gps: float) -> tuple[int, float]:
    """Split continuous GPS seconds into (week, time of week in seconds)."""
    week = int(t_gps // SECONDS_PER_WEEK)
    return week, t_gps - week * SECONDS_PER_WEEK


@dataclass(frozen=True, slots=True, eq=False)
class ImuSample:
    """One IMU interval ending at ``t_gps``: angle and velocity increments in the body frame.

    Increments (not rates) are what a strapdown integrator wants; a source that reports rates
    (MAVLink HIGHRES_IMU / RAW_IMU) multiplies them by ``dt_s``.
    """

    t_gps: float              # end of the integration interval, GPS seconds
    dt_s: float               # length of the interval, s
    dtheta_b: np.ndarray      # angle increment about body x,y,z (FRD), rad, shape (3,)
    dv_b: np.ndarray          # specific-force (velocity) increment along body x,y,z, m/s, shape (3,)
    imu_id: int = 0


@dataclass(frozen=True, slots=True)
class SatObservation:
    """Raw observables of one satellite signal at one epoch.  Missing values are NaN."""

    sat: str                          # RINEX-style id: 'G05', 'E11', 'C30', 'R07'
    pseudorange_m: float = float("nan")
    carrier_cycles: float = float("nan")   # accumulated carrier phase, cycles (RINEX sign: grows as range grows)
    doppler_hz: float = float("nan")       # RINEX sign: positive when the satellite approaches
    cn0_dbhz: float = float("nan")
    lock_time_s: float = float("nan")      # continuous carrier lock time reported by the receiver
    half_cycle_ambiguous: bool = False     # receiver flags an unresolved half-cycle ambiguity
    loss_of_lock: bool = False             # receiver flags a cycle slip / loss of lock since last epoch
    signal: str = "L1C"                    # RINEX 3 observation code of the signal (band + attribute)
    wavelength_m: float = GPS_L1_WAVELENGTH_M


@dataclass(frozen=True, slots=True, eq=False)
class GnssEpoch:
    """All observations of one receiver at one measurement epoch.

    ``t_gps`` is the receiver's own time tag (it contains the receiver clock error; the core
    estimates that error as a state).
    """

    t_gps: float
    observations: tuple[SatObservation, ...]
    source: str = "rover"             # 'rover' or 'base'


#: system time minus GPS time is constant per system: t_gps = t_system + SYSTEM_TO_GPS_S[letter];
#: BeiDou time (BDT) started at 2006-01-01 00:00:00 UTC, 14 s behind GPS time; Galileo system
#: time (GST) and QZSS time are steered to GPS time (their few-ns offsets are below code noise)
SYSTEM_TO_GPS_S = {"G": 0.0, "E": 0.0, "J": 0.0, "C": 14.0}
#: the system's week 0 in GPS weeks (GST week 0 = GPS week 1024, BDT week 0 = GPS week 1356)
SYSTEM_WEEK_TO_GPS_WEEK = {"G": 0, "E": 1024, "J": 0, "C": 1356}


@dataclass(frozen=True, slots=True)
class GpsEphemeris:
    """Keplerian broadcast ephemeris and clock of one GPS, Galileo, BeiDou or QZSS satellite
    (IS-GPS-200 20.3.3, Galileo OS SIS ICD 5.1, BeiDou ICD B1I 5.2.4, IS-QZSS-PNT).  Angles in
    radians (not semicircles).  ``BroadcastEphemeris`` is the same class.

    Times of week are in the satellite's **own system time** (BDT for BeiDou): the orbit's
    longitude of the node uses them.  ``week`` is counted in **GPS weeks** (a decoder adds
    ``SYSTEM_WEEK_TO_GPS_WEEK``), so ``t_oe_gps`` / ``t_oc_gps`` are continuous GPS seconds.

    Group delays: ``tgd_s`` is what a single-frequency user of the system's primary signal
    subtracts (GPS/QZSS TGD for L1 C/A; Galileo BGD(E1,E5b) of I/NAV or BGD(E1,E5a) of F/NAV for
    E1; BeiDou TGD1 for B1I, its clock referring to B3I); ``tgd2_s`` is BeiDou TGD2 (B2I) or the
    Galileo BGD(E1,E5b) when ``tgd_s`` came from F/NAV, else 0.  ``iode``: GPS/QZSS IODE, Galileo
    IODnav, BeiDou AODE (the same value from every source, so base and rover match)."""

    sat: str              # 'G05', 'E11', 'C30', 'J02'
    week: int             # week of toe in GPS weeks (no roll-over)
    toe_s: float          # time of ephemeris, s of the system's week
    toc_s: float          # time of clock, s of the system's week
    sqrt_a: float         # sqrt(m)
    e: float
    i0_rad: float
    omega0_rad: float     # longitude of ascending node at weekly epoch
    omega_rad: float      # argument of perigee
    m0_rad: float
    delta_n_radps: float
    idot_radps: float
    omega_dot_radps: float
    cuc_rad: float
    cus_rad: float
    crc_m: float
    crs_m: float
    cic_rad: float
    cis_rad: float
    af0_s: float
    af1_sps: float
    af2_sps2: float
    tgd_s: float = 0.0
    iode: int = 0
    iodc: int = 0
    health: int = 0
    ura_m: float = 2.0
    fit_interval_h: float = 4.0

    tgd2_s: float = 0.0

    @property
    def system(self) -> str:
        return self.sat[0]

    @property
    def t_oe_gps(self) -> float:
        return self.week * SECONDS_PER_WEEK + self.toe_s + SYSTEM_TO_GPS_S.get(self.sat[0], 0.0)

    @property
    def t_oc_gps(self) -> float:
        return self.week * SECONDS_PER_WEEK + self.toc_s + SYSTEM_TO_GPS_S.get(self.sat[0], 0.0)


BroadcastEphemeris = GpsEphemeris


@dataclass(frozen=True, slots=True, eq=False)
class BaseStationPosition:
    """Antenna reference point of a correction base station (RTCM 1005/1006)."""

    station_id: int
    r_e: np.ndarray                   # ECEF, m
    antenna_height_m: float = 0.0     # RTCM 1006 height above the marker (already in r_e for 1005)


@dataclass(frozen=True, slots=True, eq=False)
class GnssFix:
    """A receiver's own position/velocity solution (GPS_RAW_INT, NAV-PVT): loose coupling input."""

    t_gps: float
    r_e: np.ndarray                   # antenna position, ECEF, m
    v_e: np.ndarray | None            # antenna velocity, ECEF, m/s (None if not reported)
    sigma_h_m: float
    sigma_v_m: float
    sigma_vel_mps: float = 0.5
    num_sats: int = 0
    fix_type: int = 3                 # 0-1 no fix, 2 2-D, 3 3-D, 4 DGPS, 5 RTK float, 6 RTK fixed
    # False when the source carries no vertical velocity (GPS_RAW_INT: speed and course only); the
    # vertical component of v_e is then a placeholder and only the horizontal velocity is fused
    vertical_velocity_valid: bool = True
    # True when t_gps is the autopilot's boot time mapped through SYSTEM_TIME (GPS_RAW_INT), like the
    # IMU's: it then shares the IMU's time-tag offset (companion.nav.filter, dt_imu)
    autopilot_clock: bool = False


@dataclass(frozen=True, slots=True)
class GnssAttitude:
    """Body attitude from a multi-antenna GNSS receiver (seed 003): ZYX Euler angles of the body
    frame relative to local NED, antenna-baseline misalignment already removed.  A dual-antenna
    receiver (UBX NAV-RELPOSNED, GPS_RAW_INT yaw) gives heading (and pitch along the baseline);
    three antennas give all three.  Angles not measured are NaN."""

    t_gps: float
    heading_rad: float = float("nan")
    pitch_rad: float = float("nan")
    roll_rad: float = float("nan")
    sigma_heading_rad: float = math.radians(0.2)
    sigma_pitch_rad: float = math.radians(0.2)
    sigma_roll_rad: float = math.radians(0.4)
    autopilot_clock: bool = False     # t_gps from the autopilot's boot time (ATTITUDE, GPS_RAW_INT yaw)
    # the heading follows this reading rather than averaging it with earlier ones: the source's error
    # is the same from one reading to the next and already in the heading (the autopilot's compass
    # at rest); see NavEngine.release_heading
    follow_heading: bool = False


@dataclass(frozen=True, slots=True, eq=False)
class GnssBaseline:
    """Moving-baseline vector of a dual-antenna receiver pair (UBX NAV-RELPOSNED of the rover
    receiver): from the moving-base antenna to the rover antenna, local NED at the vehicle, m, with
    per-axis 1-sigma.  Only carrier-fixed vectors are useful for attitude (a float solution has
    decimetre errors); ``carrier_fixed`` says which this is.  The body-frame vector between the two
    antennas is installation data (``gnss.moving_baseline_b_m``), not part of the message."""

    t_gps: float
    rel_pos_ned_m: np.ndarray
    sigma_ned_m: np.ndarray
    carrier_fixed: bool = True
    length_sigma_m: float = float("nan")


@dataclass(frozen=True, slots=True, eq=False)
class NavSolution:
    """The fused estimate at ``t_gps`` (IMU position unless stated)."""

    t_gps: float
    r_e: np.ndarray                   # IMU position, ECEF, m
    v_e: np.ndarray                   # IMU velocity, ECEF, m/s
    C_b_e: np.ndarray                 # body-to-ECEF rotation
    sigma_r_n_m: np.ndarray           # 1-sigma position error, north/east/down, m
    sigma_v_n_mps: np.ndarray         # 1-sigma velocity error, north/east/down, m/s
    sigma_att_rad: np.ndarray         # 1-sigma attitude error about ECEF axes, rad
    # 'init', 'nav', 'coasting' (no GNSS update recently), 'untrusted', and from the integrity
    # monitor (companion.nav.integrity) 'suspect' (one inconsistent epoch), 'diverged' (an
    # inconsistent window), 'converging' (after a re-initialisation, until a consistent window)
    status: str
    last_gnss_update_t_gps: float = float("nan")
    reset_counter: int = 0            # bumped at every discontinuity (re-initialisation)
    extras: dict = field(default_factory=dict)
    # carrier-phase RTK (companion.nav.rtk_update): 'none', 'float' or 'fixed' (integer
    # ambiguities validated at the last epoch), and the LAMBDA ratio of that fix
    fix_state: str = "none"
    fix_ratio: float = float("nan")
    n_fixed: int = 0                  # DD ambiguities fixed in that epoch (0 unless 'fixed')
