"""Turn a :class:`sitl.scenario.Scenario` into truth, IMU samples and rover/base GNSS epochs.

``simulate(scenario, seed) -> SimData``.  Deterministic: each error process draws from its own
``np.random.default_rng([seed, STREAM])``.  See :mod:`sitl.scenario` for the models.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.gnss.atmosphere import klobuchar_delay_m, saastamoinen_zenith_m
from companion.gnss.signals import clock_group, frequency_hz, group_delay_m
from companion.messages import (GPS_L1_HZ, GPS_L1_WAVELENGTH_M, GPS_L2_HZ, GPS_L2_WAVELENGTH_M,
                                SPEED_OF_LIGHT_MPS, BaseStationPosition,
                                GnssEpoch, GpsEphemeris, ImuSample, SatObservation)
from companion.nav.earth import ecef_to_geodetic
from companion.nav.strapdown import invert_step

from . import sensors
from .scenario import Scenario
from .sky import elevation_azimuth, light_time_range

C = SPEED_OF_LIGHT_MPS
LAMBDA = GPS_L1_WAVELENGTH_M
DOPPLER_STEP_S = 1e-3          # central difference half-step for the Doppler range rate

# random streams (one per process; adding a process never changes the others)
_S_IMU, _S_CLK_ROVER, _S_CLK_BASE = 1, 2, 3
_S_IONO_C, _S_IONO_D, _S_TROPO_C, _S_TROPO_D, _S_SATCLK, _S_SA = 10, 11, 12, 13, 14, 15
_S_ORB_C, _S_ORB_D, _S_ORB_RAC = 16, 17, 18
_S_SITE = {"rover": 20, "base": 30}
_S_AMB = {"rover": 40, "base": 41}
_S_SITE_L2 = {"rover": 21, "base": 31}     # second frequency (Scenario.dual_frequency)
_S_AMB_L2 = {"rover": 42, "base": 43}
GAMMA_L2 = (GPS_L1_HZ / GPS_L2_HZ) ** 2      # L2 ionospheric delay / L1's
_S_PPK, _S_ATT = 50, 51
_S_IMU_UNIT = 60               # + k: redundant IMU unit k (SimData.extra_imu_units)
_S_GROUP_OFFSET = 1000         # + stream: the same process for the non-GPS satellites (_system_groups)
_S_ISB = {"rover": 2000, "base": 2001}   # [seed, _S_ISB, ord(system)]: inter-system bias


@dataclass(eq=False)
class Truth:
    t_gps: np.ndarray        # (N,) IMU sample times (true GPS time), t_gps[0] = t0
    r_e: np.ndarray          # (N, 3) IMU position, ECEF
    v_e: np.ndarray          # (N, 3)
    C_b_e: np.ndarray        # (N, 3, 3)


@dataclass(eq=False)
class SimData:
    scenario: Scenario
    seed: int
    truth: Truth
    imu: list[ImuSample]
    imu_ideal_dtheta_b: np.ndarray     # (N-1, 3) error-free increments (invert_step)
    imu_ideal_dv_b: np.ndarray
    rover_epochs: list[GnssEpoch]
    base_epochs: list[GnssEpoch]
    ephemerides: list[GpsEphemeris]
    base: BaseStationPosition
    lever_arm_b: np.ndarray
    errors: dict = field(default_factory=dict)
    gnss_fixes: list = field(default_factory=list)              # GnssFix (scenario.ppk)
    attitude_measurements: list = field(default_factory=list)   # GnssAttitude (scenario.gnss_attitude)

    @property
    def imu_ideal(self) -> list[ImuSample]:
        """Error-free IMU samples (same times as ``imu``)."""
        t, dt = self.truth.t_gps, 1.0 / self.scenario.imu.rate_hz
        return [ImuSample(float(t[i + 1]), dt, self.imu_ideal_dtheta_b[i], self.imu_ideal_dv_b[i])
                for i in range(len(t) - 1)]

    def extra_imu_units(self, n_units: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """Increments (dtheta_b (N-1, 3), dv_b (N-1, 3)) of ``n_units`` more IMUs of the scenario's
        model, mounted with the first and sampled with it (an autopilot's redundant IMUs): the same
        ideal increments, independent error realisations (unit k draws from stream
        ``[seed, _S_IMU_UNIT + k]``; unit 0 is ``imu``)."""
        tau = 1.0 / self.scenario.imu.rate_hz
        out = []
        for k in range(1, n_units + 1):
            ie = sensors.imu_errors(np.random.default_rng([self.seed, _S_IMU_UNIT + k]), self.scenario.imu,
                                    len(self.imu_ideal_dtheta_b))
            out.append((self.imu_ideal_dtheta_b + ie["gyro_error"] * tau, self.imu_ideal_dv_b + ie["accel_error"] * tau))
        return out

    def initial_state(self):
        """(t0_gps, r_e, v_e, C_b_e) of the IMU at the first sample (truth)."""
        tr = self.truth
        return float(tr.t_gps[0]), tr.r_e[0].copy(), tr.v_e[0].copy(), tr.C_b_e[0].copy()

    def truth_at(self, t_gps: float):
        """(r_e, v_e, C_b_e) of the IMU at any time in the run: cubic Hermite position between
        samples, the trajectory's own velocity and attitude."""
        return _truth_at(self.scenario, self.truth, t_gps)

    def antenna_at(self, t_gps: float):
        r, _, Cbe = self.truth_at(t_gps)
        return r + Cbe @ self.lever_arm_b


def _truth_at(scn: Scenario, tr: Truth, t_gps: float):
    f = scn.imu.rate_hz
    tau = 1.0 / f
    x = (t_gps - tr.t_gps[0]) * f
    k = min(max(int(math.floor(x)), 0), len(tr.t_gps) - 2)
    s = (t_gps - tr.t_gps[k]) / tau
    s2, s3 = s * s, s * s * s
    r = ((2 * s3 - 3 * s2 + 1) * tr.r_e[k] + (s3 - 2 * s2 + s) * tau * tr.v_e[k]
         + (-2 * s3 + 3 * s2) * tr.r_e[k + 1] + (s3 - s2) * tau * tr.v_e[k + 1])
    t_rel = t_gps - tr.t_gps[0]
    Cte = scn.C_t_e
    v = Cte @ scn.trajectory.velocity_t(t_rel)[0]
    Cbe = Cte @ scn.trajectory.attitude_t(t_rel)[0]
    return r, v, Cbe


def make_truth(scn: Scenario) -> Truth:
    f = scn.imu.rate_hz
    n = int(round(scn.duration_s * f)) + 1
    t_rel = np.arange(n) / f
    Cte = scn.C_t_e
    v_e = scn.trajectory.velocity_t(t_rel) @ Cte.T
    C_b_e = np.einsum("ij,njk->nik", Cte, scn.trajectory.attitude_t(t_rel))
    tau = 1.0 / f
    r_e = np.empty((n, 3))
    r_e[0] = scn.origin_r_e
    inc = 0.5 * tau * (v_e[:-1] + v_e[1:])
    r = r_e[0].copy()
    for i in range(n - 1):              # sequential, exactly the mechanization's trapezoid rule
        r = r + inc[i]
        r_e[i + 1] = r
    return Truth(scn.t0_gps + t_rel, r_e, v_e, C_b_e)


def ideal_increments(scn: Scenario, tr: Truth):
    """Error-free increments that take the mechanization exactly from each truth sample to the
    next (:func:`companion.nav.strapdown.invert_step`, the exact inverse of ``strapdown_step``)."""
    tau = 1.0 / scn.imu.rate_hz
    n = len(tr.t_gps)
    dth = np.empty((n - 1, 3))
    dv = np.empty((n - 1, 3))
    for i in range(n - 1):
        dth[i], dv[i] = invert_step(tr.r_e[i], tr.v_e[i], tr.C_b_e[i], tr.v_e[i + 1], tr.C_b_e[i + 1], tau)
    return dth, dv


def _system_groups(sats: list[str]) -> list[list[str]]:
    """GPS satellites first (in the given order), then every other system's: each group draws its
    random processes from its own streams (group g: stream + g x _S_GROUP_OFFSET), so adding
    Galileo/BeiDou leaves every GPS observable of a scenario as it was, bit for bit."""
    gps = [s for s in sats if s[0] == "G"]
    other = [s for s in sats if s[0] != "G"]
    return [g for g in (gps, other) if g] if other else [gps]


class _Atmosphere:
    """Slow per-satellite processes (common and rover-only parts), times relative to t0; GPS and
    the other systems in separate groups (:func:`_system_groups`)."""

    def __init__(self, scn: Scenario, seed: int, sats: list[str]):
        groups = _system_groups(list(sats))
        offsets = [0 if g[0][0] == "G" else _S_GROUP_OFFSET for g in groups] if sats else [0]
        self.groups = [_AtmosphereGroup(scn, seed, g, off) for g, off in zip(groups, offsets)]
        self.where = {s: k for k, g in enumerate(groups) for s in g}

    def slow_at(self, t_rel) -> list[dict]:
        """Every group's slow processes at the times ``t_rel`` (see :meth:`_AtmosphereGroup.slow_at`)."""
        return [g.slow_at(t_rel) for g in self.groups]

    def components(self, sat: str, slow: list[dict], i: int, *args) -> dict[str, float]:
        k = self.where[sat]
        return self.groups[k].components(sat, slow[k], i, *args)


class _AtmosphereGroup:
    """The slow processes of one group of satellites (streams offset by ``stream_offset``)."""

    def __init__(self, scn: Scenario, seed: int, sats: list[str], stream_offset: int = 0):
        self.scn = scn
        self.idx = {s: i for i, s in enumerate(sats)}
        t0, t1 = -5.0, scn.duration_s + 5.0
        S = len(sats)

        def proc(stream, sigma, tau, n=S):
            if sigma == 0.0:
                return None
            return sensors.smooth_processes(np.random.default_rng([seed, stream + stream_offset]), t0, t1,
                                            tau, n, sigma)

        self.iono_c = proc(_S_IONO_C, scn.iono.sigma_common_m, scn.iono.tau_s)
        self.iono_d = proc(_S_IONO_D, scn.iono.sigma_diff_m, scn.iono.tau_diff_s or scn.iono.tau_s)
        self.tropo_c = proc(_S_TROPO_C, scn.tropo.sigma_common_m, scn.tropo.tau_s)
        self.tropo_d = proc(_S_TROPO_D, scn.tropo.sigma_diff_m, scn.tropo.tau_diff_s or scn.tropo.tau_s)
        self.satclk = proc(_S_SATCLK, scn.sat_clock.sigma_common_m, scn.sat_clock.tau_s)
        self.sa = proc(_S_SA, scn.sa.sigma_common_m, scn.sa.tau_s)
        self.orb_c = proc(_S_ORB_C, scn.orbit.sigma_los_common_m, scn.orbit.tau_s)
        self.orb_d = proc(_S_ORB_D, scn.orbit.sigma_los_diff_m, scn.orbit.tau_s)
        self.orb_rac = (proc(_S_ORB_RAC, 1.0, scn.orbit.tau_s, 3 * S)
                        if any(scn.orbit.sigma_rac_m) else None)

    def slow_at(self, t_rel) -> dict:
        """All slow processes at the times ``t_rel`` (relative to t0): name -> (len(t), S or 3S)."""
        t_rel = np.asarray(t_rel, float)
        out = {}
        for name in ("iono_c", "iono_d", "tropo_c", "tropo_d", "satclk", "sa", "orb_c", "orb_d",
                     "orb_rac"):
            p = getattr(self, name)
            out[name] = None if p is None else p.value(t_rel)
        return out

    def components(self, sat: str, slow: dict, i: int, t_gps: float, rover: bool, r_ant, el, az,
                   r_sat, v_sat) -> dict[str, float]:
        """Slow error components (m) for one satellite; ``slow`` from :meth:`slow_at`, row ``i``."""
        scn, j = self.scn, self.idx[sat]

        def v(name):
            a = slow[name]
            return 0.0 if a is None else float(a[i, j])

        lat, lon, h = ecef_to_geodetic(r_ant)
        # ionosphere
        m_i = 1.0 if scn.iono.mapping == "none" else float(sensors.iono_obliquity(el))
        iono = m_i * (v("iono_c") + (v("iono_d") if rover else 0.0))
        if scn.iono.model == "klobuchar":
            iono += scn.iono.model_scale * klobuchar_delay_m(t_gps, lat, lon, az, el,
                                                             scn.klobuchar_alpha, scn.klobuchar_beta)
        # troposphere
        m_t = 1.0 if scn.tropo.mapping == "none" else float(sensors.tropo_obliquity(el))
        tropo = v("tropo_c") + (v("tropo_d") if rover else 0.0)
        if scn.tropo.model == "saastamoinen":
            zhd, zwd = saastamoinen_zenith_m(lat, h)
            tropo += scn.tropo.model_scale * (zhd + zwd)
        tropo *= m_t
        # orbit along the line of sight (receiver -> satellite)
        orb = v("orb_c") + (v("orb_d") if rover else 0.0)
        if slow["orb_rac"] is not None:
            d = r_sat - r_ant
            u = d / math.sqrt(float(d @ d))
            e_r = r_sat / math.sqrt(float(r_sat @ r_sat))
            e_c = _cross(r_sat, v_sat)
            e_c /= math.sqrt(float(e_c @ e_c))
            e_a = _cross(e_c, e_r)
            x = slow["orb_rac"][i, 3 * j:3 * j + 3] * np.asarray(scn.orbit.sigma_rac_m)
            orb += float(u @ (x[0] * e_r + x[1] * e_a + x[2] * e_c))
        return {"iono_m": iono, "tropo_m": tropo, "orbit_m": orb,
                "sat_clock_err_m": v("satclk"), "sa_m": v("sa")}


def _cross(a, b) -> np.ndarray:
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


_COMPONENTS = ("geometric_m", "sat_clock_brdc_m", "iono_m", "tropo_m", "orbit_m", "sat_clock_err_m",
               "sa_m", "code_mp_m", "code_noise_m", "carrier_mp_m", "carrier_noise_m",
               "doppler_noise_hz", "range_rate_mps", "elevation_rad", "azimuth_rad",
               "ambiguity_cycles", "isb_m")


class _SiteNoise:
    """Receiver site errors of one satellite group (code/carrier multipath and noise, Doppler
    noise, ambiguity draws; the second frequency from its own streams), ``stream_offset`` added
    to every stream id."""

    def __init__(self, seed: int, who: str, rx, K: int, S: int, dt_ep: float, dual: bool,
                 stream_offset: int = 0):
        rs = np.random.default_rng([seed, _S_SITE[who] + stream_offset])
        self.code_mp = sensors.gm1(rs, K, dt_ep, rx.code_mp_tau_s, rx.code_mp_m, S)
        self.car_mp = sensors.gm1(rs, K, dt_ep, rx.carrier_mp_tau_s, rx.carrier_mp_m, S)
        self.code_n = rs.standard_normal((K, S)) * rx.code_noise_m
        self.car_n = rs.standard_normal((K, S)) * rx.carrier_noise_m
        self.dop_n_mps = rs.standard_normal((K, S)) * rx.doppler_noise_mps    # / wavelength -> Hz
        self.r_amb = np.random.default_rng([seed, _S_AMB[who] + stream_offset])
        if dual:
            # L2 (P(Y), 'L2W' for GPS): its own site errors and ambiguities from their own streams,
            # so the L1 observables are those of the single-frequency scenario bit for bit
            r2 = np.random.default_rng([seed, _S_SITE_L2[who] + stream_offset])
            self.code_mp2 = sensors.gm1(r2, K, dt_ep, rx.code_mp_tau_s, rx.code_mp_m, S)
            self.car_mp2 = sensors.gm1(r2, K, dt_ep, rx.carrier_mp_tau_s, rx.carrier_mp_m, S)
            self.code_n2 = r2.standard_normal((K, S)) * rx.code_noise_m
            self.car_n2 = r2.standard_normal((K, S)) * rx.carrier_noise_m
            self.r_amb2 = np.random.default_rng([seed, _S_AMB_L2[who] + stream_offset])


def _isb_process(seed: int, who: str, system: str, scn: Scenario, K: int, dt_ep: float) -> np.ndarray:
    """Receiver inter-system bias of ``system`` against GPS (m, per epoch): a constant
    N(0, isb_sigma_m) (hardware group delays, the system-time offset) plus a random walk; 0 for GPS
    and for systems sharing GPS's clock (QZSS, companion.gnss.signals.CLOCK_GROUPS)."""
    if clock_group(system) == "G":
        return np.zeros(K)
    r = np.random.default_rng([seed, _S_ISB[who], ord(system)])
    const = r.standard_normal() * scn.isb_sigma_m
    steps = r.standard_normal(K) * scn.isb_rw_m_per_sqrt_s * math.sqrt(dt_ep)
    steps[0] = 0.0
    return const + np.cumsum(steps)


#: observed signals per system (companion.gnss.signals names): single-frequency code, then the
#: second frequency of a dual-frequency scenario.  Galileo E5b with the I/NAV clock (its BGD),
#: BeiDou B3I (the D1/D2 clock's own code)
SIGNALS = {"G": ("L1C", "L2W"), "J": ("L1C", "L2L"), "E": ("L1C", "L7Q"), "C": ("L2I", "L6I")}


class _SignalModel:
    """Per satellite and signal: wavelength, ionospheric factor (f_L1/f)^2 and broadcast group
    delay (m) the signal carries relative to the broadcast clock -- exactly what
    companion.gnss.prepare subtracts (signals.group_delay_m with the same factor)."""

    def __init__(self, eph: GpsEphemeris, signal: str):
        self.signal = signal
        f = frequency_hz(eph.sat, signal)
        self.wavelength_m = C / f
        self.iono_factor = (self.wavelength_m / (C / GPS_L1_HZ)) ** 2
        self.group_delay_m = group_delay_m(eph, (signal,), self.iono_factor)


class ReceiverModel:
    """One receiver's observations, epoch by epoch: the batch simulation and a live trajectory
    (``sitl.ardupilot_gnss``: ArduPilot SITL's truth followed in real time) share this model.

    Every random process is drawn up front for the scenario's epoch grid (receiver time tags
    ``T_rx = k / gnss_rate_hz`` over ``[t0_gps, t0_gps + duration_s]``, the same streams in the same
    order as always), so :meth:`epoch` ``k`` depends on nothing but the antenna position it is
    given.  Ask for epochs in increasing ``k``; a ``k`` not asked for is a gap in tracking (a
    satellite seen again after it gets a new ambiguity and loss of lock).  ``antenna(t)``: the
    antenna phase centre (ECEF, m) at true GPS time ``t``; a base receiver ignores it (its
    position is ``scn.base_r_e``).

    Other systems than GPS (ephemerides of Galileo, BeiDou, QZSS among ``ephs``): their site
    errors and ambiguities come from their own streams (:func:`_system_groups`); each system has
    its signals (:data:`SIGNALS`), carrier wavelength, ionospheric delay (f_L1/f)^2 x the L1 one,
    broadcast group delay, and a receiver inter-system bias on code and carrier
    (:func:`_isb_process`).  GPS keeps its historical arithmetic (L1 C/A, L2 P(Y) sharing the L1
    TGD term) so GPS-only scenarios are unchanged bit for bit."""

    def __init__(self, scn: Scenario, seed: int, who: str, atmo: _Atmosphere, ephs: list[GpsEphemeris]):
        self.scn, self.who, self.atmo, self.ephs = scn, who, atmo, ephs
        self.rover = rover = who == "rover"
        rx = self.rx = scn.rover_rx if rover else scn.base_rx
        clk_model = scn.rover_clock if rover else scn.base_clock
        dt_ep = 1.0 / scn.gnss_rate_hz
        t_end = scn.t0_gps + scn.duration_s
        k0 = math.ceil(scn.t0_gps / dt_ep)
        k1 = math.floor(t_end / dt_ep)
        self.T_rx = T_rx = np.arange(k0, k1 + 1) * dt_ep          # receiver time tags (integer seconds)
        K, S = len(T_rx), len(ephs)

        self.b, self.d = sensors.clock_process(
            np.random.default_rng([seed, _S_CLK_ROVER if rover else _S_CLK_BASE]), clk_model, K, dt_ep)
        self.t_true = T_rx - self.b / C

        self.dual = scn.dual_frequency
        groups = _system_groups([e.sat for e in ephs])
        self.site = [_SiteNoise(seed, who, rx, K, len(g), dt_ep, self.dual,
                                0 if g[0][0] == "G" else _S_GROUP_OFFSET) for g in groups] if S else []
        # satellite -> (its site-noise group, its column there)
        self.where = {s: (k, j) for k, g in enumerate(groups) for j, s in enumerate(g)}
        systems = sorted({e.sat[0] for e in ephs})
        self.isb = {s: _isb_process(seed, who, s, scn, K, dt_ep) for s in systems if s != "G"}
        self.sig = {e.sat: tuple(_SignalModel(e, s) for s in SIGNALS[e.sat[0]][:2 if self.dual else 1])
                    for e in ephs if e.sat[0] != "G"}
        self.amb2: dict[str, int] = {}

        self.errs = {c: np.full((K, S), np.nan) for c in _COMPONENTS}
        self.keep = np.ones(K, bool)
        if rover:
            for a, z in scn.rover_outages:
                self.keep &= ~((self.t_true >= a) & (self.t_true < z))
        self.slips = sorted(scn.cycle_slips) if rover else []
        self.slip_used = [False] * len(self.slips)
        self.amb: dict[str, int] = {}
        self.lock_start: dict[str, float] = {}
        self.last_seen: dict[str, int] = {}
        self.first_epoch = True

    def _phase_range(self, eph, t, r_ant, tau_guess, iters, slow, i):
        """Noise-free carrier-phase range terms except the receiver clock (m) and its parts
        (L1 ionosphere; GPS's broadcast clock term includes its TGD as always)."""
        rho, tau, r_s, v_s, clk, _ = light_time_range(eph, t, r_ant, tau_guess, iters)
        el, az = elevation_azimuth(r_ant, r_s)
        comp = self.atmo.components(eph.sat, slow, i, t, self.rover, r_ant, el, az, r_s, v_s)
        if eph.sat[0] == "G":
            brdc = C * (clk - eph.tgd_s)
            iono = comp["iono_m"]
        else:
            sm = self.sig[eph.sat][0]
            brdc = C * clk - sm.group_delay_m
            iono = sm.iono_factor * comp["iono_m"]
        phi = (rho - brdc + comp["sat_clock_err_m"] + comp["sa_m"] - iono
               + comp["tropo_m"] + comp["orbit_m"])
        return phi, rho, tau, el, az, brdc, comp

    def epoch(self, k: int, antenna=None) -> GnssEpoch | None:
        """Epoch ``k`` of the grid (None in a rover outage)."""
        if not self.keep[k]:
            return None
        scn, rx, T_rx, b, d = self.scn, self.rx, self.T_rx, self.b, self.d
        if not self.rover:
            def antenna(_t):
                return scn.base_r_e
        h = DOPPLER_STEP_S
        t = float(self.t_true[k])
        r_c = antenna(t)
        r_m, r_p = antenna(t - h), antenna(t + h)
        slow = self.atmo.slow_at(np.array([t - h, t, t + h]) - scn.t0_gps)
        amb, lock_start, last_seen, slips, e = self.amb, self.lock_start, self.last_seen, self.slips, self.errs
        obs = []
        for jj, eph in enumerate(self.ephs):
            phi, rho, tau, el, az, brdc, comp = self._phase_range(eph, t, r_c, 0.075, 3, slow, 1)
            if el < math.radians(scn.mask_deg):
                continue
            phi_m = self._phase_range(eph, t - h, r_m, tau, 2, slow, 0)[0]
            phi_p = self._phase_range(eph, t + h, r_p, tau, 2, slow, 2)[0]
            sat = eph.sat
            g, j = self.where[sat]
            site = self.site[g]
            isb = self.isb[sat[0]][k] if sat[0] in self.isb else 0.0
            rate = (phi_p - phi_m) / (2.0 * h) + d[k]
            lol = False
            prev = last_seen.get(sat)
            if prev is None or prev != k - 1:     # not tracked at the previous epoch
                if sat in amb:
                    lol = True                 # re-acquisition after a gap: new ambiguity
                amb[sat] = int(site.r_amb.integers(-2 ** 20, 2 ** 20 + 1))
                if self.dual:
                    self.amb2[sat] = int(site.r_amb2.integers(-2 ** 20, 2 ** 20 + 1))
                lock_start[sat] = T_rx[k]
            for i, (ts, ss, cyc) in enumerate(slips):
                if not self.slip_used[i] and ss == sat and ts <= T_rx[k]:
                    self.slip_used[i] = True
                    amb[sat] += int(cyc)
                    if self.dual:
                        self.amb2[sat] += int(cyc)
                    lock_start[sat] = T_rx[k]
                    lol = True
            last_seen[sat] = k
            f_el = float(sensors.elevation_factor(el, rx.el_scaling))
            mp_c, n_c = site.code_mp[k, j] * f_el, site.code_n[k, j] * f_el
            mp_p, n_p = site.car_mp[k, j] * f_el, site.car_n[k, j] * f_el
            common = rho + b[k] - brdc + comp["sat_clock_err_m"] + comp["sa_m"] + comp["tropo_m"] \
                + comp["orbit_m"]
            lock_s = float(T_rx[k] - lock_start[sat])
            lol_out = lol and not self.first_epoch
            cn0 = float(sensors.cn0_dbhz(el))
            if sat[0] == "G":
                pr = common + comp["iono_m"] + mp_c + n_c
                cp = (common - comp["iono_m"] + mp_p + n_p) / LAMBDA + amb[sat]
                dop = -rate / LAMBDA + site.dop_n_mps[k, j] / LAMBDA
                obs.append(SatObservation(sat=sat, pseudorange_m=float(pr), carrier_cycles=float(cp),
                                          doppler_hz=float(dop), cn0_dbhz=cn0, lock_time_s=lock_s,
                                          loss_of_lock=lol_out))
                if self.dual:
                    iono2 = GAMMA_L2 * comp["iono_m"]
                    pr2 = common + iono2 + (site.code_mp2[k, j] + site.code_n2[k, j]) * f_el
                    cp2 = (common - iono2 + (site.car_mp2[k, j] + site.car_n2[k, j]) * f_el) \
                        / GPS_L2_WAVELENGTH_M + self.amb2[sat]
                    obs.append(SatObservation(sat=sat, pseudorange_m=float(pr2), carrier_cycles=float(cp2),
                                              cn0_dbhz=cn0 - 3.0, lock_time_s=lock_s, loss_of_lock=lol_out,
                                              signal="L2W", wavelength_m=GPS_L2_WAVELENGTH_M))
            else:
                # every signal: common (first signal's group delay in brdc) + its own group delay
                # and ionosphere; the inter-system bias on code and carrier alike (a clock offset)
                sigs = self.sig[sat]
                s1 = sigs[0]
                base = common + isb
                lam = s1.wavelength_m
                iono1 = s1.iono_factor * comp["iono_m"]
                pr = base + iono1 + mp_c + n_c
                cp = (base - iono1 + mp_p + n_p) / lam + amb[sat]
                dop = -rate / lam + site.dop_n_mps[k, j] / lam
                obs.append(SatObservation(sat=sat, pseudorange_m=float(pr), carrier_cycles=float(cp),
                                          doppler_hz=float(dop), cn0_dbhz=cn0, lock_time_s=lock_s,
                                          loss_of_lock=lol_out, signal=s1.signal, wavelength_m=lam))
                if self.dual:
                    s2 = sigs[1]
                    base2 = base - s1.group_delay_m + s2.group_delay_m
                    iono2 = s2.iono_factor * comp["iono_m"]
                    pr2 = base2 + iono2 + (site.code_mp2[k, j] + site.code_n2[k, j]) * f_el
                    cp2 = (base2 - iono2 + (site.car_mp2[k, j] + site.car_n2[k, j]) * f_el) / s2.wavelength_m \
                        + self.amb2[sat]
                    obs.append(SatObservation(sat=sat, pseudorange_m=float(pr2), carrier_cycles=float(cp2),
                                              cn0_dbhz=cn0 - 3.0, lock_time_s=lock_s, loss_of_lock=lol_out,
                                              signal=s2.signal, wavelength_m=s2.wavelength_m))
            e["geometric_m"][k, jj] = rho
            e["sat_clock_brdc_m"][k, jj] = brdc
            for c in ("iono_m", "tropo_m", "orbit_m", "sat_clock_err_m", "sa_m"):
                e[c][k, jj] = comp[c]
            e["code_mp_m"][k, jj], e["code_noise_m"][k, jj] = mp_c, n_c
            e["carrier_mp_m"][k, jj], e["carrier_noise_m"][k, jj] = mp_p, n_p
            e["doppler_noise_hz"][k, jj] = site.dop_n_mps[k, j] / (LAMBDA if sat[0] == "G" else self.sig[sat][0].wavelength_m)
            e["range_rate_mps"][k, jj] = rate
            e["elevation_rad"][k, jj], e["azimuth_rad"][k, jj] = el, az
            e["ambiguity_cycles"][k, jj] = amb[sat]
            e["isb_m"][k, jj] = isb
        self.first_epoch = False
        return GnssEpoch(t_gps=float(T_rx[k]), observations=tuple(obs), source=self.who)
    def errors(self) -> dict:
        """Every error component per epoch and satellite (NaN where not observed), and the clock."""
        return {**self.errs, "sats": [e.sat for e in self.ephs], "t_rx_gps": self.T_rx, "t_gps": self.t_true,
                "emitted": self.keep, "rx_clock_m": self.b, "rx_clock_drift_mps": self.d}


def _receiver(scn: Scenario, seed: int, who: str, tr: Truth, atmo: _Atmosphere,
              ephs: list[GpsEphemeris], lever_b: np.ndarray):
    model = ReceiverModel(scn, seed, who, atmo, ephs)

    def antenna(t):
        r, _, Cbe = _truth_at(scn, tr, t)
        return r + Cbe @ lever_b

    epochs = [ep for ep in (model.epoch(k, antenna) for k in range(len(model.T_rx))) if ep is not None]
    return epochs, model.errors()


def simulate(scenario: Scenario, seed: int | None = None) -> SimData:
    scn = scenario
    seed = scn.default_seed if seed is None else int(seed)
    tr = make_truth(scn)
    dth, dv = ideal_increments(scn, tr)
    ie = sensors.imu_errors(np.random.default_rng([seed, _S_IMU]), scn.imu, len(dth))
    tau = 1.0 / scn.imu.rate_hz
    dth_m = dth + ie["gyro_error"] * tau
    dv_m = dv + ie["accel_error"] * tau
    imu = [ImuSample(float(tr.t_gps[i + 1]), tau, dth_m[i], dv_m[i]) for i in range(len(dth))]

    ephs = list(scn.ephemerides)
    lever = np.asarray(scn.lever_arm_b, float)
    atmo = _Atmosphere(scn, seed, [e.sat for e in ephs])
    rover_epochs, rover_err = _receiver(scn, seed, "rover", tr, atmo, ephs, lever) if scn.raw_gnss else ([], {})
    base_epochs, base_err = _receiver(scn, seed, "base", tr, atmo, ephs, lever) if scn.simulate_base else ([], {})
    errors = {"imu": ie, "rover": rover_err, "base": base_err}
    fixes = attitudes = []
    if scn.ppk is not None:
        fixes, errors["ppk"] = _ppk_fixes(scn, seed, tr, lever)
    if scn.gnss_attitude is not None:
        attitudes, errors["attitude"] = _gnss_attitudes(scn, seed, tr)
    return SimData(scenario=scn, seed=seed, truth=tr, imu=imu, imu_ideal_dtheta_b=dth,
                   imu_ideal_dv_b=dv, rover_epochs=rover_epochs, base_epochs=base_epochs,
                   ephemerides=ephs,
                   base=BaseStationPosition(scn.base_station_id, np.asarray(scn.base_r_e, float).copy()),
                   lever_arm_b=lever, errors=errors, gnss_fixes=fixes, attitude_measurements=attitudes)


def _solution_times(scn: Scenario, rate_hz: float) -> np.ndarray:
    """Solution epochs at whole multiples of 1/rate in true GPS time, outside the rover outages."""
    dt = 1.0 / rate_hz
    t_end = scn.t0_gps + scn.duration_s
    k = np.arange(math.ceil(scn.t0_gps / dt), math.floor(t_end / dt) + 1)
    t = k * dt
    keep = np.ones(len(t), bool)
    for a, z in scn.rover_outages:
        keep &= ~((t >= a) & (t < z))
    return t[keep]


def _ppk_fixes(scn: Scenario, seed: int, tr: Truth, lever_b: np.ndarray):
    """PPK-class antenna solutions (see scenario.PpkFixModel): truth antenna position/velocity
    (lever arm included, earth-rotation term of the antenna velocity included) plus errors in the
    local NED frame of the start point."""
    from companion.messages import GnssFix
    from companion.nav.earth import OMEGA_IE_RADPS

    m = scn.ppk
    t = _solution_times(scn, m.rate_hz)
    rng = np.random.default_rng([seed, _S_PPK])
    gm = sensors.gm1(rng, len(t), 1.0 / m.rate_hz, m.tau_s, 1.0, 3) * np.asarray(m.sigma_pos_ned_m)
    white = rng.standard_normal((len(t), 3)) * m.white_pos_m
    vel = rng.standard_normal((len(t), 3)) * m.sigma_vel_mps
    if m.vel_gm_sigma_mps > 0.0:
        vel = vel + sensors.gm1(rng, len(t), 1.0 / m.rate_hz, m.vel_gm_tau_s, m.vel_gm_sigma_mps, 3)
    Cne = scn.C_t_e
    f = scn.imu.rate_hz
    fixes = []
    for i, ti in enumerate(t):
        r, v, Cbe = _truth_at(scn, tr, float(ti))
        # body rate from the trajectory's attitude (central difference) for the lever-arm velocity
        h = 0.5 / f
        C_m = Cte_att(scn, float(ti) - h)
        C_p = Cte_att(scn, float(ti) + h)
        dC = C_m.T @ C_p
        w_b = np.array([dC[2, 1] - dC[1, 2], dC[0, 2] - dC[2, 0], dC[1, 0] - dC[0, 1]]) / (4.0 * h)
        l_e = Cbe @ lever_b
        r_ant = r + l_e
        v_ant = v + Cbe @ np.cross(w_b, lever_b) - np.array([-OMEGA_IE_RADPS * l_e[1], OMEGA_IE_RADPS * l_e[0], 0.0])
        fixes.append(GnssFix(t_gps=float(ti), r_e=r_ant + Cne @ (gm[i] + white[i]), v_e=v_ant + Cne @ vel[i],
                             sigma_h_m=m.sigma_h_m, sigma_v_m=m.sigma_v_m, sigma_vel_mps=m.sigma_vel_total_mps,
                             num_sats=9, fix_type=6))
    return fixes, {"t_gps": t, "pos_error_ned_m": gm + white, "vel_error_ned_mps": vel}


def Cte_att(scn: Scenario, t_gps: float) -> np.ndarray:
    """Body-to-ECEF attitude of the trajectory at a true GPS time (earth-fixed tangent frame)."""
    return scn.C_t_e @ scn.trajectory.attitude_t(t_gps - scn.t0_gps)[0]


def _gnss_attitudes(scn: Scenario, seed: int, tr: Truth):
    """Three-antenna attitude by the direct method (seed 003 eqs 3-5) from baseline vectors with
    white errors (scenario.AttitudeAntennas), expressed in the local NED frame at the IMU."""
    from companion.messages import GnssAttitude
    from companion.nav.earth import C_n_e

    m = scn.gnss_attitude
    t = _solution_times(scn, m.rate_hz)
    rng = np.random.default_rng([seed, _S_ATT])
    sig = np.array([m.sigma_h_m, m.sigma_h_m, m.sigma_v_m])
    e12 = rng.standard_normal((len(t), 3)) * sig
    e13 = rng.standard_normal((len(t), 3)) * sig
    out, true_e, meas_e = [], [], []
    for i, ti in enumerate(t):
        r, _, Cbe = _truth_at(scn, tr, float(ti))
        lat, lon, _ = ecef_to_geodetic(r)
        Cbn = C_n_e(lat, lon).T @ Cbe
        b12 = Cbn @ np.array([m.l12_m, 0.0, 0.0]) + e12[i]
        b13 = Cbn @ np.array([0.0, m.l13_m, 0.0]) + e13[i]
        heading = math.atan2(b12[1], b12[0])
        pitch = math.atan2(-b12[2], math.hypot(b12[0], b12[1]))
        # undo heading and pitch: b13 -> Rx(roll) (0, l13, 0) = (0, l13 cos roll, l13 sin roll)
        ch, sh, cp, sp = math.cos(heading), math.sin(heading), math.cos(pitch), math.sin(pitch)
        x1, y1, z1 = ch * b13[0] + sh * b13[1], -sh * b13[0] + ch * b13[1], b13[2]
        y2, z2 = y1, sp * x1 + cp * z1
        roll = math.atan2(z2, y2)
        sig_h = m.sigma_heading_rad / max(math.cos(pitch), 0.1)
        out.append(GnssAttitude(t_gps=float(ti), heading_rad=heading, pitch_rad=pitch, roll_rad=roll,
                                sigma_heading_rad=sig_h, sigma_pitch_rad=m.sigma_pitch_rad,
                                sigma_roll_rad=m.sigma_roll_rad))
        true_e.append(_euler(Cbn))
        meas_e.append((roll, pitch, heading))
    return out, {"t_gps": t, "euler_true_rad": np.array(true_e), "euler_meas_rad": np.array(meas_e)}


def _euler(Cbn: np.ndarray) -> tuple[float, float, float]:
    """(roll, pitch, heading) of a body-to-NED rotation (ZYX)."""
    return (math.atan2(Cbn[2, 1], Cbn[2, 2]), -math.asin(max(-1.0, min(1.0, Cbn[2, 0]))),
            math.atan2(Cbn[1, 0], Cbn[0, 0]))


def feed_engine(eng, sim: SimData, latency_s: float, *, use_gnss: bool = True, rover=None, base=None, imu=None):
    """Drive a NavEngine offline through a simulated flight as the service would: every GNSS epoch
    (base first, then rover) once ``latency_s`` has passed since its time, then each IMU sample.
    ``rover``, ``base``, ``imu`` replace the flight's own (a part of it, altered epochs).  Yields
    ``(k, sample)`` after the k-th sample (from 1)."""
    rover = sim.rover_epochs if rover is None else rover
    base = sim.base_epochs if base is None else base
    i_rov = i_base = 0
    for k, s in enumerate(sim.imu if imu is None else imu, start=1):
        if use_gnss:
            while i_base < len(base) and base[i_base].t_gps + latency_s <= s.t_gps:
                eng.process(base[i_base])
                i_base += 1
            while i_rov < len(rover) and rover[i_rov].t_gps + latency_s <= s.t_gps:
                eng.process(rover[i_rov])
                i_rov += 1
        eng.process_imu(s)
        yield k, s
