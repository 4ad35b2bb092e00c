"""Carrier-phase RTK inside the engine (companion.nav.rtk_update) on the simulated ``rtk`` scenario
(sitl.scenario: short baseline, dual-frequency rover, slips, a 30-s outage)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from companion.messages import GnssEpoch
from companion.nav.earth import rotation_from_rotvec
from companion.nav.measurements import antenna_state
from sitl.rtk_score import run_rtk


@pytest.fixture(scope="module")
def short_run():
    return run_rtk(seed=0, duration_s=20.0, keep_engine=True)


def _rows_at(eng, epoch, ins):
    r_ant, v_ant, l_e = antenna_state(ins, eng.lever_arm_b)
    return eng.rtk.build(eng, eng.rtk.observe(eng, epoch, r_ant), l_e, v_ant)


def test_dd_jacobians_match_finite_differences(short_run):
    eng, sim = short_run["engine"], short_run["sim"]
    epoch = [e for e in sim.rover_epochs if eng.ins_at(eng.imu_time_of(e)) is not None][-1]
    t_tag = eng.imu_time_of(epoch)
    ins = eng.ins_at(t_tag)
    rows = _rows_at(eng, epoch, ins)
    L = eng.layout
    assert rows is not None and rows.kinds.count("phase") >= 8 and rows.kinds.count("code") >= 8
    checked = 0
    # position (m) and attitude (rad), each axis: z(x + d) - z(x) = -H d
    for blk, h in ((L.pos, 0.5), (L.att, 2e-3)):
        for ax in range(3):
            d = np.zeros(3)
            d[ax] = h
            if blk == L.pos:
                p = dataclasses.replace(ins, r_e=ins.r_e + d)
            else:
                p = dataclasses.replace(ins, C_b_e=rotation_from_rotvec(d) @ ins.C_b_e)
            dz = _rows_at(eng, epoch, p).z - rows.z
            H = rows.H[:, blk][:, ax]
            np.testing.assert_allclose(dz, -H * h, rtol=2e-3, atol=2e-6)
            checked += 1
    # IMU time-tag offset: the measurement is predicted from the INS at tag t - dt_imu
    dt = 2e-3
    dz = _rows_at(eng, epoch, eng.ins_at(t_tag - dt)).z - rows.z
    np.testing.assert_allclose(dz, -rows.H[:, L.toff] * dt, rtol=2e-2, atol=5e-5)
    # one ambiguity (cycles)
    key, a = next(iter(eng.rtk.amb.items()))
    eng.block_states[a.name] = eng.block_states[a.name] + 1.0
    try:
        dz = _rows_at(eng, epoch, ins).z - rows.z
    finally:
        eng.block_states[a.name] = eng.block_states[a.name] - 1.0
    col = rows.H[:, L.index(a.name)]
    assert np.count_nonzero(col) >= 1          # its phase row (a reference: every row of its signal)
    np.testing.assert_allclose(dz, -col, rtol=1e-9, atol=1e-9)
    # one satellite's differential ionosphere (m on L1): -(f1/f)^2 on its phase rows, + on its code
    sat, name = next(iter(eng.rtk.iono.items()))
    eng.block_states[name] = eng.block_states[name] + 0.01
    try:
        dz = _rows_at(eng, epoch, ins).z - rows.z
    finally:
        eng.block_states[name] = eng.block_states[name] - 0.01
    col = rows.H[:, L.index(name)]
    np.testing.assert_allclose(dz, -col * 0.01, rtol=1e-9, atol=1e-12)
    l2 = [i for i, lab in enumerate(rows.labels) if lab.startswith(sat + "-") and " L2W phase" in lab]
    if l2:      # the L2 phase row: (154/120)^2 of the delay on L1, advanced
        assert col[l2[0]] == pytest.approx(-(154.0 / 120.0) ** 2)
    assert np.count_nonzero(col) >= 2
    assert checked == 6
    # the DD covariance: positive definite, the reference's share off the diagonal
    assert np.all(np.linalg.eigvalsh(rows.R) > 0)
    assert rows.R[0, 1] > 0


@pytest.fixture(scope="module")
def run_175():
    """The first 175 s of seed 0 (both early slips, the 30-s outage, 15 s after it)."""
    return run_rtk(seed=0, duration_s=175.0)


def test_rtk_scenario_fixes_within_30_s_refixes_within_10_s_and_never_wrong(run_175):
    r = run_175
    print({k: r[k] for k in ("first_fix_s", "rms_h_after_first_fix_m", "rms_h_fixed_epochs_m",
                             "refix_after_outage_s", "wrong_fixes", "fixed_epochs", "n_epochs")})
    assert r["first_fix_s"] <= 30.0
    assert r["refix_after_outage_s"] and max(r["refix_after_outage_s"]) <= 10.0
    assert r["wrong_fixes"] == 0
    assert r["rms_h_fixed_epochs_m"] <= 0.02
    assert r["counters"]["rtk ambiguities reset: slip flag / lock time / gap"] >= 2    # the flagged slips


@pytest.mark.xfail(reason="issue 12: the RMS_h after the first fix counts the two float epochs after the 30-s "
                          "outage (1.0 m off with a 0.9-2.0 m 3-D sigma, code only) before the re-fix: 0.12 m "
                          "offline; through the service (python -m sitl fly --scenario rtk) 0.0153 m",
                   strict=False)
def test_rtk_scenario_rms_after_the_first_fix(run_175):
    assert run_175["rms_h_after_first_fix_m"] <= 0.02


def test_without_the_ionosphere_states_the_float_fixes_later(run_175):
    """The scenario's rover-only ionosphere (2 mm zenith, 900 s) biases a float that has no state
    for it: measured 61 s to the first fix and 82 of 144 epochs fixed without, 13 s and 130 with."""
    from sitl.rtk_score import rtk_config
    from sitl.scenario import build_scenario
    from sitl.tuning import tuning_for
    scn = build_scenario("rtk")
    cfg = dataclasses.replace(rtk_config(scn, tuning_for(scn)), rtk_iono_states=False)
    off = run_rtk(seed=0, duration_s=175.0, cfg=cfg)
    assert off["wrong_fixes"] == 0
    assert off["first_fix_s"] > run_175["first_fix_s"] + 10.0
    assert off["fixed_epochs"] < run_175["fixed_epochs"]


def _strip_slip_flags(epochs):
    """The receiver's slip flags cleared and lock times kept growing: only the INS can see a slip."""
    first = {}
    out = []
    for e in epochs:
        obs = []
        for o in e.observations:
            t0 = first.setdefault((o.sat, o.signal), e.t_gps)
            obs.append(dataclasses.replace(o, loss_of_lock=False, lock_time_s=e.t_gps - t0))
        out.append(GnssEpoch(e.t_gps, tuple(obs), e.source))
    return out


def test_unflagged_slips_are_caught_by_the_ins_predicted_phase():
    r = run_rtk(seed=0, duration_s=110.0, rover_hook=_strip_slip_flags)
    c = r["counters"]
    print({k: v for k, v in c.items() if k.startswith("rtk")})
    # slips of 1 and -5 cycles at 60 s and 95 s, on both frequencies
    assert c.get("rtk slips detected: INS-predicted phase", 0) >= 4
    assert c.get("rtk ambiguities reset: slip flag / lock time / gap", 0) == 0
    assert r["wrong_fixes"] == 0
    assert r["rms_h_after_first_fix_m"] <= 0.02


def test_a_wrong_fix_is_dropped_at_once():
    """Move two held ambiguities by one cycle, and their slip-test memory with them: what a wrong
    set of integers looks like to the filter (no jump in the phase, rows that disagree).  The fix
    is dropped at once, and the filter fixes again, correctly."""
    done = []

    def knock(eng, t_s):
        rtk = eng.rtk
        if done or t_s < 40.0 or not rtk.held:
            return
        keys = sorted(k for k in rtk.held if k[1] == "L1C")[:2]
        for key in keys:
            a = rtk.amb[key]
            eng.block_states[a.name] = eng.block_states[a.name] + 1.0
            t_prev, e = rtk._resid[key]
            rtk._resid[key] = (t_prev, e - a.wavelength_m)
        done.append(t_s)

    r = run_rtk(seed=0, duration_s=70.0, hook=knock)
    c = r["counters"]
    print({k: v for k, v in c.items() if k.startswith("rtk")})
    assert done
    assert c.get("rtk wrong fixes dropped: phase residuals", 0) >= 1
    assert c.get("rtk slips detected: INS-predicted phase", 0) == 0
    fixed_after = [e for e in r["epochs"] if e[0] > done[0] + 10.0 and e[1] == "fixed"]
    assert fixed_after and all(e[4] < 0.1 for e in fixed_after)
    wrong = [e for e in r["epochs"] if e[1] == "fixed" and e[4] > 0.1]
    assert not wrong


def test_ionosphere_blocks_live_and_die_with_their_satellites_ambiguities():
    """Through slips and the 30-s outage (every ambiguity started again at the first epoch after
    it, the ionosphere kept, its variance grown): after every epoch exactly the satellites with an
    ambiguity have an ionosphere block, each in the layout."""
    seen = {"epochs": 0, "bad": [], "max_iono": 0}

    def hook(eng, t_s):
        n = eng.counters["gnss epochs"]
        if n == seen["epochs"] or eng.rtk is None:
            return
        seen["epochs"] = n
        sats = {k[0] for k in eng.rtk.amb}
        if set(eng.rtk.iono) != sats or not all(name in eng.block_states for name in eng.rtk.iono.values()):
            seen["bad"].append((round(t_s, 1), sorted(sats ^ set(eng.rtk.iono))))
        seen["max_iono"] = max(seen["max_iono"], len(eng.rtk.iono))

    r = run_rtk(seed=0, duration_s=175.0, hook=hook)
    assert seen["bad"] == []
    assert seen["max_iono"] >= 6
    assert r["counters"]["rtk ambiguities reset: slip flag / lock time / gap"] >= 10     # the outage
