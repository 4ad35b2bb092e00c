"""Who vouches for the filter's heading: the yaw from motion (companion.nav.yaw_gsf) watching it.

With one antenna the heading is the state a GNSS/INS filter knows least, and a wrong one in motion
costs metres per second.  :class:`HeadingWatch` runs a Gaussian-sum yaw estimator from the first
screened IMU sample on every GNSS velocity (the SPP Doppler velocity of a rover epoch, or
GPS_RAW_INT's in loose mode) and uses it four ways:

* **initial heading** (:meth:`initial_attitude`): the autopilot's ATTITUDE yaw with
  ``mavlink.attitude_yaw_sigma_deg`` unless the settled estimator contradicts it (then that yaw is
  not used again in the run), else the estimator's own once it has settled (with its roll and
  pitch too when there is no ATTITUDE);
* **confirmation**: a heading the estimator agrees with (or an ATTITUDE heading a narrow, not yet
  converged estimator agrees with) is *confirmed*;
* **reset**: a converged estimator that disagrees beyond GSF_AGREE_SIGMAS combined sigma resets
  our heading onto it (event, counted; the filter goes on probation unless its position stayed
  GNSS-bound), except a bank restarted after a GNSS gap that is less certain than our heading;
* **injection gate** (:meth:`gate`): not injected while the estimator contradicts our heading,
  while our heading sigma exceeds ``output.max_sigma_yaw_deg`` (unless the estimator or a
  dual-antenna heading vouches), nor in horizontal motion before the heading was confirmed once
  (at rest a wrong heading costs the lever arm only).

It shares the pipeline's counters and events (the health report's keys are the pipeline's) and
reads the engine; the pipeline says when a dual-antenna heading was fused
(:meth:`trusted_heading_fused`) and when a re-initialisation happened (:meth:`note_trouble`).
"""
from __future__ import annotations

import math
from collections import Counter
from typing import Callable

import numpy as np

from .gnss.spp import spp_epoch
from .io.mavlink_codec import mavlink2
from .messages import GnssEpoch, ImuSample
from .nav.earth import C_n_e, ecef_to_geodetic, euler_to_dcm
from .nav.imu_screen import ImuFullScale, ImuScreen
from .nav.integrity import GNSS_SOURCES, POSITION_SOURCES
from .nav.yaw_gsf import YawGsf

HEADING_RESET_QUIET_S = 60.0   # a heading reset skips probation only this long after the last one or a re-init
MOTION_HOLD_S = 0.5           # the unconfirmed-heading gate stays shut this long after the last sign of motion
GSF_CONFIRM_SIGMA_RAD = math.radians(20.0)   # a yaw from motion this narrow may confirm an ATTITUDE heading
GSF_AGREE_SIGMAS = 3.0        # our heading and the yaw from motion agree within this x their combined sigma
GSF_RESET_AFTER = 1           # ... disagree at this many GNSS velocities in a row: reset our heading
                              # (the GSF's convergence took several already; at 1 Hz a wrong heading
                              # in motion costs metres per second)
TRUSTED_HEADING_MAX_AGE_S = 5.0   # a dual-antenna heading fused this recently vouches for our heading
#: a GNSS velocity this much older than the IMU's time is not fused by the yaw from motion: its
#: bank predicts the velocity at the IMU's time, and a burst of epochs delivered late (the GPS port
#: re-claimed after an outage: 4 s of them at once) converged it 125 deg off in a straight leg
GSF_MAX_VELOCITY_AGE_S = 1.0
GSF_RESTART_PROBATION_S = 30.0    # a yaw-from-motion bank restarted after a GNSS gap does not overrule
                                  # a heading more certain than its own for this long (GPS time)
SEVERITY_WARNING = mavlink2.MAV_SEVERITY_WARNING   # of its events (STATUSTEXT)


class HeadingWatch:
    """The yaw from motion beside one engine (``engine``: companion.nav.engine.NavEngine)."""

    def __init__(self, engine, *, counters: Counter, event: Callable[[int, str], None], gap_s: float,
                 elevation_mask_deg: float, attitude_yaw_sigma_deg: float, max_sigma_yaw_deg: float,
                 lever_b_m, on_attitude_yaw_distrusted: Callable[[], None] = lambda: None):
        self.engine = engine
        self.counters = counters                 # the pipeline's (its health keys)
        self._event = event
        self.gap_s = gap_s                       # IMU time step that restarts the estimator
        self.elevation_mask_rad = math.radians(elevation_mask_deg)
        self.attitude_yaw_sigma_rad = math.radians(attitude_yaw_sigma_deg)
        self.max_sigma_yaw_rad = math.radians(max_sigma_yaw_deg)
        self.lever_b = np.asarray(lever_b_m, float)   # GNSS antenna in the body frame (m): its velocity widens the sigma
        self._on_distrust = on_attitude_yaw_distrusted
        ec = engine.cfg
        self.gsf = YawGsf()
        self.screen_counters: Counter = Counter()      # its own screen: not counted twice in the engine's
        self.screen = ImuScreen(clip_fraction=ec.imu_clip_fraction, accel_jump_mps2=ec.imu_accel_jump_mps2,
                                gyro_jump_radps=ec.imu_gyro_jump_radps, window=ec.imu_median_window,
                                counters=self.screen_counters) if ec.imu_screen_enabled else None
        self._t_imu: float | None = None
        self._r_e = None                          # last SPP position of its velocities (next start)
        self._disagreements = 0
        self.heading_resets = 0
        self._gap_restarts = 0                    # the estimator's bank restarts after GNSS gaps seen so far
        self._restart_t = -math.inf               # GPS time of the last one
        self._last_trouble_t = -math.inf          # GPS time of the last heading reset or re-initialisation
        self.attitude_yaw_trusted = True          # False for the run once the yaw from motion contradicted it
        self.heading_confirmed = False            # the filter's heading came from, or agreed with, the yaw from motion
        self._t_last_motion = -math.inf           # last solution in (or starting) horizontal motion
        self.attitude_yaw_confirmed = False       # ... and a filter started on the ATTITUDE yaw agreed with it once
        self._heading_from_attitude = False       # the filter's heading was initialised from ATTITUDE
        self._last_trusted_heading_t = -math.inf  # GPS time of the last dual-antenna heading fused
        self.gate_reason = ""                     # why the gate withheld the last solution ('' = it did not)

    # ------------------------------------------------------------------ what the pipeline says
    def restart(self) -> None:
        """The autopilot rebooted: the IMU's history is void."""
        self.gsf.reset()
        self._t_imu = None

    def set_full_scale(self, full_scale: ImuFullScale) -> None:
        if self.screen is not None:
            self.screen.set_full_scale(full_scale)

    def note_trouble(self, t_gps: float) -> None:
        """A re-initialisation: a heading reset soon after it is not let off probation."""
        self._last_trouble_t = t_gps

    def trusted_heading_fused(self, t_gps: float) -> None:
        """A dual-antenna heading was fused: it vouches for ours for TRUSTED_HEADING_MAX_AGE_S."""
        self._last_trusted_heading_t = t_gps

    # ------------------------------------------------------------------ the estimator's inputs
    def imu(self, s: ImuSample) -> None:
        """Every IMU sample, screened like the engine's (its own screen)."""
        if self._t_imu is not None:
            if abs(s.t_gps - self._t_imu) > self.gap_s:
                self.gsf.reset()
                self.counters["yaw from motion restarted: IMU time jump"] += 1
            elif not s.t_gps > self._t_imu:
                return
        th, dv = s.dtheta_b.tolist(), s.dv_b.tolist()
        scr = self.screen
        if scr is not None and not scr.check(th, dv, s.dt_s, s.t_gps):
            if not scr.bridged:
                return
            th, dv = scr.dtheta_b, scr.dv_b
        self._t_imu = s.t_gps
        self.gsf.update_imu(th, dv, s.dt_s, s.t_gps)

    def epoch_velocity(self, epoch: GnssEpoch, t_imu: float | None) -> None:
        """The SPP Doppler velocity of a rover epoch (no base needed)."""
        eng = self.engine
        sol = spp_epoch(epoch, eng.ephemerides, klobuchar=eng.cfg.klobuchar, r_init_e=self._r_e,
                        elevation_mask_rad=self.elevation_mask_rad, systems=eng.cfg.systems,
                        signal=eng.cfg.pseudorange_signal)
        if sol is None or sol.v_e is None or not (np.all(np.isfinite(sol.v_e)) and math.isfinite(sol.hdop)):
            self.counters["yaw from motion: epoch without SPP velocity"] += 1
            return
        self._r_e = sol.r_e
        self.velocity(epoch.t_gps, sol.r_e, np.asarray(sol.v_e, float),
                      eng.cfg.sigma_doppler_mps * sol.hdop / math.sqrt(2.0), t_imu)

    def velocity(self, t_gps: float, r_e, v_ant_e, sigma_mps: float, t_imu: float | None) -> None:
        """One GNSS antenna velocity (ECEF) into the estimator, then our heading checked against
        it.  The lever-arm velocity (rate x lever arm) and the fix's age (times the acceleration)
        are not modelled: they widen the sigma."""
        g = self.gsf
        lat, lon, _ = ecef_to_geodetic(r_e)
        Cne = C_n_e(lat, lon)
        v_n = Cne.T @ v_ant_e
        lag = max(0.0, t_imu - t_gps) if t_imu is not None else 0.0
        if lag > GSF_MAX_VELOCITY_AGE_S or t_gps <= g.t_last_vel:
            self.counters["yaw from motion: velocity too old or out of order (not fused)"] += 1
            return
        extra = float(np.linalg.norm(g.omega_b_radps)) * float(np.linalg.norm(self.lever_b)) \
            + g.kinematic_accel_mps2 * lag
        sig = math.hypot(sigma_mps, extra)
        if not g.fuse_velocity(t_gps, v_n[:2], sig):
            return
        self.counters["yaw from motion: velocities fused"] += 1
        self._check_heading(v_n, sig, Cne)

    # ------------------------------------------------------------------ our heading against it
    def disagrees(self, heading_rad: float, sigma_rad: float) -> bool:
        g = self.gsf
        d = (g.yaw_rad - heading_rad + math.pi) % (2.0 * math.pi) - math.pi
        return abs(d) > GSF_AGREE_SIGMAS * math.hypot(sigma_rad, g.yaw_sigma_rad)

    def _check_heading(self, v_ant_n, sigma_mps: float, Cne) -> None:
        """Converged yaw from motion against our heading: a disagreement beyond their combined
        uncertainty at GSF_RESET_AFTER velocities in a row resets our heading onto it (a linear
        update cannot turn a heading by tens of degrees), its velocity onto the GNSS one; the
        autopilot's ATTITUDE yaw is not trusted again in this run."""
        g, eng = self.gsf, self.engine
        restarts = int(getattr(g, "gap_restarts", 0))
        if restarts != self._gap_restarts:
            self._gap_restarts = restarts
            self._restart_t = eng.t_gps if eng.initialized else -math.inf
        if not (eng.initialized and g.converged):
            self._disagreements = 0
            self._confirm_attitude_heading()
            return
        heading, sigma = eng.heading_and_sigma()
        unknown = sigma > self.max_sigma_yaw_rad and g.yaw_sigma_rad < sigma     # started without a heading
        if not (unknown or self.disagrees(heading, sigma)):
            self._disagreements = 0
            self.heading_confirmed = True
            if self._heading_from_attitude and self.attitude_yaw_trusted:
                self.attitude_yaw_confirmed = True
            return
        if self.restarted_and_less_certain(sigma):
            # the bank started over after a GNSS gap and converged again within seconds: a heading
            # it has not yet watched for long, against ours that is more certain and was fused
            # through the gap (rtk flight, 30-s outage: a restarted bank converged 164 deg off at
            # 9.5 deg sigma and its reset of a 1-deg heading brought a 0.26-m wrong RTK fix)
            self._disagreements = 0
            self.counters["heading reset refused: yaw from motion restarted recently, less certain"] += 1
            return
        self._disagreements += 1
        if self._disagreements < GSF_RESET_AFTER:
            return
        self._disagreements = 0
        self._reset_heading(v_ant_n, sigma_mps, Cne, heading)

    def _reset_heading(self, v_ant_n, sigma_mps: float, Cne, heading: float) -> None:
        g, eng = self.gsf, self.engine
        delta = (g.yaw_rad - heading + math.pi) % (2.0 * math.pi) - math.pi
        # horizontal velocity from the GNSS, vertical kept (GPS_RAW_INT has none)
        cov_v_n = Cne.T @ eng.kf.P[eng.layout.vel, eng.layout.vel] @ Cne
        v_n = np.array([v_ant_n[0], v_ant_n[1], float((Cne.T @ eng.v_e)[2])])
        cov_n = np.diag([sigma_mps ** 2, sigma_mps ** 2, max(float(cov_v_n[2, 2]), 1e-4)])
        eng.reset_heading(delta, g.yaw_sigma_rad, v_imu_e=Cne @ v_n, cov_v_e=Cne @ cov_n @ Cne.T)
        # the position was integrated along the wrong heading too: on probation (status
        # 'converging', not injected) until a consistent window of GNSS, else a re-init from GNSS --
        # unless its GNSS rows kept being fused (a 25-deg heading error in a hover cost the velocity
        # and the lever arm, not the GNSS-bound position; a 5-s pause put PX4 into failsafe) ...
        # -- once: a reset within HEADING_RESET_QUIET_S of another or of a re-initialisation means
        # a heading that keeps running away (a gyro fault below every screen: 6 m injected after
        # its re-init without this), whose position is not to be trusted either
        repeated = eng.t_gps - self._last_trouble_t < HEADING_RESET_QUIET_S
        self._last_trouble_t = eng.t_gps
        probation = eng.cfg.integrity_enabled and (repeated or not self._position_gnss_bound())
        eng.aid.clear_windows()
        eng.integrity.restart(eng.t_gps, probation)
        if not probation:
            self.counters["heading reset without probation (position GNSS-bound)"] += 1
        self.heading_resets += 1
        self.counters["heading reset onto the yaw from motion"] += 1
        self.heading_confirmed = True
        if self._heading_from_attitude:
            self._distrust_attitude_yaw()
            self._heading_from_attitude = False
        self._event(SEVERITY_WARNING, f"heading reset {math.degrees(delta):+.0f} deg onto the yaw from "
                                      f"motion (sigma {math.degrees(g.yaw_sigma_rad):.1f} deg)")

    def restarted_and_less_certain(self, our_sigma_rad: float) -> bool:
        """The yaw from motion restarted after a GNSS gap less than GSF_RESTART_PROBATION_S ago
        and is less certain than our heading: it does not reset ours.  While the two disagree
        nothing is injected all the same (which one is wrong is not known: after the fault
        matrix's 60-s outage, letting ours through put 46 estimates beyond their protection level)."""
        return (our_sigma_rad < self.gsf.yaw_sigma_rad
                and self.engine.t_gps - self._restart_t < GSF_RESTART_PROBATION_S)

    def _confirm_attitude_heading(self) -> None:
        """A heading taken from the autopilot's ATTITUDE is confirmed in motion by a yaw from motion
        that is not converged yet (sigma below GSF_CONFIRM_SIGMA_RAD after one velocity in motion,
        not 10 deg after two) but agrees with it: two independent sources agreeing.  A 180-deg wrong
        autopilot heading disagrees with any bank that narrow.  Waiting for convergence withheld
        the output for 1.3 s at the start of PX4 SIH's first leg (its 0.4-m/s velocity sigma
        slows the bank down) and EKF2 dropped our position."""
        g, eng = self.gsf, self.engine
        if self.heading_confirmed or not (self._heading_from_attitude and self.attitude_yaw_trusted):
            return
        if g.n_moving_fusions < 1 or g.yaw_sigma_rad > GSF_CONFIRM_SIGMA_RAD:
            return
        heading, sigma = eng.heading_and_sigma()
        if sigma <= self.max_sigma_yaw_rad and not self.disagrees(heading, sigma):
            self.heading_confirmed = True
            self.counters["heading from ATTITUDE confirmed by the yaw from motion (not yet converged)"] += 1

    def _position_gnss_bound(self) -> bool:
        """Over the last integrity window a position source (pseudoranges, GNSS fixes) was fused
        at least ``min_updates`` times and no GNSS source rejected more than a probation allows
        (a 180-deg heading in motion left the fused pseudoranges 10-20 m off at a mean NIS of 0.2:
        their inflated variance hides it, the TDCP rows, half rejected, do not)."""
        eng = self.engine
        lim = eng.integrity.limits
        bound = False
        for src in GNSS_SOURCES:
            w = eng.aid.window(src, eng.t_gps)
            if w.n_updates == 0:
                continue
            if w.rejected_fraction > lim.probation_max_rejected_fraction:
                return False
            bound = bound or (src in POSITION_SOURCES and w.n_updates >= lim.min_updates)
        return bound

    def _distrust_attitude_yaw(self) -> None:
        if self.attitude_yaw_trusted:
            self.attitude_yaw_trusted = False
            self.attitude_yaw_confirmed = False
            self.counters["ATTITUDE yaw no longer trusted"] += 1
        self._on_distrust()

    # ------------------------------------------------------------------ what it decides
    def gate(self) -> bool:
        """Injection gate on the heading (:attr:`gate_reason` says why not): a settled yaw from
        motion (not necessarily observed lately) that disagrees with ours objects (a reset follows
        once it is observed again); a converged one that agrees vouches, as does a dual-antenna
        heading fused in the last TRUSTED_HEADING_MAX_AGE_S.  Otherwise our own heading sigma must
        be below ``output.max_sigma_yaw_deg``, and in horizontal motion the heading must have been
        confirmed by the yaw from motion once: at rest, in a hover or a vertical climb a wrong
        heading costs the lever arm only (centimetres), in motion the INS integrates along it."""
        self.gate_reason = ""
        eng = self.engine
        if not eng.initialized or eng.kf is None:
            return True           # no heading to judge (the status gate decides)
        heading, sigma = eng.heading_and_sigma()
        if self.gsf.settled and self.disagrees(heading, sigma):
            self.counters["solutions withheld: heading contradicts the yaw from motion"] += 1
            self.gate_reason = "heading disputed"
            return False
        if self.gsf.converged:
            return True
        if eng.t_gps - self._last_trusted_heading_t <= TRUSTED_HEADING_MAX_AGE_S:
            return True
        if sigma > self.max_sigma_yaw_rad:
            self.counters["solutions withheld: heading unknown"] += 1
            self.gate_reason = "heading unknown"
            return False
        if self.gsf.in_motion:
            self._t_last_motion = eng.t_gps
        # held for MOTION_HOLD_S after the last sign of motion: the IMU's velocity change restarts
        # at every GNSS velocity, and a start of motion below the moving speed must not toggle
        if not self.heading_confirmed and eng.t_gps - self._t_last_motion < MOTION_HOLD_S:
            self.counters["solutions withheld: heading not yet confirmed in motion"] += 1
            self.gate_reason = "heading unconfirmed"
            return False
        return True

    def initial_attitude(self, r_e, attitude, tilt_sigma_rad: float):
        """(C_b_e, tilt sigma, heading sigma) to initialise with, or None (counted): the autopilot's
        ``attitude`` (roll, pitch, yaw; None when there is no fresh one) with
        ``mavlink.attitude_yaw_sigma_deg`` and ``tilt_sigma_rad`` unless the settled yaw from
        motion contradicts its yaw (then that yaw is dropped for the run); then the yaw from
        motion, with the ATTITUDE's roll and pitch if there is one, else its own."""
        lat, lon, _ = ecef_to_geodetic(r_e)
        Cne = C_n_e(lat, lon)
        g = self.gsf
        att = attitude
        if att is not None and self.attitude_yaw_trusted:
            if g.settled and self.disagrees(att[2], self.attitude_yaw_sigma_rad):
                self._distrust_attitude_yaw()
                self._event(SEVERITY_WARNING, "autopilot yaw contradicts the yaw from motion: not used")
            else:
                # confirmed now, or earlier in this run (a re-init in flight, the yaw from motion
                # possibly out of date on a straight leg)
                self.heading_confirmed = g.converged or self.attitude_yaw_confirmed
                self._heading_from_attitude = True
                return Cne @ euler_to_dcm(*att), tilt_sigma_rad, self.attitude_yaw_sigma_rad
        if not g.settled:         # (settled suffices: nothing else to go by; its sigma says how good)
            self.counters["init: waiting for the yaw from motion"] += 1
            return None
        self.counters["init: heading from the yaw from motion"] += 1
        self.heading_confirmed = True
        self._heading_from_attitude = False
        if att is not None:
            return Cne @ euler_to_dcm(att[0], att[1], g.yaw_rad), tilt_sigma_rad, g.yaw_sigma_rad
        return Cne @ g.C_b_n_estimate(), g.tilt_sigma_rad, g.yaw_sigma_rad

    def snapshot(self) -> dict:
        """The health report's ``yaw_gsf`` section."""
        return {**self.gsf.snapshot(), "heading_resets": self.heading_resets,
                "attitude_yaw_trusted": self.attitude_yaw_trusted, "imu_screen": dict(self.screen_counters)}


__all__ = ["HeadingWatch", "GSF_AGREE_SIGMAS", "GSF_RESTART_PROBATION_S", "HEADING_RESET_QUIET_S"]
