"""The tightly coupled engine (RTK on, GPS / Galileo / BeiDou / QZSS) fed real rover and base
epochs with a synthetic IMU at rest at the rover's true position: the RTK update on real carriers
where no IMU was recorded with them."""
from __future__ import annotations

import math

import numpy as np

from companion.gnss.spp import spp_epoch
from companion.messages import BaseStationPosition, ImuSample
from companion.nav.earth import OMEGA_IE_RADPS, C_n_e, ecef_to_geodetic, gravity_ecef
from companion.nav.engine import EngineConfig, NavEngine
from companion.nav.filter import ProcessNoise
from companion.rtk_signals import RTK_SIGNALS


def engine_at_rest(ephemerides, base_r_e, base_epochs, rover_epochs, r_true_e, *, seed: int = 1,
                   systems: str = "GECJ", glonass_integers: bool = False):
    """(EpochReport per rover epoch, 3-D error of the engine's position after each).  The engine
    starts from the first rover epoch's SPP position half a second before it; the IMU (200 Hz,
    white noise) senses the earth's rotation and gravity at ``r_true_e``, the antenna there (no
    lever arm).  ``base_epochs`` and ``rover_epochs`` pair one to one; ``systems``,
    ``glonass_integers``: the engine's."""
    r_true_e = np.asarray(r_true_e, float)
    eng = NavEngine(EngineConfig(noise=ProcessNoise(1e-4, 1e-3, 1e-6, 1e-5), systems=systems, rtk_enabled=True,
                                 rtk_glonass_integers=glonass_integers,
                                 rtk_signals=RTK_SIGNALS, elevation_mask_deg=10.0))
    for e in ephemerides:
        eng.process(e)
    eng.process(BaseStationPosition(0, np.asarray(base_r_e, float).copy(), 0.0))
    sol = spp_epoch(rover_epochs[0], eng.ephemerides, systems=systems)
    C_b_e = C_n_e(*ecef_to_geodetic(r_true_e)[:2])
    t = rover_epochs[0].t_gps - 0.5
    eng.initialize(t, sol.r_e, np.zeros(3), C_b_e, dict(pos_m=5.0, vel_mps=0.1, tilt_rad=0.01, heading_rad=0.05,
                                                        ba_mps2=0.05, bg_radps=1e-3))
    w_ie_b = C_b_e.T @ np.array([0.0, 0.0, OMEGA_IE_RADPS])
    f_b = C_b_e.T @ -gravity_ecef(r_true_e)
    rng = np.random.default_rng(seed)
    dt = 0.005
    reps, err = [], []
    for b, r in zip(base_epochs, rover_epochs):
        while t < r.t_gps + 0.1:
            t += dt
            eng.process(ImuSample(t, dt, w_ie_b * dt + rng.normal(0, 1e-4 * math.sqrt(dt), 3),
                                  f_b * dt + rng.normal(0, 1e-3 * math.sqrt(dt), 3)))
        eng.process(b)
        reps.append(eng.process(r))
        err.append(float(np.linalg.norm(eng.r_e - r_true_e)))
    return reps, err
