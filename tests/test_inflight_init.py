"""An initialisation in flight (a re-initialisation after a divergence, a start without the
ground phase): the heading is uncertain by degrees and the vehicle manoeuvres.  The TDCP model
must carry how the velocity error grows inside the epoch interval through the attitude and the
accelerometer bias (companion.nav.measurements.tdcp_batch): without that term the gate rejected
good rows, the velocity and heading wandered by 1 m/s and several degrees, and the integrity
monitor re-initialised the filter again and again."""
import math

import numpy as np
import pytest

from companion.nav.earth import C_n_e, ecef_to_geodetic, rotation_from_rotvec
from companion.nav.engine import NavEngine
from sitl.paper import mode_config
from sitl.scenario import build_scenario
from sitl.simulate import feed_engine, simulate
from sitl.tuning import tuning_for


def _heading_deg(C_b_e, r_e):
    lat, lon, _ = ecef_to_geodetic(r_e)
    C = C_n_e(lat, lon).T @ C_b_e
    return math.degrees(math.atan2(C[1, 0], C[0, 0]))


# -5 deg was 4.02 deg at 3.95 of its own sigma until the GNSS rows were carried across the
# measurement latency (companion.nav.measurements.LatencyTransition): 2.73 deg at 2.52 sigma now
@pytest.mark.parametrize("heading_error_deg", [5.0, -5.0])
def test_tdcp_dgps_initialised_in_flight_converges_without_rejections(heading_error_deg):
    sc = build_scenario("uav")
    tun = tuning_for(sc)
    sim = simulate(sc, 1)
    eng = NavEngine(mode_config("tdcp_dgps", tun, sim.lever_arm_b))
    for e in sim.ephemerides:
        eng.process(e)
    eng.process(sim.base)
    tr = sim.truth
    k0 = int(np.searchsorted(tr.t_gps, tr.t_gps[0] + 60.0))      # in the survey pattern, moving
    lat, lon, _ = ecef_to_geodetic(tr.r_e[k0])
    down_e = C_n_e(lat, lon)[:, 2]
    p0 = dict(tun.p0, heading_rad=math.radians(6.0), pos_m=1.5, vel_mps=0.3)
    C0 = rotation_from_rotvec(down_e * math.radians(heading_error_deg)) @ tr.C_b_e[k0]
    eng.initialize(tr.t_gps[k0], tr.r_e[k0] + np.array([1.0, -0.5, 0.7]), tr.v_e[k0] + 0.2, C0, p0)
    t_init = tr.t_gps[k0]
    rover = [e for e in sim.rover_epochs if e.t_gps > t_init]
    base = [e for e in sim.base_epochs if e.t_gps > t_init - 2.0]
    lag = tun.gnss_latency_s
    worst_after_20s = worst_ratio = 0.0
    for _, s in feed_engine(eng, sim, lag, rover=rover, base=base, imu=sim.imu[k0:k0 + int(40.0 * sc.imu.rate_hz)]):
        if eng.t_gps - t_init >= 20.0:
            k = int(np.searchsorted(tr.t_gps, eng.t_gps))
            dh = (_heading_deg(eng.C_b_e, eng.r_e) - _heading_deg(tr.C_b_e[k], tr.r_e[k]) + 180.0) % 360.0 - 180.0
            worst_after_20s = max(worst_after_20s, abs(dh))
            worst_ratio = max(worst_ratio, abs(math.radians(dh)) / eng.heading_and_sigma()[1])
    rejected = sum(v for k, v in eng.counters.items() if k.startswith("tdcp rejected"))
    used = eng.counters["tdcp used"]
    print(f"heading error {heading_error_deg:+.0f} deg at init: worst {worst_after_20s:.2f} deg 20-40 s after it; "
          f"(at most {worst_ratio:.2f} of its own sigma); TDCP rows {used} used, {rejected} rejected; "
          f"integrity {eng.integrity.state}")
    assert used > 200
    assert rejected <= 0.01 * used
    # the heading is observable only through the manoeuvres: it improves, and the filter knows how well
    assert worst_after_20s < 0.7 * abs(heading_error_deg)
    assert worst_ratio < 3.0
    assert eng.reset_counter == 1 and eng.integrity.state == "ok"
