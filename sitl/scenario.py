"""Simulation scenarios: every truth motion and every error process, with its model and numbers.

``build_scenario(name)`` returns a frozen :class:`Scenario`; ``sitl.simulate.simulate(scenario, seed)``
turns it into truth, IMU samples and rover/base GNSS epochs.  Same (scenario, seed) -> identical
output; each error process draws from its own ``np.random.default_rng([seed, stream_id])``.

Modelling choices (both scenarios)
----------------------------------
* Time: ``t_gps`` continuous GPS seconds.  IMU samples on a uniform grid in true GPS time starting
  at ``t0_gps`` = integer second + ``imu_phase_s`` (6.3 ms).  Receivers output epochs at integer
  seconds of *receiver* time (1 Hz), i.e. true time ``t = T_rx - b_rx/c``; so every GNSS epoch falls
  3.7 ms after an IMU sample (100 Hz and 200 Hz) and the INS must be interpolated.
  ``GnssEpoch.t_gps`` is the receiver time tag (contains the receiver clock bias).
* Truth: trajectory velocity ``v_t`` and attitude ``C_b_t`` in an earth-fixed tangent frame (NED at
  the start point); ``v_e = C_t_e v_t``, ``C_b_e = C_t_e C_b_t``, position by the mechanization's
  trapezoid rule ``r1 = r0 + (v0+v1) tau/2``.  Error-free IMU increments come from
  ``companion.nav.strapdown.invert_step`` (exact inverse of the mechanization), so they reproduce
  the truth to rounding.  Between IMU samples the truth is cubic-Hermite in position with the
  trajectory's own velocity/attitude.
* IMU errors are added to the *rates* over each interval: dtheta = dtheta_true + (b_g + n_g) dt,
  dv = dv_true + (b_a + n_a) dt, with b = turn-on bias + 1st-order Gauss-Markov bias instability,
  n = white noise (uniform for the paper, Gaussian with a noise density for MEMS:
  sigma per sample = density / sqrt(dt)).
* Pseudorange  P = rho + c(dt_r - dt_s,true) + I + T + E_orb + MP + eps
  Carrier    Phi = (rho + c(dt_r - dt_s,true) - I + T + E_orb + mp + e)/lambda + N  (cycles)
  Doppler      D = -(d/dt of the noise-free phase term, m/s)/lambda + n_D          (Hz, RINEX sign)
  rho: light-time geometric range with earth rotation (sitl.sky.light_time_range) to the antenna
  r_ant = r_e + C_b_e l_b.  c dt_s,true = c(dt_s,broadcast - TGD) - E_clk - E_SA, so the satellite
  clock error and SA enter P and Phi with + sign (common to base and rover).
* The paper's Table 1 "+-X" are read as bounds of a uniform distribution, as in the paper's own
  "rand(+-a)" notation for the IMU (eqs 34-35): each process gets the uniform law's standard
  deviation X/sqrt(3), but is Gaussian and smooth in time.
* Slow range errors (iono, tropo, orbit, satellite clock, SA) are per-satellite critically damped
  2nd-order Gauss-Markov processes (x'' + 2x'/tau + x/tau^2 = w; std sigma, rate std sigma/tau;
  C1-smooth), generated on a 1-s grid and evaluated by cubic spline (value and rate).  Each has a
  common part (identical at base and rover) and a differential part that only the rover sees, so
  base-corrected rover pseudoranges keep exactly the differential part (the DGPS column).
* Site errors per receiver: code multipath 1st-order GM (tau 5-10 s), code noise white, carrier
  multipath 1st-order GM, carrier noise white, Doppler noise white; optionally scaled 1/sin(el)
  (capped at el=5 deg).  C/N0 = 32 + 18 sin(el) dB-Hz.
* Receiver clock (bias b [m], drift d [m/s]): TCXO with white FM (S_f = c^2 h0/2) and random-walk
  FM (S_g = 2 pi^2 c^2 h_-2), h0 = 2e-19 s, h_-2 = 2e-20 1/s, steered by the receiver as a
  critically damped loop of time constant tau_steer: b' = d + w_f, d' = -b/tau^2 - 2 d/tau + w_g;
  started from its stationary distribution.  Bias stays sub-microsecond.
* Carrier ambiguity: a random integer in [-2^20, 2^20] per satellite and lock; a new one after any
  loss of lock (satellite rise, outage).  ``cycle_slips`` ((t_gps, sat, cycles), rover only) add
  cycles from the first epoch at or after t_gps, set ``loss_of_lock`` and reset ``lock_time_s``.
* Elevation mask applied per receiver and epoch (paper 5 deg, uav 10 deg).

"paper" (seed 000 sec 4.1)
--------------------------
* Place/time: 6 deg S, 22 deg E, h 1000 m; GPS week 1316, t0 = tow 252000 s + 6.3 ms (all six
  Table 3 ephemerides, toe 251980/252000, are within their 4-h fit interval); 500 s.  Sky: SV1, 2,
  3, 5, 6 between 11 and 29 deg, SV4 below the horizon (masked).  af0/af1 (not in the paper) fixed
  small values (sitl.sky.PAPER_AF0_S/AF1_SPS), IDOT 0, TGD 0.
* Motion: at rest, attitude zero (body = NED); ZYX Euler angles grow at (roll, pitch, yaw) rates
  (0, 0.01, 0.01) rad/s relative to the tangent NED frame; constant kinematic acceleration w.r.t.
  the earth in body axes a_b = (0.25, 0.15, 1e-5) m/s^2.  a_z: the OCR "105" is read 1e-5 (the
  text writes decimals with a comma, "0,25", "0,15", "0,01", so "105" without one is a mangled
  superscript "10^-5", as "10^-6" became "1075" in eq 34; and 1.05 m/s^2 would drive the vehicle
  9 km below its start within 160 s, whereas 1e-5 gives a monotonic climb).  The result: a climbing
  looping flight: up to 52 m/s, 14.9 km altitude gain after 500 s.
* IMU 100 Hz HG1700 class per eqs 34-35: gyro bias 2.424068e-6 rad/s (0.5 deg/h) per axis with a
  seeded random sign + uniform white noise +-2.424068e-6 rad/s per sample; accel bias 0.0249 m/s^2
  per axis with random sign + uniform noise +-0.00637 m/s^2.  No bias instability.
* Table 1 (1-sigma = X/sqrt(3)): GPS column = total rover error, DGPS column = differential part.
  iono 5 / 0.5 m (tau 600 s), tropo 1.5 / 0.2 m (1200 s), sat clock 3 / 0 m (1200 s), orbit
  4.2 / 0.3 m (LOS scalar, 1800 s), SA 100 / 0 m (satellite clock dither, tau 180 s: rate std
  0.32 m/s), rover code multipath 1 m (GM tau 5 s), rover code noise 1 m (white); no elevation
  mapping (the table values are slant errors).  Rover carrier noise 2.5 mm, carrier multipath 1 cm
  (tau 5 s), Doppler 0.05 m/s.  Receiver clock steered with tau 10 s (bias std ~3 m = the table's
  "receiver clock +-5 m" read as uniform).  Base: 3 km away at bearing 135 deg, h 1000 m, geodetic
  quality: code noise 0.1 m, code MP 0.15 m, carrier 1 mm / 3 mm, own clock (tau 30 s).

"paper-nosa": identical to "paper" but SA = 0 (SA was switched off in May 2000; with SA on,
its 0.3 m/s rate std also corrupts undifferenced TDCP range rates).

"uav" (survey flight near GEONET 0759/3040, real broadcast ephemeris)
--------------------------------------------------------------------
* Base at station 3040's RINEX header position; takeoff 100 m S, 50 m E of station 0759's header
  position, 2 m below it (baseline ~3.3 km).  2005-04-02 00:20:00 GPST (week 1316, tow 519600),
  300 s; all healthy satellites of 07590920.05n whose ephemeris is valid over the whole run, mask
  10 deg.  Lever arm IMU->antenna (0.10, 0.0, -0.15) m body.
* Motion: sitl.trajectory.survey_flight (rest, climb 50 m, six 216-m legs at 9 m/s with
  alternating coordinated 180-deg turns, hover 30 s, descend, rest); rover outage (no rover
  epochs) t0+130 .. t0+160 s, covering turn 3 and the start of leg 4.
* IMU 200 Hz, ICM-42688 class: gyro turn-on bias N(0, 0.25 deg/s) per axis, bias instability GM
  10 deg/h (tau 200 s), ARW 0.2 deg/sqrt(h); accel turn-on bias N(0, 0.1 m/s^2), bias instability
  GM 5e-3 m/s^2 (tau 300 s), noise density 7e-4 m/s^2/sqrt(Hz) (70 ug/sqrt(Hz)).
* SA off.  Iono: truth = 1.15 x Klobuchar (broadcast alpha/beta of the nav file) at the receiver's
  own position + zenith fluctuation 0.5 m (tau 900 s) x thin-shell obliquity; rover-only
  differential 1 cm zenith (tau 600 s).  Tropo: truth = 1.05 x Saastamoinen at the receiver's own
  height x Black-Eisner mapping (so the 50-m altitude difference is a real differential), + wet
  fluctuation 3 cm zenith (1800 s) common and 5 mm rover-only.  Orbit: 3-D error vector per
  satellite (radial 0.3, along 1.0, cross 0.6 m, tau 1800 s) projected on each receiver's own LOS.
  Satellite clock error 1.0 m (1200 s).  Rover (drone patch antenna): code noise 0.25 m, code MP
  0.4 m (tau 8 s), carrier 2 mm / 8 mm (tau 8 s), all x 1/sin(el); Doppler 0.05 m/s.  Base
  (geodetic choke ring): 0.1 m, 0.1 m, 1 mm, 2 mm, x 1/sin(el).  Clocks steered, tau 30 s.

"rtk-gec" (issue 12: 'rtk' under the 'uav-gec' sky)
---------------------------------------------------
* 'rtk' (short baseline, dual-frequency rover, three slips on the same GPS satellites, the 30-s
  outage) with the 'uav-gec' sky and dual_frequency on every system: GPS L1 C/A + L2 P(Y), Galileo
  E1 + E5b, BeiDou B1I + B3I.  The GPS observables are 'rtk''s bit for bit.  No QZSS: the
  recording the sky is moved from has no QZSS ephemerides.

"uav-gec" (issue 11: 'uav' under GPS + Galileo + BeiDou)
--------------------------------------------------------
* Sky: 'uav''s GPS (GEONET 2005) plus the real Galileo I/NAV and BeiDou D1/D2 (MEO, IGSO, GEO)
  ephemerides of a base station in Hiroshima, 2022-12-13 01:09 GPST, moved by one common time shift
  onto 2005-04-02 00:20:00 GPST (sitl.sky_multignss: the ECEF orbits at the scenario start are those
  over Japan 38 s after the recording's start, the shift being on a 120-s grid so that RTCM 1046 /
  1042 carry the moved ephemerides exactly).  Above the 10-deg mask: GPS 7, Galileo 9, BeiDou 19.
* Signals (companion.gnss.signals names): Galileo E1 'L1C' (+ E5b 'L7Q' if dual_frequency), BeiDou
  B1I 'L2I' (+ B3I 'L6I'), each with its own carrier wavelength; ionosphere (f_L1/f)^2 x the L1 delay
  (same Klobuchar truth + fluctuation as GPS); the broadcast group delays applied as prepare removes
  them (Galileo BGD(E1,E5b) of the I/NAV clock, BeiDou TGD1 on B1I against the B3I clock).
* The same receiver error model for every system (Galileo E1 and BeiDou B1I code noise and multipath
  as GPS L1 C/A: the rover's patch antenna and its multipath dominate, not the code chipping rate),
  the same per-satellite orbit / satellite-clock / atmosphere processes, drawn from streams of their
  own so the GPS observables are 'uav''s bit for bit.  Receiver inter-system bias per system (not
  GPS; QZSS would share GPS's), rover and base independently: N(0, 30 m) + random walk
  2 mm/sqrt(s), on code and carrier alike.

"nhc" / "nhc-skid" (seed 002, car near GEONET 0759, real 2005-04-02 ephemeris, 00:20 GPST)
------------------------------------------------------------------------------------------
* Motion: sitl.trajectory.road_drive, 596 s: rest 15 s, straights, three 90-deg turns, a
  roundabout (30 right / 210 left / 30 right), a 45-deg curve, braking, a 20-s stop at 249-269 s,
  5-20 m/s; grade -3..+3 deg (= pitch), crossfall +-1.5 deg, suspension roll 0.4 deg per m/s^2
  outward, side-slip 0.1 deg per m/s^2 (body lateral speed <= 0.05 m/s); body vertical velocity 0.
  'nhc-skid': + 2 m/s body-lateral skid held 3 s from t0+320 s (0.5-s ramps), GNSS available.
* IMU ADIS16405 class, 50 Hz: gyro turn-on (after calibration) 0.05 deg/s, in-run instability GM
  0.007 deg/s (tau 100 s), ARW 2 deg/sqrt(h); accel turn-on 1 mg, instability GM 0.2 mg (100 s),
  VRW 0.2 m/s/sqrt(h).  Lever arm IMU->antenna (0.5, 0, -0.9) m.
* GNSS u-blox EVK-6T class standalone L1, 1 Hz, mask 10 deg, SA off: iono 1.15 x Klobuchar +
  0.5 m zenith GM (900 s); tropo 1.05 x Saastamoinen + 3 cm; orbit RAC (0.3, 1.0, 0.6) m; satellite
  clock 1 m; code noise 0.4 m, code multipath 0.6 m GM 10 s, both x 1/sin(el); Doppler 0.1 m/s.
  Rover outages (no epochs) 135-165 s (30 s, roundabout) and 350-410 s (60 s).  No base.

"attitude" (seed 003) / "attitude-mems"
---------------------------------------
* Motion: sitl.trajectory.survey_aircraft, 600 s (the paper flew 2.6 h): 55-65 m/s, 300-m climb,
  180/180/270/90-deg coordinated turns (bank 17-23 deg), 150-m descent; pitch = flight-path angle +
  2.5 deg x load factor.  Lever arm (1, 0, -1) m.
* IMU 200 Hz, seed 003 Table 1: gyro bias 0.05 deg/h, ARW 0.002 deg/sqrt(h), accel bias 250 ug,
  VRW 0.001 m/s/sqrt(h) (turn-on biases, Gaussian per axis); initial misalignment sigma 0.01 deg
  tilt, 0.03 deg heading.  'attitude-mems': the 'nhc' ADIS16405 model at 200 Hz, 0.3/3 deg.
* GNSS: no raw observables; PPK-class GnssFix at 1 Hz (PpkFixModel: position GM 4/4/6 cm N/E/U,
  tau 60 s, + 1 cm white; velocity 1 cm/s white, the paper's Table 1 figure) and three-antenna
  GnssAttitude at 1 Hz (AttitudeAntennas: l12 = l13 = 1 m, baseline errors 1.75 mm horizontal,
  3.5 mm vertical -> heading 0.10, pitch 0.20, roll 0.20 deg).  The paper's own "0.5 cm / 1 cm
  point errors give 0.1/0.2 deg at 1 m" is inconsistent to first order (0.5 cm / 1 m = 0.29 deg);
  the errors are scaled to its stated 0.1 deg heading with its 1:2 horizontal:vertical ratio.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.messages import SPEED_OF_LIGHT_MPS, GpsEphemeris, gps_time
from companion.nav.earth import C_n_e, ecef_to_geodetic, geodetic_to_ecef

from . import sky
from .trajectory import PaperTrajectory, road_drive, survey_aircraft, survey_flight

_SQ3 = math.sqrt(3.0)


@dataclass(frozen=True)
class SlowError:
    """A per-satellite slow range error (2nd-order GM, critically damped), metres.

    value(receiver) = mapping(el) * [model_scale * model(receiver) + sigma_common_m * g(t)
                                     + (rover only) sigma_diff_m * h(t)]
    g, h: unit-variance independent GM processes with correlation times tau_s, tau_diff_s.
    mapping: 'none' (1), 'iono' (thin-shell obliquity, 350 km), 'tropo' (Black-Eisner).
    model: 'none', 'klobuchar' (already slant, not mapped again), 'saastamoinen' (zenith, mapped).
    """

    sigma_common_m: float
    sigma_diff_m: float
    tau_s: float
    tau_diff_s: float | None = None
    mapping: str = "none"
    model: str = "none"
    model_scale: float = 1.0


@dataclass(frozen=True)
class OrbitError:
    """Broadcast-orbit error.  Scalar LOS processes (common + rover-only) and/or a 3-D vector in
    radial/along/cross axes projected on each receiver's own line of sight; GM2, tau_s."""

    sigma_los_common_m: float = 0.0
    sigma_los_diff_m: float = 0.0
    sigma_rac_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tau_s: float = 1800.0


@dataclass(frozen=True)
class ReceiverErrors:
    """Site/receiver errors (1-sigma, metres at zenith when el_scaling)."""

    code_noise_m: float
    code_mp_m: float
    code_mp_tau_s: float
    carrier_noise_m: float
    carrier_mp_m: float
    carrier_mp_tau_s: float
    doppler_noise_mps: float = 0.05
    el_scaling: bool = False          # multiply by 1/sin(el), el capped at 5 deg


@dataclass(frozen=True)
class ClockModel:
    """Steered TCXO: b' = d + w_f, d' = -b/tau^2 - 2d/tau + w_g; PSDs in m^2/s and m^2/s^3."""

    h0_s: float = 2e-19
    h_minus2_per_s: float = 2e-20
    steer_tau_s: float = 30.0

    @property
    def s_f(self) -> float:
        return SPEED_OF_LIGHT_MPS ** 2 * self.h0_s / 2.0

    @property
    def s_g(self) -> float:
        return 2.0 * math.pi ** 2 * SPEED_OF_LIGHT_MPS ** 2 * self.h_minus2_per_s


@dataclass(frozen=True)
class ImuModel:
    """IMU errors on rates (rad/s, m/s^2).  Bias = turn-on + GM instability; noise white."""

    rate_hz: float
    gyro_bias_fixed_radps: float = 0.0     # magnitude, per-axis random sign (paper)
    gyro_bias_sigma_radps: float = 0.0     # turn-on, Gaussian per axis
    gyro_bi_sigma_radps: float = 0.0       # bias instability (1st-order GM)
    gyro_bi_tau_s: float = 300.0
    gyro_noise_uniform_radps: float = 0.0  # half-width of uniform white noise per sample
    gyro_arw_radps_per_sqrthz: float = 0.0  # noise density (rad/s/sqrt(Hz) = rad/sqrt(s))
    accel_bias_fixed_mps2: float = 0.0
    accel_bias_sigma_mps2: float = 0.0
    accel_bi_sigma_mps2: float = 0.0
    accel_bi_tau_s: float = 300.0
    accel_noise_uniform_mps2: float = 0.0
    accel_vrw_mps2_per_sqrthz: float = 0.0


@dataclass(frozen=True)
class PpkFixModel:
    """Post-processed (PPK-class) antenna position/velocity solutions fed as ``GnssFix``.
    Position error per local NED axis = 1st-order GM (sigma_pos_ned_m, tau_s: PPK errors wander
    with the satellite geometry and residual atmosphere) + white noise; velocity error white."""

    rate_hz: float = 1.0
    sigma_pos_ned_m: tuple[float, float, float] = (0.04, 0.04, 0.06)
    tau_s: float = 60.0
    white_pos_m: float = 0.01
    sigma_vel_mps: float = 0.01              # white velocity error per axis
    vel_gm_sigma_mps: float = 0.0            # time-correlated velocity error per axis (1st-order GM)
    vel_gm_tau_s: float = 20.0

    @property
    def sigma_vel_total_mps(self) -> float:
        return math.hypot(self.sigma_vel_mps, self.vel_gm_sigma_mps)

    @property
    def sigma_h_m(self) -> float:
        """2-D horizontal sigma as GnssFix wants it (per-axis variance = sigma_h^2 / 2)."""
        s = self.sigma_pos_ned_m
        return math.sqrt(s[0] ** 2 + s[1] ** 2 + 2.0 * self.white_pos_m ** 2)

    @property
    def sigma_v_m(self) -> float:
        return math.hypot(self.sigma_pos_ned_m[2], self.white_pos_m)


@dataclass(frozen=True)
class AttitudeAntennas:
    """Three GNSS antennas (seed 003 fig 1): antenna 2 at ``l12_m`` along body x, antenna 3 at
    ``l13_m`` along body y from antenna 1 (perpendicular: the best geometry for roll).  Each
    baseline vector is measured (carrier-phase moving baseline, fixed ambiguities) with white
    errors ``sigma_h_m`` per horizontal and ``sigma_v_m`` vertical component, independent between
    baselines and epochs.  The direct method (seed 003 eqs 3-5) gives heading and pitch from
    baseline 12 and roll from baseline 13; first order (eqs 9-11):
    sigma_heading = sigma_h / (l12 cos pitch), sigma_pitch = sigma_v / l12,
    sigma_roll = sigma_v / l13 (antenna-baseline misalignment: zero, i.e. already calibrated)."""

    l12_m: float = 1.0
    l13_m: float = 1.0
    sigma_h_m: float = 0.00175
    sigma_v_m: float = 0.0035
    rate_hz: float = 1.0

    @property
    def sigma_heading_rad(self) -> float:
        return self.sigma_h_m / self.l12_m

    @property
    def sigma_pitch_rad(self) -> float:
        return self.sigma_v_m / self.l12_m

    @property
    def sigma_roll_rad(self) -> float:
        return self.sigma_v_m / self.l13_m


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    trajectory: object                       # PaperTrajectory | SurveyTrajectory
    t0_gps: float                            # first IMU sample (truth start), true GPS time
    duration_s: float
    imu: ImuModel
    ephemerides: tuple[GpsEphemeris, ...]
    base_r_e: np.ndarray
    base_station_id: int = 0
    lever_arm_b: tuple[float, float, float] = (0.0, 0.0, 0.0)
    mask_deg: float = 5.0
    gnss_rate_hz: float = 1.0
    iono: SlowError = SlowError(0.0, 0.0, 600.0)
    tropo: SlowError = SlowError(0.0, 0.0, 1200.0)
    sat_clock: SlowError = SlowError(0.0, 0.0, 1200.0)
    sa: SlowError = SlowError(0.0, 0.0, 180.0)
    orbit: OrbitError = OrbitError()
    rover_rx: ReceiverErrors = ReceiverErrors(0.3, 0.5, 5.0, 0.002, 0.01, 5.0)
    base_rx: ReceiverErrors = ReceiverErrors(0.1, 0.15, 5.0, 0.001, 0.003, 5.0)
    rover_clock: ClockModel = ClockModel()
    base_clock: ClockModel = ClockModel()
    klobuchar_alpha: tuple = (0.0, 0.0, 0.0, 0.0)
    klobuchar_beta: tuple = (0.0, 0.0, 0.0, 0.0)
    rover_outages: tuple[tuple[float, float], ...] = ()      # (t_gps start, t_gps end), no rover epochs
    cycle_slips: tuple[tuple[float, str, int], ...] = ()     # (t_gps, sat, cycles), rover
    default_seed: int = 0
    # added for seeds 002/003 (defaults reproduce the original scenarios bit for bit)
    raw_gnss: bool = True                    # simulate rover raw observables
    simulate_base: bool = True               # simulate base-station raw observables
    ppk: PpkFixModel | None = None           # also emit PPK-class GnssFix solutions
    gnss_attitude: AttitudeAntennas | None = None   # also emit three-antenna GnssAttitude
    initial_attitude_sigma_rad: tuple[float, float] | None = None   # (tilt, heading) alignment
    dual_frequency: bool = False             # also GPS L2 P(Y) ('L2W') code and carrier (the rtk scenario)
    # added for multi-GNSS (issue 11); the defaults keep every GPS-only scenario bit for bit
    systems: str = "G"                       # RINEX letters of the simulated systems ('GEC')
    isb_sigma_m: float = 30.0                # receiver inter-system bias, constant part, 1-sigma per system
    isb_rw_m_per_sqrt_s: float = 0.002       # its random walk (system-time offset and hardware drift)
    notes: dict = field(default_factory=dict, compare=False)

    @property
    def origin_r_e(self) -> np.ndarray:
        lat, lon, h = self.trajectory.origin_llh
        return geodetic_to_ecef(lat, lon, h)

    @property
    def C_t_e(self) -> np.ndarray:
        lat, lon, _ = self.trajectory.origin_llh
        return C_n_e(lat, lon)


def _paper() -> Scenario:
    lat, lon, h = math.radians(-6.0), math.radians(22.0), 1000.0
    week = 1316
    t0 = gps_time(week, 252000.0) + 0.0063
    duration = 500.0
    traj = PaperTrajectory(origin_llh=(lat, lon, h), duration_s=duration,
                           a_b_mps2=(0.25, 0.15, 1e-5), euler_rates_radps=(0.0, 0.01, 0.01))
    # base 3 km from the start, bearing 135 deg, same ellipsoidal height
    d_n = 3000.0 * np.array([math.cos(math.radians(135.0)), math.sin(math.radians(135.0)), 0.0])
    r0 = geodetic_to_ecef(lat, lon, h)
    bl = ecef_to_geodetic(r0 + C_n_e(lat, lon) @ d_n)
    base = geodetic_to_ecef(bl[0], bl[1], h)

    def tab(gps, dgps, tau, **kw):
        g, d = gps / _SQ3, dgps / _SQ3
        return SlowError(math.sqrt(g * g - d * d), d, tau, **kw)

    return Scenario(
        name="paper",
        description="seed 000 sec 4.1: constant body acceleration and Euler rates, HG1700 IMU, "
                    "Table 1 errors, Table 3 ephemerides, 6S 22E",
        trajectory=traj, t0_gps=t0, duration_s=duration,
        imu=ImuModel(rate_hz=100.0,
                     gyro_bias_fixed_radps=2.424068e-6, gyro_noise_uniform_radps=2.424068e-6,
                     accel_bias_fixed_mps2=0.0249, accel_noise_uniform_mps2=0.00637),
        ephemerides=tuple(sky.paper_ephemerides(week)),
        base_r_e=base, base_station_id=1, lever_arm_b=(0.0, 0.0, 0.0), mask_deg=5.0,
        iono=tab(5.0, 0.5, 600.0), tropo=tab(1.5, 0.2, 1200.0),
        sat_clock=tab(3.0, 0.0, 1200.0), sa=tab(100.0, 0.0, 180.0),
        orbit=OrbitError(sigma_los_common_m=math.sqrt(4.2 ** 2 - 0.3 ** 2) / _SQ3,
                         sigma_los_diff_m=0.3 / _SQ3, tau_s=1800.0),
        rover_rx=ReceiverErrors(code_noise_m=1.0 / _SQ3, code_mp_m=1.0 / _SQ3, code_mp_tau_s=5.0,
                                carrier_noise_m=0.0025, carrier_mp_m=0.01, carrier_mp_tau_s=5.0,
                                doppler_noise_mps=0.05),
        base_rx=ReceiverErrors(code_noise_m=0.1, code_mp_m=0.15, code_mp_tau_s=5.0,
                               carrier_noise_m=0.001, carrier_mp_m=0.003, carrier_mp_tau_s=5.0,
                               doppler_noise_mps=0.02),
        rover_clock=ClockModel(steer_tau_s=10.0), base_clock=ClockModel(steer_tau_s=30.0),
        default_seed=0,
    )


def _uav(systems: str = "G", n_legs: int = 6) -> Scenario:
    from companion.gnss.rinex import read_rinex_nav_header_iono

    week = 1316
    t_start_int = gps_time(week, 6 * 86400.0 + 20 * 60.0)     # 2005-04-02 00:20:00 GPST
    t0 = t_start_int + 0.0063
    lat7, lon7, h7 = ecef_to_geodetic(sky.GEONET_0759_R_E)
    start = sky.GEONET_0759_R_E + C_n_e(lat7, lon7) @ np.array([-100.0, 50.0, 2.0])
    lat0, lon0, h0 = ecef_to_geodetic(start)
    traj = survey_flight((lat0, lon0, h0), heading0_rad=math.radians(20.0), n_legs=n_legs)
    duration = traj.duration_s
    ephs = sky.select_ephemerides(sky.geonet_ephemerides(), t0, t0 + duration)
    if systems != "G":
        from .sky_multignss import moved_ephemerides
        others = "".join(s for s in systems if s != "G")
        ephs.update(sky.select_ephemerides(moved_ephemerides(t_start_int, others), t0, t0 + duration))
    iono_ab = read_rinex_nav_header_iono(sky.GEONET_NAV)
    alpha, beta = (tuple(float(x) for x in iono_ab[0]), tuple(float(x) for x in iono_ab[1])) \
        if iono_ab is not None else ((0.0,) * 4, (0.0,) * 4)
    deg = math.pi / 180.0
    return Scenario(
        name="uav",
        description="survey flight near GEONET 0759, base at 3040, real 2005-04-02 broadcast "
                    "ephemeris, MEMS IMU, 30-s rover outage",
        trajectory=traj, t0_gps=t0, duration_s=duration,
        imu=ImuModel(rate_hz=200.0,
                     gyro_bias_sigma_radps=0.25 * deg, gyro_bi_sigma_radps=10.0 * deg / 3600.0,
                     gyro_bi_tau_s=200.0, gyro_arw_radps_per_sqrthz=0.2 * deg / 60.0,
                     accel_bias_sigma_mps2=0.1, accel_bi_sigma_mps2=5e-3, accel_bi_tau_s=300.0,
                     accel_vrw_mps2_per_sqrthz=7e-4),
        ephemerides=tuple(ephs[s] for s in sorted(ephs)),
        base_r_e=sky.GEONET_3040_R_E.copy(), base_station_id=3040,
        lever_arm_b=(0.10, 0.0, -0.15), mask_deg=10.0,
        iono=SlowError(0.5, 0.01, 900.0, tau_diff_s=600.0, mapping="iono", model="klobuchar",
                       model_scale=1.15),
        tropo=SlowError(0.03, 0.005, 1800.0, mapping="tropo", model="saastamoinen",
                        model_scale=1.05),
        sat_clock=SlowError(1.0, 0.0, 1200.0), sa=SlowError(0.0, 0.0, 180.0),
        orbit=OrbitError(sigma_rac_m=(0.3, 1.0, 0.6), tau_s=1800.0),
        rover_rx=ReceiverErrors(code_noise_m=0.25, code_mp_m=0.4, code_mp_tau_s=8.0,
                                carrier_noise_m=0.002, carrier_mp_m=0.008, carrier_mp_tau_s=8.0,
                                doppler_noise_mps=0.05, el_scaling=True),
        base_rx=ReceiverErrors(code_noise_m=0.1, code_mp_m=0.1, code_mp_tau_s=8.0,
                               carrier_noise_m=0.001, carrier_mp_m=0.002, carrier_mp_tau_s=8.0,
                               doppler_noise_mps=0.02, el_scaling=True),
        rover_clock=ClockModel(steer_tau_s=30.0), base_clock=ClockModel(steer_tau_s=30.0),
        klobuchar_alpha=alpha, klobuchar_beta=beta,
        rover_outages=((t0 + 130.0, t0 + 160.0),),
        default_seed=0, systems=systems,
    )


def _uav_gec() -> Scenario:
    """'uav' under GPS (GEONET 2005) + Galileo + BeiDou (Hiroshima 2022, moved onto the same epoch:
    sitl.sky_multignss); the GPS observables are those of 'uav' bit for bit."""
    import dataclasses
    s = _uav("GEC")
    return dataclasses.replace(s, name="uav-gec", description=s.description + ", GPS+Galileo+BeiDou")


def _uav_hour() -> Scenario:
    """'uav' stretched to an hour: 106 survey legs instead of 6 (a 216-m by 4.2-km strip), the same
    sensors, sky and 30-s outage.  For long-run checks (the field log of an hour's flight)."""
    import dataclasses
    s = _uav(n_legs=106)
    return dataclasses.replace(s, name="uav-1h", description=s.description + ", one hour (106 legs)")


def _paper_nosa() -> Scenario:
    """The paper scenario with SA switched off (as since May 2000); everything else identical."""
    import dataclasses
    return dataclasses.replace(_paper(), name="paper-nosa", sa=SlowError(0.0, 0.0, 180.0),
                               description=_paper().description + ", SA off")


def _geonet_iono():
    from companion.gnss.rinex import read_rinex_nav_header_iono
    iono_ab = read_rinex_nav_header_iono(sky.GEONET_NAV)
    return (tuple(float(x) for x in iono_ab[0]), tuple(float(x) for x in iono_ab[1])) \
        if iono_ab is not None else ((0.0,) * 4, (0.0,) * 4)


#: the skid of the 'nhc-skid' variant: start (s from t0), body-lateral speed, hold
NHC_SKID = (320.0, 2.0, 3.0)
#: the two rover outages of 'nhc' (s from t0): 30 s over the roundabout, 60 s over the end of
#: the 20-m/s straight, the 45-deg curve and the next straight
NHC_OUTAGES = ((135.0, 165.0), (350.0, 410.0))


def _nhc(skid: bool = False) -> Scenario:
    deg = math.pi / 180.0
    mg = 9.80665e-3
    week = 1316
    t0 = gps_time(week, 6 * 86400.0 + 20 * 60.0) + 0.0063       # 2005-04-02 00:20:00 GPST
    lat7, lon7, h7 = ecef_to_geodetic(sky.GEONET_0759_R_E)
    start = sky.GEONET_0759_R_E + C_n_e(lat7, lon7) @ np.array([-300.0, 200.0, 1.5])
    lat0, lon0, h0 = ecef_to_geodetic(start)
    traj = road_drive((lat0, lon0, h0), heading0_rad=math.radians(30.0),
                      skid_at_s=NHC_SKID[0] if skid else None, skid_mps=NHC_SKID[1], skid_s=NHC_SKID[2])
    duration = traj.duration_s
    ephs = sky.select_ephemerides(sky.geonet_ephemerides(), t0, t0 + duration)
    alpha, beta = _geonet_iono()
    return Scenario(
        name="nhc-skid" if skid else "nhc",
        description="seed 002: car near GEONET 0759, ADIS16405 IMU 50 Hz, u-blox EVK-6T standalone L1 "
                    "1 Hz, outages of 30 s and 60 s" + (", 2 m/s skid for 3 s" if skid else ""),
        trajectory=traj, t0_gps=t0, duration_s=duration,
        imu=ImuModel(rate_hz=50.0,
                     gyro_bias_sigma_radps=0.05 * deg, gyro_bi_sigma_radps=0.007 * deg, gyro_bi_tau_s=100.0,
                     gyro_arw_radps_per_sqrthz=2.0 * deg / 60.0,
                     accel_bias_sigma_mps2=1.0 * mg, accel_bi_sigma_mps2=0.2 * mg, accel_bi_tau_s=100.0,
                     accel_vrw_mps2_per_sqrthz=0.2 / 60.0),
        ephemerides=tuple(ephs[s] for s in sorted(ephs)),
        base_r_e=sky.GEONET_3040_R_E.copy(), base_station_id=3040,
        lever_arm_b=(0.5, 0.0, -0.9), mask_deg=10.0,
        iono=SlowError(0.5, 0.0, 900.0, mapping="iono", model="klobuchar", model_scale=1.15),
        tropo=SlowError(0.03, 0.0, 1800.0, mapping="tropo", model="saastamoinen", model_scale=1.05),
        sat_clock=SlowError(1.0, 0.0, 1200.0), sa=SlowError(0.0, 0.0, 180.0),
        orbit=OrbitError(sigma_rac_m=(0.3, 1.0, 0.6), tau_s=1800.0),
        rover_rx=ReceiverErrors(code_noise_m=0.4, code_mp_m=0.6, code_mp_tau_s=10.0,
                                carrier_noise_m=0.003, carrier_mp_m=0.01, carrier_mp_tau_s=10.0,
                                doppler_noise_mps=0.1, el_scaling=True),
        rover_clock=ClockModel(steer_tau_s=30.0), klobuchar_alpha=alpha, klobuchar_beta=beta,
        rover_outages=tuple((t0 + a, t0 + b) for a, b in NHC_OUTAGES),
        simulate_base=False, default_seed=2,
    )


def _attitude() -> Scenario:
    deg = math.pi / 180.0
    ug = 9.80665e-6
    week = 1316
    t0 = gps_time(week, 6 * 86400.0 + 20 * 60.0) + 0.0063
    lat7, lon7, h7 = ecef_to_geodetic(sky.GEONET_0759_R_E)
    start = sky.GEONET_0759_R_E + C_n_e(lat7, lon7) @ np.array([0.0, 0.0, -1200.0])
    lat0, lon0, h0 = ecef_to_geodetic(start)
    traj = survey_aircraft((lat0, lon0, h0))
    return Scenario(
        name="attitude",
        description="seed 003: 10-min survey flight, navigation-grade IMU 200 Hz, PPK position/velocity "
                    "1 Hz, three-antenna GNSS attitude 1 Hz (1 m baselines)",
        trajectory=traj, t0_gps=t0, duration_s=traj.duration_s,
        imu=ImuModel(rate_hz=200.0,
                     gyro_bias_sigma_radps=0.05 * deg / 3600.0, gyro_arw_radps_per_sqrthz=0.002 * deg / 60.0,
                     accel_bias_sigma_mps2=250.0 * ug, accel_vrw_mps2_per_sqrthz=0.001 / 60.0),
        ephemerides=(), base_r_e=sky.GEONET_3040_R_E.copy(), base_station_id=3040,
        lever_arm_b=(1.0, 0.0, -1.0), raw_gnss=False, simulate_base=False,
        ppk=PpkFixModel(), gnss_attitude=AttitudeAntennas(),
        initial_attitude_sigma_rad=(0.01 * deg, 0.03 * deg), default_seed=3,
    )


def _attitude_mems() -> Scenario:
    """'attitude' with the ADIS16405-class MEMS IMU of 'nhc' (at 200 Hz) and a compass-class initial
    alignment (tilt 0.3 deg, heading 3 deg): where 1-m-baseline GNSS attitude does help roll/pitch."""
    import dataclasses
    nhc = _nhc()
    base = _attitude()
    return dataclasses.replace(base, name="attitude-mems",
                               description=base.description.replace("navigation-grade IMU", "ADIS16405-class IMU"),
                               imu=dataclasses.replace(nhc.imu, rate_hz=200.0),
                               initial_attitude_sigma_rad=(math.radians(0.3), math.radians(3.0)))


#: the rtk scenario's slips (s from t0, rank of the satellite by elevation at that time, cycles):
#: the reference (highest) satellite, a middle one and a low one
RTK_SLIPS = ((60.0, 0, 1), (95.0, 3, -5), (200.0, 5, 2))
RTK_OUTAGE_S = (130.0, 160.0)


def _rtk(systems: str = "G") -> Scenario:
    """'uav' with a short baseline and a dual-frequency (L1 C/A + L2 P(Y)) RTK rover: the base on
    station 0759's header position (110 m from the take-off, at most ~0.5 km away), the rover a
    drone-class RTK receiver, three cycle slips and the 30-s outage.  ``systems`` 'GEC': the
    'uav-gec' sky (Galileo E1 + E5b, BeiDou B1I + B3I as well); the slips hit the same GPS
    satellites as in 'rtk' (ranked among GPS only), whose observables are 'rtk''s bit for bit."""
    import dataclasses
    from companion.gnss.ephemeris import satellite_state
    uav = _uav(systems)
    t0 = uav.t0_gps
    base = sky.GEONET_0759_R_E.copy()
    slips = []
    for dt, rank, cyc in RTK_SLIPS:
        els = sorted(((sky.elevation_azimuth(base, satellite_state(e, t0 + dt)[0])[0], e.sat)
                      for e in uav.ephemerides if e.sat[0] == "G"), reverse=True)
        els = [x for x in els if x[0] > math.radians(uav.mask_deg + 5.0)]
        slips.append((t0 + dt, els[min(rank, len(els) - 1)][1], cyc))
    return dataclasses.replace(
        uav, name="rtk",
        description="uav with a 0.1-0.5 km baseline (base on GEONET 0759), dual-frequency RTK rover, "
                    "3 cycle slips, 30-s rover outage",
        base_r_e=base, base_station_id=759, dual_frequency=True,
        # short baseline: the rover-only atmosphere is a few millimetres
        iono=dataclasses.replace(uav.iono, sigma_diff_m=0.002),
        tropo=dataclasses.replace(uav.tropo, sigma_diff_m=0.002),
        rover_rx=ReceiverErrors(code_noise_m=0.25, code_mp_m=0.3, code_mp_tau_s=8.0,
                                carrier_noise_m=0.002, carrier_mp_m=0.005, carrier_mp_tau_s=8.0,
                                doppler_noise_mps=0.05, el_scaling=True),
        rover_outages=((t0 + RTK_OUTAGE_S[0], t0 + RTK_OUTAGE_S[1]),),
        cycle_slips=tuple(slips))


def _rtk_gec() -> Scenario:
    """'rtk' under GPS + Galileo + BeiDou (the 'uav-gec' sky), dual-frequency on every system."""
    import dataclasses
    s = _rtk("GEC")
    return dataclasses.replace(s, name="rtk-gec", description=s.description + ", GPS+Galileo+BeiDou "
                               "(E1+E5b, B1I+B3I)")


_BUILDERS = {"paper": _paper, "paper-nosa": _paper_nosa, "uav": _uav, "uav-gec": _uav_gec, "uav-1h": _uav_hour, "nhc": _nhc,
             "nhc-skid": lambda: _nhc(skid=True), "attitude": _attitude,
             "attitude-mems": _attitude_mems, "rtk": _rtk, "rtk-gec": _rtk_gec}


def build_scenario(name: str) -> Scenario:
    """'paper', 'paper-nosa', 'uav', 'uav-gec', 'uav-1h', 'nhc', 'nhc-skid', 'attitude', 'attitude-mems' or
    'rtk', 'rtk-gec' (see the module docstring)."""
    try:
        return _BUILDERS[name]()
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; known: {sorted(_BUILDERS)}") from None


SCENARIOS = tuple(_BUILDERS)
