"""The engine's aiding from receiver solutions and vehicle constraints (a mixin of
:class:`companion.nav.engine.NavEngine`): loose position/velocity fixes (SPP or the autopilot's
GPS_RAW_INT), multi-antenna attitude, dual-antenna baselines, the non-holonomic constraint and the
zero-motion updates.  Each builds its rows with :mod:`.measurements` and fuses them through the
engine's ``_update_with``; the raw-epoch loop stays in the engine."""
from __future__ import annotations

import logging
import math

import numpy as np

from ..messages import GnssAttitude, GnssBaseline, GnssFix
from .earth import C_n_e, ecef_to_geodetic
from .measurements import (antenna_state, attitude_batch, attitude_rate_e, baseline_batch,
                           horizontal_velocity_fix_batch, nhc_batch, position_fix_batch, velocity_fix_batch,
                           zero_rate_batch, zero_velocity_batch)

log = logging.getLogger("companion.nav.engine")

#: a followed heading reading (GnssAttitude.follow_heading) finds the heading released to this many
#: times its sigma: a gain of ~0.99, the heading then as certain as the reading, no more
HEADING_RELEASE = 10.0


class ReceiverAiding:
    """Loose fixes, GNSS attitude and baselines, NHC and zero-motion updates of the NavEngine."""

    def _spp(self, ins, prep):
        from ..gnss.spp import solve_spp
        return solve_spp(prep, r_init_e=antenna_state(ins, self.lever_arm_b)[0])

    def _spp_velocity_cov_e(self, sol) -> np.ndarray:
        """ECEF covariance of an SPP Doppler velocity: Doppler sigma x DOP, local NED axes."""
        lat, lon, _ = ecef_to_geodetic(sol.r_e)
        Cne = C_n_e(lat, lon)
        sv = self.cfg.sigma_doppler_mps
        cov_v = np.diag([(sv * sol.hdop / math.sqrt(2)) ** 2] * 2 + [(sv * sol.vdop) ** 2])
        return Cne @ cov_v @ Cne.T

    def _loose_batches(self, ins, prep, sol):
        if sol is None:
            self.counters["loose: no SPP solution"] += 1
            return []
        lat, lon, _ = ecef_to_geodetic(sol.r_e)
        Cne = C_n_e(lat, lon)
        sig = max(float(np.median(prep.sigma_pseudorange_m)), self.cfg.sigma_pseudorange_floor_m)
        sig *= math.sqrt(self._correlation_inflation(prep.t_gps))  # same weighting as tight coupling
        cov_n = np.diag([(sig * sol.hdop / math.sqrt(2)) ** 2] * 2 + [(sig * sol.vdop) ** 2])
        out = [position_fix_batch(ins, sol.r_e, Cne @ cov_n @ Cne.T, self.lever_arm_b, layout=self.layout)]
        if sol.v_e is not None:
            out.append(velocity_fix_batch(ins, sol.v_e, self._spp_velocity_cov_e(sol), self.lever_arm_b,
                                          layout=self.layout))
        return out

    def process_fix(self, fix: GnssFix):
        """Loose coupling of a receiver's own fix (GPS_RAW_INT / NAV-PVT), at the fix's GPS time."""
        if not self.initialized:
            self.counters["fix before init"] += 1
            return None
        if self.imu_time_of(fix) > self.t_gps:
            self._wait_for_imu(fix)
            return None
        return self._process_fix(fix)

    def _process_fix(self, fix: GnssFix):
        ins = self.ins_at(self.imu_time_of(fix))
        if ins is None or fix.fix_type < 3 or not np.all(np.isfinite(fix.r_e)):
            self.counters["fix unusable"] += 1
            return None
        lat, lon, _ = ecef_to_geodetic(fix.r_e)
        Cne = C_n_e(lat, lon)
        cov = Cne @ np.diag([fix.sigma_h_m ** 2 / 2, fix.sigma_h_m ** 2 / 2, fix.sigma_v_m ** 2]) @ Cne.T
        if fix.v_e is not None:
            ins = self._course_alignment(ins, fix.v_e, np.eye(3) * fix.sigma_vel_mps ** 2)
        ap = fix.autopilot_clock
        batches = [position_fix_batch(ins, fix.r_e, cov, self.lever_arm_b, layout=self.layout, autopilot_clock=ap)]
        if fix.v_e is not None and fix.vertical_velocity_valid:
            batches.append(velocity_fix_batch(ins, fix.v_e, np.eye(3) * fix.sigma_vel_mps ** 2, self.lever_arm_b,
                                              layout=self.layout, autopilot_clock=ap))
        elif fix.v_e is not None:       # no vertical velocity in the message: do not assert zero
            batches.append(horizontal_velocity_fix_batch(ins, fix.v_e, fix.sigma_vel_mps, Cne, self.lever_arm_b,
                                                         layout=self.layout, autopilot_clock=ap))
        reports = [self.kf.gate(b) for b in batches]
        for r in reports:
            self.counters[f"fix {r.kind} used"] += r.n_accepted
            for reason in r.rejected_reason.values():
                self.counters[f"fix {r.kind} rejected: {reason}"] += 1
        self._record(reports, fix.t_gps)
        dx = self.kf.update(batches, self._held_back(reports))
        if any(r.n_accepted for r in reports):
            self._feedback(dx)
            self.last_gnss_update_t = fix.t_gps
        self._check_integrity(fix.t_gps)
        return reports

    def process_attitude(self, att: GnssAttitude):
        """Multi-antenna GNSS attitude at its GPS time (seed 003)."""
        if not self.initialized:
            self.counters["attitude before init"] += 1
            return None
        if self.imu_time_of(att) > self.t_gps:
            self._wait_for_imu(att)
            return None
        return self._process_attitude(att)

    def _process_attitude(self, att: GnssAttitude):
        ins = self.ins_at(self.imu_time_of(att))
        if ins is None:
            self.counters["attitude older than INS history"] += 1
            return None
        lat, lon, _ = ecef_to_geodetic(ins.r_e)
        b = attitude_batch(ins.C_b_e, C_n_e(lat, lon), att, layout=self.layout,
                           rate_e=None if att.autopilot_clock else attitude_rate_e(ins))
        if not len(b):
            self.counters["attitude without angles"] += 1
            return None
        if att.follow_heading and math.isfinite(att.heading_rad):
            self.release_heading(HEADING_RELEASE * att.sigma_heading_rad)
        return self._update_with(b, "attitude", "attitude used")

    def process_baseline(self, bl: GnssBaseline):
        """Dual-antenna moving-baseline vector at its GPS time (heading aiding)."""
        if not self.initialized:
            self.counters["baseline before init"] += 1
            return None
        if self.cfg.moving_baseline_b_m is None:
            self.counters["baseline ignored: no moving_baseline_b_m configured"] += 1
            return None
        if not bl.carrier_fixed:
            self.counters["baseline ignored: carrier not fixed"] += 1
            return None
        if not (np.all(np.isfinite(bl.rel_pos_ned_m)) and np.all(np.isfinite(bl.sigma_ned_m))):
            self.counters["baseline rejected: not finite"] += 1
            return None
        b = np.asarray(self.cfg.moving_baseline_b_m, float)
        length, nominal = float(np.linalg.norm(bl.rel_pos_ned_m)), float(np.linalg.norm(b))
        sig_len = bl.length_sigma_m if math.isfinite(bl.length_sigma_m) else float(np.max(bl.sigma_ned_m))
        if abs(length - nominal) > self.cfg.baseline_length_tol_m + 3.0 * sig_len:
            self.counters["baseline rejected: length (wrong carrier fix?)"] += 1
            return None
        if self.imu_time_of(bl) > self.t_gps:
            self._wait_for_imu(bl)
            return None
        return self._process_baseline(bl)

    def _process_baseline(self, bl: GnssBaseline):
        ins = self.ins_at(self.imu_time_of(bl))
        if ins is None:
            self.counters["baseline older than INS history"] += 1
            return None
        lat, lon, _ = ecef_to_geodetic(ins.r_e)
        b = baseline_batch(ins.C_b_e, C_n_e(lat, lon), bl, np.asarray(self.cfg.moving_baseline_b_m, float),
                           layout=self.layout, rate_e=attitude_rate_e(ins))
        return self._update_with(b, "baseline", "baseline rows used")

    def _nhc_update(self) -> None:
        """Non-holonomic constraint while moving on the ground.  Repeated gate rejections mean the
        assumption is broken (skid, lift, a vehicle that is not a car): suspend it for a while."""
        if not self.ground_mode or self.t_gps < self._nhc_suspended_until:
            return
        if float(self.v_e @ self.v_e) < self.cfg.nhc_min_speed_mps ** 2:
            return
        b = nhc_batch(self.v_e, self.C_b_e, self.cfg.nhc_sigma_lateral_mps, self.cfg.nhc_sigma_vertical_mps,
                      layout=self.layout)
        rep = self.kf.gate(b)
        self._record((rep,), self.t_gps)
        if rep.n_accepted < len(b):
            self._nhc_rejections += 1
            self.counters["nhc rejected: innovation gate"] += len(b) - rep.n_accepted
            if self._nhc_rejections >= self.cfg.nhc_suspend_after_rejections:
                self._nhc_suspended_until = self.t_gps + self.cfg.nhc_suspend_s
                self._nhc_rejections = 0
                self.counters["nhc suspended"] += 1
                log.info("non-holonomic constraint violated repeatedly: suspended for %.0f s", self.cfg.nhc_suspend_s)
                return
        else:
            self._nhc_rejections = 0
        self.counters["nhc used"] += rep.n_accepted
        dx = self.kf.update([b], [rep])
        if rep.n_accepted:
            self._feedback(dx)

    def _zero_motion_update(self) -> None:
        """ZUPT + ZARU from the still window (only if the INS agrees it is nearly at rest)."""
        speed = float(np.linalg.norm(self.v_e))
        if speed > self.cfg.zupt_max_speed_mps:
            self.counters["zupt skipped: INS speed"] += 1
            return
        w_mean, w_std_mean = self._still.gyro_mean_and_sigma()
        batches = [zero_velocity_batch(self.v_e, self.cfg.zupt_sigma_mps, layout=self.layout),
                   zero_rate_batch(w_mean, self.C_b_e, self.b_g, max(w_std_mean, self.cfg.zaru_sigma_floor_radps),
                                   layout=self.layout)]
        reports = [self.kf.gate(b) for b in batches]
        for r in reports:
            self.counters[f"{r.kind} used"] += r.n_accepted
            self.counters[f"{r.kind} rejected"] += len(r.labels) - r.n_accepted
        self._record(reports, self.t_gps)
        dx = self.kf.update(batches, reports)
        if any(r.n_accepted for r in reports):
            self._feedback(dx)
