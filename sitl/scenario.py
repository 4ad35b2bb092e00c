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
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.messages import SPEED_OF_LIGHT_MPS, GpsEphemeris, gps_time
from companion.nav.earth import C_n_e, ecef_to_geodetic, geodetic_to_ecef

from . import sky
from .trajectory import PaperTrajectory, survey_flight

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


def _uav() -> Scenario:
    from companion.gnss.rinex import read_rinex_nav_header_iono

    week = 1316
    t_start_int = gps_time(week, 6 * 86400.0 + 20 * 60.0)     # 2005-04-02 00:20:00 GPST
    t0 = t_start_int + 0.0063
    lat7, lon7, h7 = ecef_to_geodetic(sky.GEONET_0759_R_E)
    start = sky.GEONET_0759_R_E + C_n_e(lat7, lon7) @ np.array([-100.0, 50.0, 2.0])
    lat0, lon0, h0 = ecef_to_geodetic(start)
    traj = survey_flight((lat0, lon0, h0), heading0_rad=math.radians(20.0))
    duration = traj.duration_s
    ephs = sky.select_ephemerides(sky.geonet_ephemerides(), t0, t0 + duration)
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
        default_seed=0,
    )


def _paper_nosa() -> Scenario:
    """The paper scenario with SA switched off (as since May 2000); everything else identical."""
    import dataclasses
    return dataclasses.replace(_paper(), name="paper-nosa", sa=SlowError(0.0, 0.0, 180.0),
                               description=_paper().description + ", SA off")


_BUILDERS = {"paper": _paper, "paper-nosa": _paper_nosa, "uav": _uav}


def build_scenario(name: str) -> Scenario:
    """'paper', 'paper-nosa' or 'uav' (see the module docstring for every modelling choice)."""
    try:
        return _BUILDERS[name]()
    except KeyError:
        raise ValueError(f"unknown scenario {name!r}; known: {sorted(_BUILDERS)}") from None


SCENARIOS = tuple(_BUILDERS)
