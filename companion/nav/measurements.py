"""Measurement models: each turns the predicted INS state at the measurement time and a raw
measurement into a :class:`~companion.nav.filter.MeasurementBatch` (innovation z, Jacobian H,
noise variances).  Adding a sensor means adding one function here, not editing the filter.

Conventions: ``u`` is the unit line-of-sight vector from the antenna to the satellite (ECEF), so
d(range)/d(r_antenna) = -u^T.  The antenna is at r_ant = r_imu + C_b_e l_b; with the attitude error
convention C(true) = (I + [psi x]) C(est), d(r_ant)/d(psi) = -[(C_b_e l_b) x].

IMU time-tag offset (state ``dt_imu``, see :mod:`.filter`): a measurement taken at GNSS time t is
predicted from the INS at tag t - dt_imu, so its column is d(predicted)/d(dt_imu) = minus the rate
of change of the prediction along the INS trajectory: u.v_ant for a range, the antenna
acceleration (and the turning line of sight) for a range rate, -v_ant for a position, -a_ant for a
velocity, -H_psi (C_b_e w_ib_b - w_ie_e) for an attitude.  A measurement time-tagged on the
autopilot's own clock (GPS_RAW_INT, ATTITUDE: boot time mapped like the IMU's) shares the IMU's
offset and gets no column (``autopilot_clock``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..gnss.phase import PhaseRecord, row_dot  # PhaseRecord re-exported: TDCP's previous-epoch record
from .earth import OMEGA_IE_RADPS, skew
from .filter import LAYOUT, MeasurementBatch
from .state_layout import isb_block_name, system_of


_TEN_DEG_RAD = math.radians(10.0)


@dataclass
class InsPoint:
    """Nominal (INS) state at one instant, usually interpolated to a GNSS epoch's GPS time."""

    t_gps: float
    r_e: np.ndarray
    v_e: np.ndarray
    C_b_e: np.ndarray
    omega_ib_b: np.ndarray      # body angular rate over the last IMU interval, rad/s
    clock_bias_m: float
    clock_drift_mps: float
    a_e: np.ndarray | None = None   # IMU acceleration (ECEF, m/s^2) there, for the dt_imu column
    # nominal values of the layout's extra blocks by name (inter-system biases ``isb_E`` in m, ...)
    block_states: dict[str, np.ndarray] | None = None


def antenna_state(ins: InsPoint, lever_arm_b: np.ndarray):
    """(r_ant_e, v_ant_e, lever_arm_e) from the IMU state (seed 004 lever-arm equations)."""
    l_e = ins.C_b_e @ lever_arm_b
    w = ins.omega_ib_b
    wxl = np.array([w[1] * lever_arm_b[2] - w[2] * lever_arm_b[1],
                    w[2] * lever_arm_b[0] - w[0] * lever_arm_b[2],
                    w[0] * lever_arm_b[1] - w[1] * lever_arm_b[0]])
    earth_term = np.array([-OMEGA_IE_RADPS * l_e[1], OMEGA_IE_RADPS * l_e[0], 0.0])
    return ins.r_e + l_e, ins.v_e + ins.C_b_e @ wxl - earth_term, l_e


def antenna_velocity_attitude_partial(ins: InsPoint, lever_arm_b: np.ndarray) -> np.ndarray:
    """d v_ant / d psi (3x3): how an attitude error psi (C_true = (I + [psi x]) C) moves the
    antenna velocity of :func:`antenna_state`, v_ant = v + C (w x l) - W_ie x (C l).

    Not used by the rows yet (tests/test_measurement_jacobians.py checks it against finite
    differences).  Put into the Doppler and velocity-fix rows it broke the course alignment of a
    car started 120 deg off with no compass (tests/test_course_alignment.py): at rest, with the
    IMU's per-sample rate (gyro noise) in w, the column made the filter confident of a heading
    103 deg wrong within 15 s; in TDCP rows it cost an in-flight start's consistency
    (tests/test_inflight_init.py).  A rate averaged over the interval and a column only once the
    heading is known are the candidates."""
    w_l_e = ins.C_b_e @ np.cross(np.asarray(ins.omega_ib_b, float), lever_arm_b)
    l_e = ins.C_b_e @ lever_arm_b
    return -skew(w_l_e) + skew(np.array([0.0, 0.0, OMEGA_IE_RADPS])) @ skew(l_e)


def antenna_acceleration(ins: InsPoint, lever_arm_b: np.ndarray) -> np.ndarray:
    """Antenna acceleration (ECEF) at a constant body rate: the time derivative of
    :func:`antenna_state`'s velocity with dC/dt = C [w x] - [W_ie x] C (W_ie the earth rate)."""
    a = np.zeros(3) if ins.a_e is None else np.asarray(ins.a_e, float)
    w = np.asarray(ins.omega_ib_b, float)
    C = ins.C_b_e
    earth = np.array([0.0, 0.0, OMEGA_IE_RADPS])
    wl_e = C @ np.cross(w, lever_arm_b)
    return (a + C @ np.cross(w, np.cross(w, lever_arm_b)) - 2.0 * np.cross(earth, wl_e)
            + np.cross(earth, np.cross(earth, C @ lever_arm_b)))


def attitude_rate_e(ins: InsPoint) -> np.ndarray:
    """Rotation rate of C_b_e as an ECEF rotation vector: C(t + h) = (I + h [rate x]) C(t)."""
    return ins.C_b_e @ np.asarray(ins.omega_ib_b, float) - np.array([0.0, 0.0, OMEGA_IE_RADPS])


def line_of_sight(r_sat_e: np.ndarray, r_ant_e: np.ndarray):
    """(ranges (n,), unit vectors antenna->satellite (n,3))."""
    d = r_sat_e - r_ant_e
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    return rho, d / rho[:, None]


def pseudorange_batch(ins: InsPoint, prep, lever_arm_b: np.ndarray, layout=LAYOUT,
                      sigma_floor_m: float = 0.0) -> MeasurementBatch:
    """Corrected pseudoranges (standalone-modelled or DGPS-corrected, see gnss.prepare):
    model rho = |r_sat - r_ant| + clock_bias (+ isb of the satellite's system) + noise.  The
    receiver clock is GPS's; a system with an inter-system bias block in ``layout`` (``isb_E``
    etc.) adds that bias, whose nominal value is ``ins.block_states[name]``."""
    ok = np.isfinite(prep.pseudorange_m)
    r_ant, v_ant, l_e = antenna_state(ins, lever_arm_b)
    rho, u = line_of_sight(prep.r_sat_e[ok], r_ant)
    z = prep.pseudorange_m[ok] - (rho + ins.clock_bias_m)
    H = np.zeros((len(z), layout.n))
    H[:, layout.pos] = -u
    H[:, layout.att] = u @ skew(l_e)
    H[:, layout.clk] = 1.0
    H[:, layout.toff] = u @ v_ant
    sig = np.maximum(prep.sigma_pseudorange_m[ok], sigma_floor_m)
    labels = [s for s, k in zip(prep.sats, ok) if k]
    if layout.isb_index:
        states = ins.block_states or {}
        for k, sat in enumerate(labels):
            system = system_of(sat)
            col = layout.isb_index.get(system)
            if col is not None:
                H[k, col] = 1.0
                z[k] -= float(states.get(isb_block_name(system), (0.0,))[0])
    return MeasurementBatch("pseudorange", labels, z, H, sig * sig)


def doppler_batch(ins: InsPoint, prep, lever_arm_b: np.ndarray, sigma_mps: float,
                  layout=LAYOUT) -> MeasurementBatch:
    """Pseudorange rate from Doppler: -lambda*D + c*sat_clock_drift = u.(v_sat - v_ant) + drift."""
    ok = np.isfinite(prep.doppler_hz)
    r_ant, v_ant, _ = antenna_state(ins, lever_arm_b)
    rho, u = line_of_sight(prep.r_sat_e[ok], r_ant)
    dv = prep.v_sat_e[ok] - v_ant
    rate_meas = -prep.wavelength_m[ok] * prep.doppler_hz[ok] + prep.sat_clock_drift_mps[ok]
    u_dv = np.einsum("ij,ij->i", u, dv)
    rate_pred = u_dv + ins.clock_drift_mps
    H = np.zeros((len(rate_meas), layout.n))
    H[:, layout.vel] = -u
    # no attitude column: see antenna_velocity_attitude_partial
    H[:, layout.drift] = 1.0
    # dt_imu: the antenna acceleration along the line of sight, and the line of sight turning as
    # the antenna moves (d u / d r_ant = -(I - u u^T) / rho)
    uv = u @ v_ant
    H[:, layout.toff] = (u @ antenna_acceleration(ins, lever_arm_b)
                         + (np.einsum("ij,j->i", dv, v_ant) - uv * u_dv) / rho)
    labels = [s for s, k in zip(prep.sats, ok) if k]
    return MeasurementBatch("doppler", labels, rate_meas - rate_pred, H, np.full(len(labels), sigma_mps ** 2))


def tdcp_batch(ins: InsPoint, prep, previous: dict[str, PhaseRecord], lever_arm_b: np.ndarray,
               sigma_phase_m: float, sigma_rate_floor_mps: float, max_interval_s: float,
               layout=LAYOUT, phase_correction_m: dict[str, float] | None = None,
               elevation_scaling: bool = False, specific_force_e: np.ndarray | None = None) -> MeasurementBatch:
    """Pseudorange rate from time-differenced carrier phase (seed 000 eqs 2-7, 14).

    Over one epoch interval the integer ambiguity cancels.  The *prediction* uses the INS
    displacement between the two epochs (not the current velocity times the interval), so
    vehicle acceleration inside the interval costs nothing:

        z = [lambda (phi_k - phi_k-1) + c (dt_sat,k - dt_sat,k-1) + corr]/T
            - [ |r_sat,k - r_ant,k| - range_k-1 + drift T ] / T

    The error of the INS displacement is modelled as dv_k T (the velocity error over the
    interval), giving the paper's range-rate Jacobian H_v = -u plus the receiver clock drift.
    With ``specific_force_e`` (the mean specific force over the interval, ECEF, m/s^2) the
    displacement error also carries how the velocity error grew inside the interval,
    ``(T^2 / 2) ([f x] psi + C_b_e dba)``: with a heading uncertain by degrees (an initialisation
    in flight) and the vehicle accelerating, that term is several TDCP sigmas, and leaving it out
    made the gate reject good rows until the filter re-initialised again.
    A time-tag error dt_imu is common to both epochs (it is a slowly varying state): it changes the
    interval's range difference by (u_k.v_ant,k - u_k-1.v_ant,k-1) dt_imu, the change of the
    line-of-sight velocity over the interval (``PhaseRecord.los_rate_mps`` holds the earlier one).
    ``phase_correction_m`` optionally removes common errors (e.g. a base station's time-differenced
    carrier, see :mod:`companion.nav.engine`).  With ``elevation_scaling`` the carrier noise grows as
    1/sin(elevation) (multipath), floored at 10 degrees.
    """
    r_ant, v_ant, _ = antenna_state(ins, lever_arm_b)
    # the rows: satellites with a continuous carrier and a previous record (plain Python, cheap),
    # then every row's arithmetic at once over those satellites
    idx, prevs, corrs = [], [], []
    t_now = prep.t_gps
    carrier, wavelength = prep.carrier_cycles.tolist(), prep.wavelength_m.tolist()
    isfinite = math.isfinite
    for i, sat in enumerate(prep.sats):
        prev = previous.get(sat)
        if prev is None or not isfinite(carrier[i]):
            continue
        T = t_now - prev.t_gps
        if not (0.0 < T <= max_interval_s) or wavelength[i] != prev.wavelength_m:
            continue
        corr = 0.0
        if phase_correction_m is not None:
            c = phase_correction_m.get(sat)
            if c is None:
                continue
            corr = c
        idx.append(i)
        prevs.append(prev)
        corrs.append(corr)
    labels = [prep.sats[i] for i in idx]
    m = len(idx)
    if not m:
        return MeasurementBatch("tdcp", labels, np.zeros(0), np.zeros((0, layout.n)), np.zeros(0))
    # previous epoch: (t, cycles, range, clock, los rate, los x, y, z) per row
    pv = np.array([(p.t_gps, p.carrier_cycles, p.geometric_range_m, p.sat_clock_bias_m, p.los_rate_mps,
                    p.los_e[0], p.los_e[1], p.los_e[2]) for p in prevs], dtype=float)
    T = t_now - pv[:, 0]
    los_prev = pv[:, 5:8]
    d = prep.r_sat_e[idx] - r_ant
    rho = np.sqrt(row_dot(d, d))
    u = d / rho[:, None]
    dphase_m = prep.wavelength_m[idx] * (prep.carrier_cycles[idx] - pv[:, 1])
    meas = (dphase_m + prep.sat_clock_bias_m[idx] - pv[:, 3] + np.array(corrs)) / T
    pred = (rho - pv[:, 2]) / T + ins.clock_drift_mps
    u_mid = u + los_prev
    u_mid /= np.sqrt(row_dot(u_mid, u_mid))[:, None]
    H = np.zeros((m, layout.n))
    H[:, layout.vel] = -u_mid
    H[:, layout.pos] = (los_prev - u) / T[:, None]
    H[:, layout.drift] = 1.0
    # no lever-arm attitude column: see antenna_velocity_attitude_partial
    if specific_force_e is not None:
        H[:, layout.att] = (-0.5 * T)[:, None] * (u_mid @ skew(specific_force_e))
        H[:, layout.ba] = (-0.5 * T)[:, None] * (u_mid @ ins.C_b_e)
    # dt_imu: the same tag error at both epochs moved both ranges by u . v_ant of their epoch
    H[:, layout.toff] = (row_dot(u, v_ant) - pv[:, 4]) / T
    sig = np.full(m, sigma_phase_m)
    if elevation_scaling:      # math.sin: numpy's may differ from it in the last bit
        sig = sig / np.array([math.sin(max(e, _TEN_DEG_RAD)) for e in prep.elevation_rad[idx].tolist()])
    rvar = 2.0 * sig * sig / (T * T) + sigma_rate_floor_mps ** 2
    return MeasurementBatch("tdcp", labels, meas - pred, H, rvar)


def position_fix_batch(ins: InsPoint, r_fix_e: np.ndarray, cov_e: np.ndarray, lever_arm_b: np.ndarray,
                       layout=LAYOUT, autopilot_clock: bool = False) -> MeasurementBatch:
    """Loose coupling: antenna position from a GNSS fix.  ``cov_e`` is its 3x3 ECEF covariance;
    it is decorrelated (whitened) so the filter's per-row gating and diagonal noise apply.
    ``autopilot_clock``: the fix is time-tagged on the autopilot's clock (no dt_imu column)."""
    r_ant, v_ant, l_e = antenna_state(ins, lever_arm_b)
    H = np.zeros((3, layout.n))
    H[:, layout.pos] = np.eye(3)
    H[:, layout.att] = -skew(l_e)
    if not autopilot_clock:
        H[:, layout.toff] = -v_ant
    return _whitened("position", ["x", "y", "z"], r_fix_e - r_ant, H, cov_e)


def velocity_fix_batch(ins: InsPoint, v_fix_e: np.ndarray, cov_e: np.ndarray, lever_arm_b: np.ndarray,
                       layout=LAYOUT, autopilot_clock: bool = False) -> MeasurementBatch:
    """Loose coupling: antenna velocity from a GNSS fix."""
    _, v_ant, _ = antenna_state(ins, lever_arm_b)
    H = np.zeros((3, layout.n))
    H[:, layout.vel] = np.eye(3)
    if not autopilot_clock:
        H[:, layout.toff] = -antenna_acceleration(ins, lever_arm_b)
    return _whitened("velocity", ["vx", "vy", "vz"], v_fix_e - v_ant, H, cov_e)


def horizontal_velocity_fix_batch(ins: InsPoint, v_fix_e: np.ndarray, sigma_mps: float, C_n_e_: np.ndarray,
                                  lever_arm_b: np.ndarray, layout=LAYOUT,
                                  autopilot_clock: bool = False) -> MeasurementBatch:
    """Loose coupling: north and east antenna velocity only, for a fix that does not carry a
    vertical one (GPS_RAW_INT: speed over ground and course).  ``C_n_e_`` is the local NED-to-ECEF
    rotation; rows are z_ne = C_e_n[0:2] (v_fix - v_ant), each with variance sigma^2."""
    _, v_ant, _ = antenna_state(ins, lever_arm_b)
    C_e_ne = C_n_e_.T[0:2]
    H = np.zeros((2, layout.n))
    H[:, layout.vel] = C_e_ne
    if not autopilot_clock:
        H[:, layout.toff] = -C_e_ne @ antenna_acceleration(ins, lever_arm_b)
    return MeasurementBatch("velocity", ["vn", "ve"], C_e_ne @ (np.asarray(v_fix_e, float) - v_ant), H,
                            np.full(2, sigma_mps ** 2))


def _whitened(kind, labels, z, H, cov):
    L = np.linalg.cholesky(cov)
    Li = np.linalg.inv(L)
    return MeasurementBatch(kind, labels, Li @ z, Li @ H, np.ones(len(labels)))


def zero_velocity_batch(v_e: np.ndarray, sigma_mps: float, layout=LAYOUT) -> MeasurementBatch:
    """ZUPT (seed 002's ground phases): the vehicle is at rest, so the true velocity is zero."""
    H = np.zeros((3, layout.n))
    H[:, layout.vel] = np.eye(3)
    return MeasurementBatch("zupt", ["vx", "vy", "vz"], -np.asarray(v_e, float), H, np.full(3, sigma_mps ** 2))


def zero_rate_batch(omega_meas_b: np.ndarray, C_b_e: np.ndarray, b_g: np.ndarray, sigma_radps: float,
                    layout=LAYOUT) -> MeasurementBatch:
    """ZARU: at rest the gyros measure the earth rate plus their bias, so the mean raw rate over a
    still window observes the gyro bias directly (heading drift of a MEMS gyro stops on the ground)."""
    earth_b = C_b_e.T @ np.array([0.0, 0.0, OMEGA_IE_RADPS])
    H = np.zeros((3, layout.n))
    H[:, layout.bg] = np.eye(3)
    z = np.asarray(omega_meas_b, float) - earth_b - b_g
    return MeasurementBatch("zaru", ["wx", "wy", "wz"], z, H, np.full(3, sigma_radps ** 2))


def nhc_batch(v_e: np.ndarray, C_b_e: np.ndarray, sigma_lateral_mps: float, sigma_vertical_mps: float,
              layout=LAYOUT) -> MeasurementBatch:
    """Non-holonomic constraint (seed 002): a land vehicle does not move sideways or vertically in
    its own body frame, z = [v_y^b, v_z^b] = 0.  With v_b = C^T v and C(true) = (I + [psi x]) C:
    dv_b = C^T dv + C^T [v x] psi."""
    Ct = C_b_e.T
    v_b = Ct @ v_e
    H = np.zeros((2, layout.n))
    H[:, layout.vel] = Ct[1:3]
    H[:, layout.att] = (Ct @ skew(v_e))[1:3]
    return MeasurementBatch("nhc", ["v_lateral", "v_vertical"], -v_b[1:3], H,
                            np.array([sigma_lateral_mps ** 2, sigma_vertical_mps ** 2]))


def _euler_of(C_b_e: np.ndarray, C_e_n: np.ndarray) -> np.ndarray:
    C = C_e_n @ C_b_e
    return np.array([math.atan2(C[2, 1], C[2, 2]), -math.asin(max(-1.0, min(1.0, C[2, 0]))),
                     math.atan2(C[1, 0], C[0, 0])])


def attitude_batch(C_b_e: np.ndarray, C_n_e_: np.ndarray, meas, layout=LAYOUT,
                   rate_e: np.ndarray | None = None) -> MeasurementBatch:
    """Euler angles from a multi-antenna GNSS receiver (seed 003).  The Jacobian of the Euler angles
    with respect to the misalignment psi (the relation between Euler-angle errors and the platform
    misalignment) is evaluated by central differences of the exact Euler map, which stays correct
    at any attitude short of pitch +-90 deg.  ``rate_e`` (:func:`attitude_rate_e`) gives the dt_imu
    column -H_psi rate_e; None (a measurement on the autopilot's clock) gives none."""
    from .earth import rotation_from_rotvec

    C_e_n = C_n_e_.T
    e0 = _euler_of(C_b_e, C_e_n)
    J = np.empty((3, 3))
    h = 1e-6
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        ep = _euler_of(rotation_from_rotvec(d) @ C_b_e, C_e_n)
        em = _euler_of(rotation_from_rotvec(-d) @ C_b_e, C_e_n)
        J[:, j] = _wrap_pi(ep - em) / (2 * h)
    values = [(0, "roll", meas.roll_rad, meas.sigma_roll_rad), (1, "pitch", meas.pitch_rad, meas.sigma_pitch_rad),
              (2, "heading", meas.heading_rad, meas.sigma_heading_rad)]
    rows = [(i, name, v, s) for i, name, v, s in values if math.isfinite(v)]
    H = np.zeros((len(rows), layout.n))
    z = np.empty(len(rows))
    r = np.empty(len(rows))
    for k, (i, _, v, s) in enumerate(rows):
        H[k, layout.att] = J[i]
        if rate_e is not None:
            H[k, layout.toff] = -J[i] @ rate_e
        z[k] = _wrap_pi(np.array([v - e0[i]]))[0]
        r[k] = s * s
    return MeasurementBatch("attitude", [name for _, name, _, _ in rows], z, H, r)


def baseline_batch(C_b_e: np.ndarray, C_n_e_: np.ndarray, meas, baseline_b_m: np.ndarray,
                   layout=LAYOUT, rate_e: np.ndarray | None = None) -> MeasurementBatch:
    """Moving-baseline vector of a dual-antenna receiver (UBX NAV-RELPOSNED): the NED vector from
    the moving-base antenna to the rover antenna, predicted as ``C_e_n C_b_e b`` with the body
    vector ``b`` of the installation.  It observes the heading (and the tilt about the axis
    perpendicular to it) at any attitude, whatever direction the antennas are mounted in -- a
    heading-only measurement with an offset is exact only for a baseline along body x or a level
    vehicle.  Jacobian w.r.t. the misalignment by central differences, as :func:`attitude_batch`;
    ``rate_e`` as there (NAV-RELPOSNED is tagged with GPS time)."""
    from .earth import rotation_from_rotvec

    C_e_n = C_n_e_.T
    b = np.asarray(baseline_b_m, float)
    pred = C_e_n @ C_b_e @ b
    H = np.zeros((3, layout.n))
    h = 1e-6
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        H[:, layout.att.start + j] = (C_e_n @ rotation_from_rotvec(d) @ C_b_e @ b
                                      - C_e_n @ rotation_from_rotvec(-d) @ C_b_e @ b) / (2 * h)
    if rate_e is not None:
        H[:, layout.toff] = -H[:, layout.att] @ rate_e
    z = np.asarray(meas.rel_pos_ned_m, float) - pred
    r = np.maximum(np.asarray(meas.sigma_ned_m, float), 1e-3) ** 2
    return MeasurementBatch("baseline", ["baseline N", "baseline E", "baseline D"], z, H, r)


def _wrap_pi(a: np.ndarray) -> np.ndarray:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class LatencyTransition:
    """The INS error dynamics over a measurement's latency ``latency_s`` = (current IMU time) -
    (the time the measurement was predicted at), to first order: x_then = (I - F latency) x_now
    with the core of the filter's F (position <- velocity, velocity <- attitude -[f x] and
    accelerometer bias -C, attitude <- gyro bias -C, clock <- drift).

    The engine keeps one error state, at the current IMU time, and corrects the nominal state
    there.  A GNSS epoch arrives 0.1-0.25 s after its time (receiver output, corrections
    waited for); its rows see the errors of *then*.  Taking those as the errors of now was
    harmless with a well-known attitude, but after an initialisation in flight (heading
    uncertain by degrees, tilt by 2, biases unknown) the velocity error changes by f x psi over
    the latency -- 0.05 m/s at 2 deg of tilt and 0.15 s, four TDCP sigmas -- and the TDCP rows
    then pushed the heading and the gyro bias 4-5 sigma the wrong way (the in-flight start
    without ATTITUDE wandered 20-60 deg within 25 s; tests/test_inflight_init.py)."""

    latency_s: float
    specific_force_e: np.ndarray
    C_b_e: np.ndarray

    def rows_of_now(self, H: np.ndarray, layout=LAYOUT) -> np.ndarray:
        """Measurement rows H (in the errors at the measurement's time) as rows in the errors
        now: H (I - F latency)."""
        L = layout
        d = self.latency_s
        out = H.copy()
        out[:, L.vel] -= d * H[:, L.pos]
        out[:, L.att] += d * (H[:, L.vel] @ skew(self.specific_force_e))
        out[:, L.ba] += d * (H[:, L.vel] @ self.C_b_e)
        out[:, L.bg] += d * (H[:, L.att] @ self.C_b_e)
        out[:, L.drift] -= d * H[:, L.clk]
        return out

    def correction_then(self, dx: np.ndarray, layout=LAYOUT) -> np.ndarray:
        """A correction of the errors now, referred back to the measurement's time: (I - F latency) dx."""
        L = layout
        d = self.latency_s
        out = dx.copy()
        out[L.pos] -= d * dx[L.vel]
        out[L.vel] += d * (skew(self.specific_force_e) @ dx[L.att] + self.C_b_e @ dx[L.ba])
        out[L.att] += d * (self.C_b_e @ dx[L.bg])
        out[L.clk] -= d * dx[L.drift]
        return out


def single_difference(batch: MeasurementBatch, ref_label: str) -> MeasurementBatch:
    """Between-satellite single differences (seed 004): every row minus the reference satellite's.
    The receiver clock bias and drift columns cancel exactly, so no clock state is needed.  The
    differenced noise is correlated through the reference (R = D diag(r) D^T); it is whitened so the
    filter's per-row gating and diagonal noise still apply (row k of the result then mixes rows 1..k)."""
    labels = list(batch.labels)
    if ref_label not in labels or len(labels) < 2:
        return MeasurementBatch(batch.kind + "_sd", [], np.zeros(0), np.zeros((0, batch.H.shape[1])), np.zeros(0))
    ref = labels.index(ref_label)
    others = [i for i in range(len(labels)) if i != ref]
    z = batch.z[others] - batch.z[ref]
    H = batch.H[others] - batch.H[ref]
    R = np.diag(batch.r_var[others]) + batch.r_var[ref]
    return _whitened(batch.kind + "_sd", [f"{labels[i]}-{ref_label}" for i in others], z, H, R)
