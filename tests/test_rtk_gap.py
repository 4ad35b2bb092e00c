"""A gap in the rover's data (nothing arrives for 30 s) through the RTK engine: bridged when the
receiver's lock time says it tracked all through it, started again when it did not; the epochs
that arrive in a burst after the gap (late, one right behind the other) fix at once and right."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from companion.nav.earth import C_n_e, ecef_to_geodetic, rotation_from_rotvec
from companion.nav.engine import NavEngine
from sitl.paper import initial_errors
from sitl.rtk_score import WRONG_FIX_M, rtk_config
from sitl.scenario import build_scenario
from sitl.simulate import simulate
from sitl.tuning import tuning_for

GAP_S = (40.0, 70.0)        # flight seconds with no rover data
DURATION_S = 90.0


@pytest.fixture(scope="module")
def sim():
    scn = dataclasses.replace(build_scenario("rtk"), duration_s=DURATION_S)
    return simulate(scn, 0)


def _restart_locks_after(epochs, t_s):
    """Lock times from 0 again at ``t_s`` (what a receiver that lost the signals reports)."""
    out = []
    for e in epochs:
        if e.t_gps < t_s:
            out.append(e)
            continue
        obs = tuple(dataclasses.replace(o, lock_time_s=min(o.lock_time_s, e.t_gps - t_s)) for o in e.observations)
        out.append(dataclasses.replace(e, observations=obs))
    return out


def _run(sim, rover, burst_s: float = 0.0) -> dict:
    """The engine as sitl.rtk_score runs it; the rover epochs after the gap held back until
    ``burst_s`` after its end (then all that arrived meanwhile in one go, as the service reads a
    receiver's backlog), the others 80 ms after their time.  Epoch outcomes with their true errors."""
    scn, tuning = sim.scenario, tuning_for(sim.scenario)
    eng = NavEngine(rtk_config(scn, tuning))
    for eph in sim.ephemerides:
        eng.process(eph)
    eng.process(sim.base)
    tr = sim.truth
    t0 = float(tr.t_gps[0])
    d_att, d_pos, d_vel = initial_errors(np.random.default_rng(10_000), tuning.p0, tr.r_e[0])
    eng.initialize(tr.t_gps[0], tr.r_e[0] + d_pos, tr.v_e[0] + d_vel, rotation_from_rotvec(d_att) @ tr.C_b_e[0],
                   tuning.p0)
    lat0, lon0, _ = ecef_to_geodetic(tr.r_e[0])
    up_e = -C_n_e(lat0, lon0)[:, 2]
    out = []

    def on_epoch(rep):
        d = eng.r_e - sim.truth_at(eng.t_gps)[0]
        out.append((rep.t_gps - t0, rep.fix_state, float(np.linalg.norm(d)),
                    float(np.linalg.norm(d - up_e * (d @ up_e)))))
    eng.on_epoch = on_epoch
    lat = tuning.gnss_latency_s
    release = [e.t_gps + lat if not GAP_S[1] <= e.t_gps - t0 < GAP_S[1] + burst_s
               else t0 + GAP_S[1] + burst_s for e in rover]
    i_rov = i_base = 0
    base = sim.base_epochs
    for s in sim.imu:
        while i_base < len(base) and base[i_base].t_gps + lat <= s.t_gps:
            eng.process(base[i_base])
            i_base += 1
        while i_rov < len(rover) and release[i_rov] <= s.t_gps:
            eng.process(rover[i_rov])
            i_rov += 1
        eng.process_imu(s)
    return {"epochs": out, "counters": dict(eng.counters)}


def _after_gap(r):
    return [e for e in r["epochs"] if e[0] >= GAP_S[1]]


def _link_outage(sim):
    t0 = float(sim.truth.t_gps[0])
    return [e for e in sim.rover_epochs if not GAP_S[0] <= e.t_gps - t0 < GAP_S[1]]


def test_a_link_outage_with_continuous_lock_keeps_the_ambiguities(sim):
    r = _run(sim, _link_outage(sim))
    c = r["counters"]
    print({k: v for k, v in c.items() if k.startswith("rtk")})
    assert c.get("rtk ambiguities kept through a data gap (lock time)", 0) >= 10
    after = _after_gap(r)
    assert after[0][1] == "fixed"                     # the first epoch after the gap
    fixed = [e for e in r["epochs"] if e[1] == "fixed"]
    assert not [e for e in fixed if e[2] > WRONG_FIX_M]
    assert np.sqrt(np.mean(np.square([e[3] for e in after]))) < 0.02


def test_a_loss_of_lock_in_the_gap_starts_the_ambiguities_again(sim):
    t0 = float(sim.truth.t_gps[0])
    r = _run(sim, _restart_locks_after(_link_outage(sim), t0 + GAP_S[1] - 1.0))
    c = r["counters"]
    assert c.get("rtk ambiguities kept through a data gap (lock time)", 0) == 0
    assert c.get("rtk ambiguities reset: slip flag / lock time / gap", 0) >= 10
    assert _after_gap(r)[0][1] == "float"
    assert not [e for e in r["epochs"] if e[1] == "fixed" and e[2] > WRONG_FIX_M]


def test_epochs_in_a_burst_after_the_gap_fix_at_once_and_right(sim):
    """The service read the receiver's backlog 3 s after the gap: four epochs at once, the first
    3 s late.  Each is predicted from the INS path corrected by the one before (the engine moves
    its history with every correction) and its rows are in the errors of now."""
    r = _run(sim, _link_outage(sim), burst_s=3.0)
    c = r["counters"]
    print({k: v for k, v in c.items() if k.startswith("rtk")})
    after = _after_gap(r)
    assert len(after) >= 15 and all(e[1] == "fixed" for e in after)
    assert not [e for e in r["epochs"] if e[1] == "fixed" and e[2] > WRONG_FIX_M]
    assert c.get("rtk wrong fixes dropped: phase residuals", 0) == 0
    assert np.sqrt(np.mean(np.square([e[3] for e in after]))) < 0.02
