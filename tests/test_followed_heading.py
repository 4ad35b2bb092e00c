"""A followed heading source (GnssAttitude.follow_heading: the autopilot's compass at rest): its
error is the same from one reading to the next, so the heading follows the latest reading with
the reading's sigma instead of averaging the readings into a false certainty."""
import math

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


class _Engine:
    initialized = True

    def __init__(self):
        self.got = []

    def process(self, msg):
        self.got.append(msg)


class _TimeMap:
    @staticmethod
    def to_gps(t_boot_s):
        return 1.4e9 + t_boot_s


def test_the_pipeline_follows_the_autopilot_heading_on_the_ground_only():
    from types import SimpleNamespace

    from companion.config import config_from_dict
    from companion.pipeline import NavPipeline
    pipe = NavPipeline(config_from_dict({"mavlink": {"autopilot_heading_on_ground": True}}))
    pipe.engine, pipe.time_map = _Engine(), _TimeMap()
    t_ms = [0]

    def reading(yaw=0.3):
        t_ms[0] += 100                             # ten readings a second pass the rate limit
        before = len(pipe.engine.got)
        pipe._ground_heading(SimpleNamespace(time_boot_ms=t_ms[0], yaw=yaw))
        return len(pipe.engine.got) > before

    pipe.on_ground = True
    assert reading()
    att = pipe.engine.got[-1]
    assert att.follow_heading and att.autopilot_clock and att.heading_rad == 0.3
    assert att.sigma_heading_rad == pytest.approx(SIGMA)
    t_ms[0] -= 50
    assert not reading()                           # 50 ms after the last: not yet
    assert reading()
    pipe.on_ground = False                         # in the air our own heading (see the README)
    assert not reading()
    pipe.on_ground = True
    pipe.heading.attitude_yaw_trusted = False              # the yaw from motion contradicted the compass
    assert not reading()
    assert pipe.counters["autopilot heading fused (on the ground)"] == 2
