"""Smooth truth trajectories in an earth-fixed local tangent frame ``t`` (NED axes at the origin).

A trajectory gives, for times ``t_rel`` in seconds since its start (vectorised over arrays):

* ``velocity_t(t_rel)`` -> (N, 3): velocity w.r.t. the earth, tangent-frame NED axes, m/s;
* ``attitude_t(t_rel)`` -> (N, 3, 3): body (FRD) to tangent-frame rotation ``C_b_t``.

Position is *not* a trajectory output: the simulator integrates the velocity with the
mechanization's trapezoid rule, so that an error-free IMU reproduces the truth to rounding.
The tangent frame is earth-fixed (origin ``origin_llh``), so ``v_e = C_t_e v_t`` and
``C_b_e = C_t_e C_b_t`` with ``C_t_e = C_n_e(lat0, lon0)``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# 8-point Gauss-Legendre nodes/weights on [0, 1]
_GL_X, _GL_W = np.polynomial.legendre.leggauss(8)
_GL_X = 0.5 * (_GL_X + 1.0)
_GL_W = 0.5 * _GL_W


def euler_to_dcm_vec(roll, pitch, yaw) -> np.ndarray:
    """Vectorised ZYX Euler angles -> C_b_n, shape (N, 3, 3) (same formula as earth.euler_to_dcm)."""
    roll, pitch, yaw = np.broadcast_arrays(np.asarray(roll, float), np.asarray(pitch, float),
                                           np.asarray(yaw, float))
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    C = np.empty(roll.shape + (3, 3))
    C[..., 0, 0] = cp * cy
    C[..., 0, 1] = -cr * sy + sr * sp * cy
    C[..., 0, 2] = sr * sy + cr * sp * cy
    C[..., 1, 0] = cp * sy
    C[..., 1, 1] = cr * cy + sr * sp * sy
    C[..., 1, 2] = -sr * cy + cr * sp * sy
    C[..., 2, 0] = -sp
    C[..., 2, 1] = sr * cp
    C[..., 2, 2] = cr * cp
    return C


# ------------------------------------------------------------------------------------------
# paper (seed 000 sec 4.1)
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PaperTrajectory:
    """Seed 000 sec 4.1: start at rest, Euler angles (roll, pitch, yaw) = euler0 + euler_rates * t
    (rates of the ZYX Euler angles relative to the local tangent NED frame), and a constant
    kinematic acceleration w.r.t. the earth expressed in body axes, ``a_b``:
    dv_t/dt = C_b_t(t) a_b.  The velocity is the exact integral (8-point Gauss-Legendre per
    ``node_dt_s`` panel: rounding-level accurate for these smooth integrands)."""

    origin_llh: tuple[float, float, float]          # lat rad, lon rad, h m
    duration_s: float
    a_b_mps2: tuple[float, float, float]
    euler_rates_radps: tuple[float, float, float]   # roll, pitch, yaw rates
    euler0_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)
    node_dt_s: float = 0.01
    _cache: dict = field(default_factory=dict, compare=False, repr=False)

    def attitude_t(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        e0, w = self.euler0_rad, self.euler_rates_radps
        return euler_to_dcm_vec(e0[0] + w[0] * t, e0[1] + w[1] * t, e0[2] + w[2] * t)

    def _accel_t(self, t) -> np.ndarray:
        return self.attitude_t(t) @ np.asarray(self.a_b_mps2, float)

    def _nodes(self):
        if "v" not in self._cache:
            h = self.node_dt_s
            n = int(math.ceil((self.duration_s + 2.0) / h)) + 1
            tk = np.arange(n) * h
            pts = tk[:-1, None] + h * _GL_X[None, :]                       # (n-1, 8)
            a = self._accel_t(pts.ravel()).reshape(pts.shape + (3,))
            dv = h * np.einsum("j,ijk->ik", _GL_W, a)
            v = np.zeros((n, 3))
            v[1:] = np.cumsum(dv, axis=0)
            self._cache["t"], self._cache["v"] = tk, v
        return self._cache["t"], self._cache["v"]

    def velocity_t(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        tk, vk = self._nodes()
        h = self.node_dt_s
        k = np.clip(np.floor(t / h + 1e-9).astype(int), 0, len(tk) - 2)
        frac = t - tk[k]
        pts = tk[k][:, None] + frac[:, None] * _GL_X[None, :]
        a = self._accel_t(pts.ravel()).reshape(pts.shape + (3,))
        return vk[k] + frac[:, None] * np.einsum("j,ijk->ik", _GL_W, a)


# ------------------------------------------------------------------------------------------
# uav survey flight
# ------------------------------------------------------------------------------------------
def _smootherstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _smootherstep_d(x):
    inside = (x > 0.0) & (x < 1.0)
    xc = np.clip(x, 0.0, 1.0)
    return np.where(inside, 30.0 * xc * xc * (1.0 - xc) ** 2, 0.0)


def _smootherstep_int(x):
    """Integral of the smootherstep from 0 to x (x may exceed 1)."""
    xc = np.clip(x, 0.0, 1.0)
    base = xc ** 4 * (xc * (xc - 3.0) + 2.5)
    return base + np.maximum(x - 1.0, 0.0)


@dataclass(frozen=True)
class SmoothProfile:
    """Scalar profile: value0 + sum of smootherstep (6x^5-15x^4+10x^3) steps (t_start, duration, delta).
    C2-continuous, so quantities derived from its derivative stay C1."""

    value0: float
    steps: tuple[tuple[float, float, float], ...]

    def value(self, t):
        t = np.asarray(t, float)
        out = np.full(t.shape, self.value0)
        for t0, d, dv in self.steps:
            out = out + dv * _smootherstep((t - t0) / d)
        return out

    def rate(self, t):
        t = np.asarray(t, float)
        out = np.zeros(t.shape)
        for t0, d, dv in self.steps:
            out = out + dv / d * _smootherstep_d((t - t0) / d)
        return out

    def integral(self, t):
        """Integral from 0 to t (all steps must start at t >= 0)."""
        t = np.asarray(t, float)
        out = self.value0 * t
        for t0, d, dv in self.steps:
            out = out + dv * d * _smootherstep_int((t - t0) / d)
        return out


@dataclass(frozen=True)
class SurveyTrajectory:
    """Multirotor survey flight built from C2-smooth profiles of ground speed V, heading rate
    and down velocity:  v_t = (V cos psi, V sin psi, v_d), psi = psi0 + integral(psi_dot).
    Attitude: yaw = psi (track heading), thrust axis (-z_b) along a - g + k_drag v (a multirotor
    tilts into its acceleration and against linear drag k_drag), which makes turns coordinated.
    Acceleration and angular rate are continuous."""

    origin_llh: tuple[float, float, float]
    duration_s: float
    speed: SmoothProfile
    heading_rate: SmoothProfile
    v_down: SmoothProfile
    heading0_rad: float
    drag_per_s: float = 0.25
    g_mps2: float = 9.80
    events: tuple[tuple[str, float, float], ...] = ()   # (name, t_rel start, t_rel end)

    def heading(self, t):
        return self.heading0_rad + self.heading_rate.integral(t)

    def velocity_t(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        V, psi = self.speed.value(t), self.heading(t)
        return np.stack([V * np.cos(psi), V * np.sin(psi), self.v_down.value(t)], axis=-1)

    def accel_t(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        V, Vd = self.speed.value(t), self.speed.rate(t)
        psi, psid = self.heading(t), self.heading_rate.value(t)
        c, s = np.cos(psi), np.sin(psi)
        return np.stack([Vd * c - V * psid * s, Vd * s + V * psid * c, self.v_down.rate(t)], axis=-1)

    def attitude_t(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        thrust = self.accel_t(t) + self.drag_per_s * self.velocity_t(t)
        thrust[:, 2] -= self.g_mps2
        z_b = -thrust / np.linalg.norm(thrust, axis=1, keepdims=True)
        psi = self.heading(t)
        x_h = np.stack([np.cos(psi), np.sin(psi), np.zeros_like(psi)], axis=-1)
        y_b = np.cross(z_b, x_h)
        y_b /= np.linalg.norm(y_b, axis=1, keepdims=True)
        x_b = np.cross(y_b, z_b)
        return np.stack([x_b, y_b, z_b], axis=-1)   # columns = body axes in t-frame


def survey_flight(origin_llh, heading0_rad: float = 0.3, cruise_mps: float = 9.0,
                  turn_rate_radps: float = 0.45, leg_s: float = 24.0, n_legs: int = 6,
                  climb_m: float = 50.0) -> SurveyTrajectory:
    """The 'uav' flight (times in s from start; all ramps are smootherstep):

    rest 0-8; climb 50 m at 2.5 m/s (8-31); accelerate to 9 m/s (32-38); 6 survey legs of 24 s
    (216 m) joined by 5 alternating 180-degree coordinated turns (0.45 rad/s peak, radius ~20 m,
    bank ~22 deg, 2-s turn-rate ramps); decelerate (227-233); hover 233-263; descend 50 m at
    2 m/s (263-291); rest to 300.
    """
    climb_rate, ramp_v = 2.5, 3.0
    t_climb = 8.0
    hold = climb_m / climb_rate                       # symmetric ramps: gain = rate * (t_stop - t_start)
    v_down_steps = [(t_climb, ramp_v, -climb_rate), (t_climb + hold, ramp_v, climb_rate)]
    t_acc, ramp_acc = t_climb + hold + ramp_v + 1.0, 6.0
    speed_steps = [(t_acc, ramp_acc, cruise_mps)]
    ramp_turn = 2.0
    turn_hold = math.pi / turn_rate_radps - ramp_turn
    turn_len = ramp_turn + turn_hold + ramp_turn
    events = [("rest", 0.0, t_climb), ("climb", t_climb, t_climb + hold + ramp_v),
              ("accelerate", t_acc, t_acc + ramp_acc)]
    t = t_acc + ramp_acc
    hr_steps = []
    for k in range(n_legs):
        events.append((f"leg{k + 1}", t, t + leg_s))
        t += leg_s
        if k < n_legs - 1:
            sgn = 1.0 if k % 2 == 0 else -1.0
            hr_steps.append((t, ramp_turn, sgn * turn_rate_radps))
            hr_steps.append((t + ramp_turn + turn_hold, ramp_turn, -sgn * turn_rate_radps))
            events.append((f"turn{k + 1}", t, t + turn_len))
            t += turn_len
    speed_steps.append((t, ramp_acc, -cruise_mps))
    events.append(("decelerate", t, t + ramp_acc))
    t += ramp_acc
    events.append(("hover", t, t + 30.0))
    t += 30.0
    descent_rate = 2.0
    hold_d = climb_m / descent_rate
    v_down_steps += [(t, ramp_v, descent_rate), (t + hold_d, ramp_v, -descent_rate)]
    events.append(("descend", t, t + hold_d + ramp_v))
    t += hold_d + ramp_v
    duration = max(300.0, math.ceil(t + 5.0))
    events.append(("landed", t, duration))
    return SurveyTrajectory(origin_llh=tuple(origin_llh), duration_s=duration,
                            speed=SmoothProfile(0.0, tuple(speed_steps)),
                            heading_rate=SmoothProfile(0.0, tuple(hr_steps)),
                            v_down=SmoothProfile(0.0, tuple(v_down_steps)),
                            heading0_rad=heading0_rad, events=tuple(events))


# ------------------------------------------------------------------------------------------
# ground vehicle (seed 002: non-holonomic constraint)
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class GroundTrajectory:
    """A car on a road, from C2-smooth profiles (all times t_rel, s):

    * speed V along the body x axis, heading psi = psi0 + integral(psi_dot);
    * pitch = road grade angle theta (the body x axis follows the road, so the velocity has
      no body-vertical component: v_t = V (cos theta cos psi, cos theta sin psi, -sin theta));
    * roll = road crossfall (bank) + suspension roll outward in turns,
      ``-roll_per_lat_accel * a_lat`` (a_lat = V psi_dot; roll is a rotation about the velocity
      axis, so it does not break the constraint);
    * body lateral velocity v_y = side-slip ``-slip_per_lat_accel * a_lat * ...`` (the rear drifts
      out: a slip angle proportional to the lateral acceleration, beta = -k a_lat, v_y = V beta)
      plus an optional injected skid profile ``skid`` (m/s, body y), added as v_y C_b_t[:, 1].

    With ``slip_per_lat_accel = 0`` and no skid the body velocity is exactly (V, 0, 0): the
    non-holonomic constraint holds for the truth."""

    origin_llh: tuple[float, float, float]
    duration_s: float
    speed: SmoothProfile
    heading_rate: SmoothProfile
    grade: SmoothProfile                     # pitch = road grade angle, rad
    bank: SmoothProfile                      # road crossfall, rad
    heading0_rad: float
    roll_per_lat_accel: float = 0.0          # rad per m/s^2 (suspension roll, outward)
    slip_per_lat_accel: float = 0.0          # rad per m/s^2 (side-slip angle)
    skid: SmoothProfile = SmoothProfile(0.0, ())
    events: tuple[tuple[str, float, float], ...] = ()

    def heading(self, t):
        return self.heading0_rad + self.heading_rate.integral(t)

    def _angles(self, t):
        V = self.speed.value(t)
        a_lat = V * self.heading_rate.value(t)
        roll = self.bank.value(t) - self.roll_per_lat_accel * a_lat
        return V, a_lat, roll, self.grade.value(t), self.heading(t)

    def lateral_velocity_b(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        V, a_lat, _, _, _ = self._angles(t)
        return -self.slip_per_lat_accel * a_lat * V + self.skid.value(t)

    def attitude_t(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        _, _, roll, pitch, psi = self._angles(t)
        return euler_to_dcm_vec(roll, pitch, psi)

    def velocity_t(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        V, a_lat, roll, pitch, psi = self._angles(t)
        C = euler_to_dcm_vec(roll, pitch, psi)
        v_y = -self.slip_per_lat_accel * a_lat * V + self.skid.value(t)
        return V[:, None] * C[:, :, 0] + v_y[:, None] * C[:, :, 1]


class _Route:
    """Builds speed / heading-rate smootherstep steps along a time cursor."""

    def __init__(self):
        self.t = 0.0
        self.v = 0.0
        self.speed_steps: list = []
        self.hr_steps: list = []
        self.events: list = []

    def hold(self, name: str, dur: float):
        self.events.append((name, self.t, self.t + dur))
        self.t += dur

    def speed_to(self, v: float, dur: float, name: str | None = None):
        self.speed_steps.append((self.t, dur, v - self.v))
        self.events.append((name or ("accelerate" if v > self.v else "brake"), self.t, self.t + dur))
        self.v = v
        self.t += dur

    def turn(self, angle_deg: float, rate_dps: float, ramp_s: float = 1.5, name: str = "turn"):
        """Turn by angle_deg (+ = right, NED yaw) at a peak rate; the angle is exact."""
        a = math.radians(abs(angle_deg))
        w = math.radians(rate_dps) * (1.0 if angle_deg > 0 else -1.0)
        hold = a / abs(w) - ramp_s
        assert hold >= 0.0, "turn too short for its ramps"
        self.hr_steps.append((self.t, ramp_s, w))
        self.hr_steps.append((self.t + ramp_s + hold, ramp_s, -w))
        dur = 2.0 * ramp_s + hold
        self.events.append((name, self.t, self.t + dur))
        self.t += dur


def road_drive(origin_llh, heading0_rad: float = math.radians(30.0), skid_at_s: float | None = None,
               skid_mps: float = 2.0, skid_s: float = 3.0) -> GroundTrajectory:
    """The 'nhc' drive (~10 min, speeds 5-20 m/s; event times in ``events``):

    rest 15 s; accelerate to 12 m/s; straight; brake to 7 m/s; 90-deg right turn (17 deg/s,
    radius ~24 m); accelerate to 15; straight; brake to 7; roundabout (enter 30 deg right,
    circulate 210 deg left at 15 deg/s, radius ~27 m, exit 30 deg right); accelerate to 18;
    straight over a hill; brake to a stop; stop 20 s (ZUPT); accelerate to 10; 90-deg left turn;
    accelerate to 20; long straight; brake to 10; gentle 45-deg right curve; straight; 90-deg
    right turn at 8 m/s; accelerate to 14; straight; brake to a stop; rest.

    Road profile: grade steps between -3 and +3 deg (pitch), crossfall between -1.5 and +1.5 deg;
    suspension roll 0.4 deg per m/s^2 of lateral acceleration (outward; ~4 deg/g, a passenger
    car); side-slip angle 0.1 deg per m/s^2 (at 2 m/s^2 and 7 m/s: 0.025 m/s sideways, well
    inside the constraint's 0.1 m/s noise).  Optional skid: a body-lateral velocity ``skid_mps``
    held for ``skid_s`` (0.5-s smootherstep ramps on each side) starting at ``skid_at_s``.
    """
    r = _Route()
    r.hold("rest", 15.0)
    r.speed_to(12.0, 8.0)
    r.hold("straight1", 40.0)
    r.speed_to(7.0, 5.0)
    r.turn(90.0, 17.0, name="turn1 (90 right)")
    r.speed_to(15.0, 8.0)
    r.hold("straight2", 55.0)
    r.speed_to(7.0, 6.0)
    r.turn(30.0, 12.0, name="roundabout entry")
    r.turn(-210.0, 15.0, name="roundabout")
    r.turn(30.0, 12.0, name="roundabout exit")
    r.speed_to(18.0, 10.0)
    r.hold("straight3 (hill)", 60.0)
    r.speed_to(0.0, 12.0)
    r.hold("stop", 20.0)
    r.speed_to(10.0, 8.0)
    r.turn(-90.0, 15.0, name="turn2 (90 left)")
    r.speed_to(20.0, 10.0)
    r.hold("straight4", 90.0)
    r.speed_to(10.0, 6.0)
    r.turn(45.0, 6.0, name="curve (45 right)")
    r.hold("straight5", 40.0)
    r.speed_to(8.0, 4.0)
    r.turn(90.0, 17.0, name="turn3 (90 right)")
    r.speed_to(14.0, 8.0)
    r.hold("straight6", 75.0)
    r.speed_to(5.0, 6.0)
    r.turn(-90.0, 20.0, name="turn4 (90 left)")
    r.hold("straight7", 35.0)
    r.speed_to(0.0, 5.0)
    r.hold("rest", 10.0)
    duration = math.ceil(r.t)
    deg = math.radians(1.0)
    # grade / crossfall changes never fall in the rest or stop phases
    grade = SmoothProfile(0.0, ((40.0, 8.0, 1.5 * deg), (100.0, 10.0, -2.5 * deg), (185.0, 10.0, 4.0 * deg),
                                (215.0, 10.0, -6.0 * deg), (236.0, 8.0, 3.0 * deg), (300.0, 10.0, 2.0 * deg),
                                (340.0, 12.0, -3.0 * deg), (420.0, 10.0, 1.0 * deg), (470.0, 10.0, -1.5 * deg),
                                (520.0, 10.0, 1.5 * deg)))
    bank = SmoothProfile(0.0, ((35.0, 5.0, 1.0 * deg), (110.0, 5.0, -2.0 * deg), (200.0, 5.0, 1.5 * deg),
                               (300.0, 5.0, -1.5 * deg), (360.0, 6.0, 2.5 * deg), (500.0, 6.0, -1.5 * deg)))
    skid = SmoothProfile(0.0, ())
    events = list(r.events)
    if skid_at_s is not None:
        ramp = 0.5
        skid = SmoothProfile(0.0, ((skid_at_s, ramp, skid_mps), (skid_at_s + ramp + skid_s, ramp, -skid_mps)))
        events.append(("skid", skid_at_s, skid_at_s + 2 * ramp + skid_s))
    return GroundTrajectory(origin_llh=tuple(origin_llh), duration_s=float(duration),
                            speed=SmoothProfile(0.0, tuple(r.speed_steps)),
                            heading_rate=SmoothProfile(0.0, tuple(r.hr_steps)),
                            grade=grade, bank=bank, heading0_rad=heading0_rad,
                            roll_per_lat_accel=math.radians(0.4), slip_per_lat_accel=math.radians(0.1),
                            skid=skid, events=tuple(events))


# ------------------------------------------------------------------------------------------
# fixed-wing survey aircraft (seed 003: GNSS attitude)
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FixedWingTrajectory:
    """An aircraft in coordinated flight, no wind: ground speed V, heading psi (track = yaw, no
    side-slip), climb rate -v_d.  Flight-path angle gamma = atan(-v_d / V); pitch = gamma + alpha
    with the angle of attack alpha = alpha0 * load factor (n = 1/cos(roll)); roll = the
    coordinated bank atan(V psi_dot / g)."""

    origin_llh: tuple[float, float, float]
    duration_s: float
    speed: SmoothProfile
    heading_rate: SmoothProfile
    v_down: SmoothProfile
    heading0_rad: float
    alpha0_rad: float = math.radians(2.5)
    g_mps2: float = 9.80
    events: tuple[tuple[str, float, float], ...] = ()

    def heading(self, t):
        return self.heading0_rad + self.heading_rate.integral(t)

    def velocity_t(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        V, psi = self.speed.value(t), self.heading(t)
        return np.stack([V * np.cos(psi), V * np.sin(psi), self.v_down.value(t)], axis=-1)

    def attitude_t(self, t_rel) -> np.ndarray:
        t = np.atleast_1d(np.asarray(t_rel, float))
        V, psi = self.speed.value(t), self.heading(t)
        roll = np.arctan(V * self.heading_rate.value(t) / self.g_mps2)
        gamma = np.arctan2(-self.v_down.value(t), V)
        pitch = gamma + self.alpha0_rad / np.cos(roll)
        return euler_to_dcm_vec(roll, pitch, psi)


def survey_aircraft(origin_llh, heading0_rad: float = math.radians(80.0)) -> FixedWingTrajectory:
    """The 'attitude' flight, 10 min (seed 003 flew 2.6 h; shorter here to keep a Monte Carlo run
    at a few seconds): a light survey aircraft at 55-65 m/s.

    straight 40 s; climb 300 m at 5 m/s; 180-deg standard-rate turn right (3 deg/s, bank ~17 deg);
    survey line 90 s; 180-deg turn left; survey line 90 s with a 150-m descent; 270-deg turn right at
    4 deg/s (bank ~23 deg) while speeding up to 65 m/s; line 60 s; 90-deg turn left; rest of the time
    straight and level.  All profiles are smootherstep steps (C2)."""
    r = _Route()
    r.v = 55.0
    vd_steps = []
    r.hold("straight", 40.0)
    vd_steps += [(r.t, 5.0, -5.0), (r.t + 60.0, 5.0, 5.0)]
    r.hold("climb 300 m", 65.0)
    r.hold("level", 10.0)
    r.turn(180.0, 3.0, ramp_s=4.0, name="turn1 (180 right)")
    r.hold("line1", 90.0)
    r.turn(-180.0, 3.0, ramp_s=4.0, name="turn2 (180 left)")
    vd_steps += [(r.t + 20.0, 5.0, 3.0), (r.t + 70.0, 5.0, -3.0)]
    r.hold("line2 (descent 150 m)", 90.0)
    r.speed_steps.append((r.t, 20.0, 10.0))
    r.turn(270.0, 4.0, ramp_s=4.0, name="turn3 (270 right, speed up)")
    r.hold("line3", 60.0)
    r.turn(-90.0, 3.0, ramp_s=4.0, name="turn4 (90 left)")
    duration = 600.0
    r.hold("line4", duration - r.t)
    return FixedWingTrajectory(origin_llh=tuple(origin_llh), duration_s=duration,
                               speed=SmoothProfile(55.0, tuple(r.speed_steps)),
                               heading_rate=SmoothProfile(0.0, tuple(r.hr_steps)),
                               v_down=SmoothProfile(0.0, tuple(vd_steps)),
                               heading0_rad=heading0_rad, events=tuple(r.events))
