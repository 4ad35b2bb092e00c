"""The yaw from motion watching our heading (companion.heading_watch), with a stand-in estimator
and engine: each decision on its own (the flights through the pipeline: test_yaw_gsf_pipeline)."""
from __future__ import annotations

import math
from collections import Counter
from types import SimpleNamespace

import numpy as np
import pytest

from companion.config import config_from_dict
from companion.heading_watch import (GSF_AGREE_SIGMAS, GSF_RESTART_PROBATION_S, MOTION_HOLD_S,
                                     TRUSTED_HEADING_MAX_AGE_S, HeadingWatch)
from companion.nav.earth import C_n_e, dcm_to_euler, ecef_to_geodetic, geodetic_to_ecef
from companion.nav.engine import NavEngine

R_E = geodetic_to_ecef(math.radians(35.0), math.radians(139.6), 70.0)


def _watch(heading_rad=0.0, sigma_rad=math.radians(1.0), **gsf):
    """A watch over a stand-in engine (heading, sigma) and a stand-in estimator (``gsf`` fields)."""
    events, distrusted = [], []
    w = HeadingWatch(NavEngine(config_from_dict({}).engine_config()), counters=Counter(),
                     event=lambda sev, text: events.append(text), gap_s=1.0, elevation_mask_deg=10.0,
                     attitude_yaw_sigma_deg=5.0, max_sigma_yaw_deg=10.0, lever_b_m=(0.0, 0.0, 0.0),
                     on_attitude_yaw_distrusted=lambda: distrusted.append(True))
    w.engine = SimpleNamespace(initialized=True, t_gps=1000.0, kf=object(),
                               heading_and_sigma=lambda: (heading_rad, sigma_rad))
    fields = dict(gap_restarts=0, converged=False, settled=False, in_motion=False, yaw_rad=0.0,
                  yaw_sigma_rad=math.radians(30.0), tilt_sigma_rad=0.05, C_b_n_estimate=lambda: np.eye(3))
    fields.update(gsf)
    w.gsf = SimpleNamespace(**fields)
    return w, events, distrusted


def test_a_restarted_yaw_from_motion_does_not_overrule_a_more_certain_heading():
    """After a GNSS gap the yaw-from-motion bank starts over; converged again within seconds it
    may sit on a wrong mode (the rtk flight's 30-s outage: 164 deg off at 9.5 deg sigma) -- it
    does not reset a heading more certain than its own for GSF_RESTART_PROBATION_S; while they
    disagree nothing is injected (which of the two is wrong is not known)."""
    w, _, _ = _watch(converged=True, settled=True, yaw_rad=math.radians(164.0), yaw_sigma_rad=math.radians(9.5))

    class ResetReached(Exception):
        pass

    class Kf:                                  # the reset's first step reads the covariance
        @property
        def P(self):
            raise ResetReached

    eng = w.engine
    eng.kf, eng.layout = Kf(), SimpleNamespace(vel=slice(3, 6))
    Cne = np.eye(3)
    with pytest.raises(ResetReached):          # no restart: a converged, disagreeing bank resets ours
        w._check_heading(np.array([10.0, 0.0, 0.0]), 0.1, Cne)
    assert not w.restarted_and_less_certain(math.radians(1.0))
    w.gsf.gap_restarts = 1                                                   # the bank restarted (a gap)
    w._disagreements = 0
    w._check_heading(np.array([10.0, 0.0, 0.0]), 0.1, Cne)
    assert w.counters["heading reset refused: yaw from motion restarted recently, less certain"] == 1
    assert w.heading_resets == 0 and not w.gate() and w.gate_reason == "heading disputed"
    assert not w.restarted_and_less_certain(math.radians(12.0))     # ours less certain: it may
    eng.t_gps += GSF_RESTART_PROBATION_S + 0.1
    assert not w.restarted_and_less_certain(math.radians(1.0))       # watched long enough


def test_the_gate_says_why_it_withholds():
    # a settled estimator just beyond the agreement bound objects, just inside it does not
    bound = GSF_AGREE_SIGMAS * math.hypot(math.radians(1.0), math.radians(5.0))
    w, _, _ = _watch(settled=True, converged=True, yaw_rad=bound * 1.01, yaw_sigma_rad=math.radians(5.0))
    assert not w.gate() and w.gate_reason == "heading disputed"
    w.gsf.yaw_rad = bound * 0.99
    assert w.gate() and w.gate_reason == ""
    # nobody vouches and our own sigma is too wide: unknown, until a dual-antenna heading is fused
    w, _, _ = _watch(sigma_rad=math.radians(15.0))
    assert not w.gate() and w.gate_reason == "heading unknown"
    w.trusted_heading_fused(w.engine.t_gps)
    assert w.gate()
    w.engine.t_gps += TRUSTED_HEADING_MAX_AGE_S + 0.1
    assert not w.gate()
    # a narrow heading never confirmed: fine at rest, withheld in motion and MOTION_HOLD_S after it
    w, _, _ = _watch()
    assert w.gate()
    w.gsf.in_motion = True
    assert not w.gate() and w.gate_reason == "heading unconfirmed"
    w.gsf.in_motion = False
    w.engine.t_gps += MOTION_HOLD_S * 0.5
    assert not w.gate()
    w.engine.t_gps += MOTION_HOLD_S
    assert w.gate()
    w.gsf.in_motion, w.heading_confirmed = True, True
    assert w.gate()
    assert w.counters["solutions withheld: heading not yet confirmed in motion"] == 2


def test_initial_attitude_takes_the_autopilot_yaw_unless_the_yaw_from_motion_contradicts_it():
    roll, pitch = 0.02, -0.03
    # agreeing (or nothing settled to contradict it): ATTITUDE with its configured yaw sigma
    w, events, distrusted = _watch(settled=True, yaw_rad=0.5, yaw_sigma_rad=math.radians(4.0))
    C, tilt_sigma, yaw_sigma = w.initial_attitude(R_E, (roll, pitch, 0.52), 0.02)
    assert (tilt_sigma, yaw_sigma) == (0.02, w.attitude_yaw_sigma_rad) and w.attitude_yaw_trusted
    assert not events and not distrusted and not w.heading_confirmed      # settled is not converged
    # contradicting: said once, the yaw dropped for the run, the estimator's yaw with ATTITUDE's tilt
    w.gsf.yaw_rad = 2.0
    C, tilt_sigma, yaw_sigma = w.initial_attitude(R_E, (roll, pitch, 0.52), 0.02)
    assert events == ["autopilot yaw contradicts the yaw from motion: not used"] and distrusted == [True]
    assert not w.attitude_yaw_trusted and w.heading_confirmed and yaw_sigma == w.gsf.yaw_sigma_rad
    lat, lon, _ = ecef_to_geodetic(R_E)
    assert dcm_to_euler(C_n_e(lat, lon).T @ C) == pytest.approx((roll, pitch, 2.0), abs=1e-9)
    w.gsf.yaw_rad = 0.52                      # agreeing again later: the autopilot's yaw stays dropped
    assert w.initial_attitude(R_E, (roll, pitch, 0.52), 0.02)[2] == w.gsf.yaw_sigma_rad
    # no ATTITUDE and nothing settled: wait (counted)
    w, _, _ = _watch()
    assert w.initial_attitude(R_E, None, 0.02) is None
    assert w.counters["init: waiting for the yaw from motion"] == 1
