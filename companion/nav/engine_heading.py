"""Heading from the course over ground and heading resets (a mixin of
:class:`companion.nav.engine.NavEngine`): the first epochs after an initialisation with an unknown
heading align it with the antenna velocity (:mod:`.course_alignment`), and the shell may reset it
(yaw from motion, :mod:`.yaw_gsf`)."""
from __future__ import annotations

import logging
import math

import numpy as np

from ..messages import GnssAttitude
from .earth import C_n_e, ecef_to_geodetic
from .course_alignment import course_from_velocity, down_axis_e, heading_of, heading_reset, heading_variance
from .measurements import InsPoint, antenna_state, attitude_batch

log = logging.getLogger("companion.nav.engine")


class HeadingAlignment:
    """Course alignment and heading resets of the NavEngine."""

    def _course_alignment_pending(self) -> bool:
        return (self.cfg.course_alignment_enabled and self.ground_mode
                and self.course_epochs_fused < self.cfg.course_alignment_epochs)

    def _course_alignment(self, ins: InsPoint, v_ant_e, cov_v_e) -> InsPoint:
        """In-motion heading alignment (companion.nav.course_alignment) from one GNSS antenna
        velocity (ECEF, m/s) and its covariance, at the epoch's INS point.  Returns the INS point
        to build this epoch's other measurements on (re-interpolated after a heading reset)."""
        cfg = self.cfg
        if not self._course_alignment_pending() or v_ant_e is None or not np.all(np.isfinite(v_ant_e)):
            return ins
        u = down_axis_e(ins.r_e)
        yaw_rate = float(u @ (ins.C_b_e @ ins.omega_ib_b))
        if abs(yaw_rate) > cfg.course_alignment_max_yaw_rate_radps:
            self.counters["course alignment waiting: turning"] += 1
            return ins
        _, v_ant_pred, _ = antenna_state(ins, self.lever_arm_b)
        v_imu = np.asarray(v_ant_e, float) - (v_ant_pred - ins.v_e)      # lever-arm velocity removed
        m = course_from_velocity(ins.t_gps, v_imu, cov_v_e, ins.r_e, cfg.course_alignment_slip_sigma_rad,
                                 self.course_epochs_fused)
        if m.speed_h_mps < cfg.course_alignment_min_speed_mps:
            return ins
        L = self.layout
        delta = (m.heading_rad - heading_of(ins.C_b_e, ins.r_e) + math.pi) % (2.0 * math.pi) - math.pi
        sigma_filter = math.sqrt(max(heading_variance(self.kf.P[L.att, L.att], u), 0.0))
        if sigma_filter < math.pi / 4.0 and float(ins.C_b_e[:, 0] @ v_imu) < 0.0:
            # the heading is known well enough to see that the vehicle is reversing: the course
            # points backwards (with no idea of the heading, forward motion is assumed)
            self.counters["course alignment waiting: reversing"] += 1
            return ins
        if max(sigma_filter, abs(delta)) > cfg.course_alignment_reset_above_rad:
            # too far for a linear update: turn the attitude (now and its short history) onto the course
            self.reset_heading(delta, m.sigma_rad, v_imu_e=v_imu, cov_v_e=cov_v_e, v_ref_e=ins.v_e)
            self.counters["course alignment: heading reset"] += 1
            log.info("heading reset to the course over ground %.1f deg (%+.1f deg, filter sigma was %.1f deg) "
                     "at %.1f m/s", math.degrees(m.heading_rad), math.degrees(delta), math.degrees(sigma_filter),
                     m.speed_h_mps)
        else:
            b = attitude_batch(ins.C_b_e, C_n_e(*ecef_to_geodetic(ins.r_e)[:2]),
                               GnssAttitude(ins.t_gps, heading_rad=m.heading_rad, sigma_heading_rad=m.sigma_rad),
                               layout=self.layout)
            if not self._update_with(b, "course alignment", "course alignment: heading fused").n_accepted:
                return ins
        self.course_epochs_fused += 1
        if math.isnan(self.course_alignment_t_gps):
            self.course_alignment_t_gps = ins.t_gps
        return self.ins_at(ins.t_gps) or ins

    def reset_heading(self, delta_heading_rad: float, sigma_heading_rad: float, *, v_imu_e=None, cov_v_e=None,
                      v_ref_e=None) -> None:
        """Heading reset (companion.nav.course_alignment.heading_reset): turn the attitude, now and
        its short history, by ``delta_heading_rad`` about local down and replace the heading
        variance by ``sigma_heading_rad**2``.  With a GNSS velocity of the IMU ``v_imu_e`` (ECEF, m/s)
        and its covariance, the velocity is taken from it as well (it was integrated along the wrong
        heading; its error is then uncorrelated with everything else): the state moves by
        ``v_imu_e - v_ref_e``, ``v_ref_e`` being the INS velocity at the GNSS time (default: now)."""
        L = self.layout
        R, P = heading_reset(self.kf.P, L.att, down_axis_e(self.r_e), delta_heading_rad, sigma_heading_rad)
        dv = np.zeros(3)
        if v_imu_e is not None:
            dv = np.asarray(v_imu_e, float) - (self.v_e if v_ref_e is None else np.asarray(v_ref_e, float))
            P[L.vel, :] = 0.0
            P[:, L.vel] = 0.0
            P[L.vel, L.vel] = cov_v_e
        self.kf.P = P
        self.C_b_e = R @ self.C_b_e
        self.v_e = self.v_e + dv
        self._hist.correct(None, dv, R)
        self.carrier.clear()     # the antenna moved with the lever arm: restart the carrier bookkeeping
        self._prev_epoch_v = None
        if self.smoother is not None:
            self.smoother.start(self)     # a jump of the nominal state: the smoothing restarts here

    def release_heading(self, sigma_heading_rad: float) -> None:
        """Raise the heading variance to at least ``sigma_heading_rad**2`` (tilt, cross-covariances
        and the state kept): before a reading of a heading source whose error is correlated in time
        and already in the heading (the autopilot's compass at rest), so that its readings are not
        averaged as if independent and the heading is never more certain than the source."""
        L = self.layout
        u = down_axis_e(self.r_e)
        var = heading_variance(self.kf.P[L.att, L.att], u)
        if var < sigma_heading_rad ** 2:
            self.kf.P[L.att, L.att] += (sigma_heading_rad ** 2 - var) * np.outer(u, u)

    def heading_and_sigma(self) -> tuple[float, float]:
        """The filter's heading (rad, clockwise from true north) and its 1-sigma (rad)."""
        u = down_axis_e(self.r_e)
        var = heading_variance(self.kf.P[self.layout.att, self.layout.att], u)
        return heading_of(self.C_b_e, self.r_e), math.sqrt(max(var, 0.0))
