"""A followed heading source (GnssAttitude.follow_heading: the autopilot's compass at rest): its
error is the same from one reading to the next, so the heading follows the latest reading with
the reading's sigma instead of averaging the readings into a false certainty."""
import math

import numpy as np
import pytest

from companion.messages import GnssAttitude
from companion.nav.engine import EngineConfig, NavEngine
from tests.test_engine import NOISE, _straight_line_imu

SIGMA = math.radians(5.0)


def _engine(heading_sigma_rad):
    t0, r0, v, C, samples, _ = _straight_line_imu(v_n=(0.0, 0.0, 0.0), seconds=3.0)
    eng = NavEngine(EngineConfig(noise=NOISE))
    p0 = dict(tilt_rad=1e-3, heading_rad=heading_sigma_rad, pos_m=0.5, vel_mps=0.05, ba_mps2=0.03, bg_radps=1e-5)
    eng.initialize(t0, r0, v, C, p0)
    return eng, samples


def _read(eng, samples, k, offsets_deg, follow):
    """Readings at the tags of samples k, k+100, ...: the heading at the start plus each offset."""
    h0 = eng.heading_and_sigma()[0]
    out = []
    i = 0
    for j, off in enumerate(offsets_deg):
        while i <= k + 100 * j:
            eng.process(samples[i])
            i += 1
        eng.process(GnssAttitude(samples[k + 100 * j].t_gps, heading_rad=h0 + math.radians(off),
                                 sigma_heading_rad=SIGMA, autopilot_clock=True, follow_heading=follow))
        h, s = eng.heading_and_sigma()
        out.append((math.degrees(h - h0), math.degrees(s)))
    return out


def test_followed_readings_move_the_heading_to_the_latest_with_its_sigma():
    # a heading known to 0.06 deg (a copy of the same compass) still follows a reading 8 deg away
    eng, samples = _engine(1e-3)
    out = _read(eng, samples, 10, [8.0, 3.0, -2.0], follow=True)
    for (h, s), off in zip(out, [8.0, 3.0, -2.0]):
        assert h == pytest.approx(off, abs=0.1)
        assert s == pytest.approx(5.0, abs=0.1)       # never more certain than one reading


def test_readings_not_followed_are_averaged():
    eng, samples = _engine(SIGMA)
    out = _read(eng, samples, 10, [8.0, 3.0, -2.0], follow=False)
    h, s = out[-1]
    assert h == pytest.approx((8.0 + 3.0 - 2.0) / 4.0, abs=0.3)      # prior (0) and three readings
    assert s == pytest.approx(5.0 / 2.0, abs=0.1)
