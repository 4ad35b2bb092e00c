"""GPS_RAW_INT carries speed and course, no vertical velocity: the loose update must not assert
zero vertical velocity for a climbing vehicle (engine level, exact straight-line climb)."""
import math

import numpy as np

from companion.messages import GnssFix, ImuSample
from companion.nav.earth import C_n_e, geodetic_to_ecef
from companion.nav.engine import EngineConfig, NavEngine
from companion.nav.filter import ProcessNoise
from companion.nav.strapdown import invert_step

NOISE = ProcessNoise(1e-4, 1e-3, 1e-6, 1e-5)
P0 = dict(tilt_rad=1e-3, heading_rad=1e-3, pos_m=1.0, vel_mps=1.0, ba_mps2=0.05, bg_radps=1e-4)


def _climb(valid_vertical: bool, climb_mps=3.0, seconds=20.0, rate_hz=100.0):
    lat, lon = math.radians(35.0), math.radians(139.0)
    C = C_n_e(lat, lon)
    v = C @ np.array([8.0, 2.0, -climb_mps])           # NED: climbing
    r = geodetic_to_ecef(lat, lon, 100.0)
    tau = 1.0 / rate_hz
    t0 = 1.4e9
    eng = NavEngine(EngineConfig(noise=NOISE))
    eng.initialize(t0, r, C @ np.array([8.0, 2.0, 0.0]), C, P0)   # starts thinking it is level
    v_h = C @ np.array([8.0, 2.0, 0.0])                # what GPS_RAW_INT gives: speed and course
    for k in range(int(seconds * rate_hz)):
        dth, dv = invert_step(r, v, C, v, C, tau)
        r = r + v * tau
        t = t0 + (k + 1) * tau
        eng.process_imu(ImuSample(t, tau, dth, dv))
        if (k + 1) % int(rate_hz / 5) == 0:            # 5 Hz fixes
            eng.process_fix(GnssFix(t, r.copy(), v_h, sigma_h_m=0.5, sigma_v_m=1.0, sigma_vel_mps=0.2,
                                    vertical_velocity_valid=valid_vertical))
    return float(C[:, 2] @ (eng.v_e - v)), eng


def test_climb_is_not_pulled_to_zero_vertical_velocity():
    err_h_only, eng = _climb(False)
    err_asserted, _ = _climb(True)
    print(f"vertical velocity error after 20 s of a 3 m/s climb: {err_h_only:+.3f} m/s horizontal-only, "
          f"{err_asserted:+.3f} m/s with a zero vertical asserted")
    assert eng.counters["fix velocity used"] > 0 and eng.aid.sources["velocity"].labels == ["vn", "ve"]
    assert abs(err_h_only) < 0.1
    assert abs(err_asserted) > 0.5
