"""Backward and combined post-processed RTK (``companion gnss --mode rtk --direction``): the
backward pass on real data, its handling of the receivers' loss-of-lock flags (a flag at epoch k
is a slip between k - 1 and k: going backward it resets at k - 1), and the per-epoch combination
of the two passes (companion.gnss.rtk_combine)."""
from __future__ import annotations

import numpy as np
import pytest

from companion.gnss import rtk_post
from companion.gnss.rinex_obs import read_rinex_obs
from companion.gnss.rtk import Q_FIX, Q_FLOAT, RtkSolution
from companion.gnss.rtk_combine import combine
from companion.gnss.rtk_post import solve_rtk_rinex
from tests.test_rtk_geonet import BASE, NAV, REF_0759, ROVER, _rms, slipped_reader


def _sol(t, r, sigma, q):
    return RtkSolution(t, np.asarray(r, float), np.eye(3) * sigma ** 2, q, 8, 5.0 if q == Q_FIX else 0.0,
                       10 if q == Q_FIX else 0, 12, 0.99)


def test_the_combination_rules():
    c = {}
    f = [_sol(0, [0, 0, 0], 0.005, Q_FIX), _sol(1, [0, 0, 0], 0.005, Q_FIX), _sol(2, [0, 0, 0], 0.005, Q_FIX),
         _sol(3, [0, 0, 0], 0.3, Q_FLOAT), _sol(4, [0, 0, 0], 0.3, Q_FLOAT), _sol(5, [0, 0, 0], 0.005, Q_FIX)]
    b = [_sol(0, [0.004, 0, 0], 0.005, Q_FIX), _sol(1, [0.05, 0, 0], 0.005, Q_FIX), _sol(2, [0.2, 0, 0], 0.3, Q_FLOAT),
         _sol(3, [3.0, 0, 0], 0.1, Q_FIX), _sol(4, [0.1, 0, 0], 0.2, Q_FLOAT), _sol(6, [0, 0, 0], 0.2, Q_FLOAT)]
    out = {s.t_gps: s for s in combine(f, b, c)}
    assert sorted(out) == [0, 1, 2, 3, 4, 5, 6]
    # both fixed alike: fixed, their mean, no smaller covariance than either (same observations)
    assert out[0].quality == Q_FIX and out[0].r_e[0] == pytest.approx(0.002) and out[0].cov_e[0, 0] == pytest.approx(0.005 ** 2)
    # two fixes 5 cm apart with 5-mm sigmas: float, covering both
    assert out[1].quality == Q_FLOAT and out[1].cov_e[0, 0] >= 0.025 ** 2
    # a fix and a consistent float: the fix; a fix 3 m from a 0.3-m float: the float
    assert out[2].quality == Q_FIX and out[2] is f[2]
    assert out[3].quality == Q_FLOAT and out[3] is f[3]
    # two floats: the tighter one; an epoch of one pass only: that pass
    assert out[4] is b[4] and out[5] is f[5] and out[6] is b[5]
    assert c == {"combined: both passes fixed": 1, "combined: the two passes' fixes disagree (float)": 1,
                 "combined: one pass fixed": 1, "combined: a fix disagrees with the other pass's float (float)": 1,
                 "combined: both passes float": 1, "combined: one pass only": 2}


@pytest.mark.real_data
def test_geonet_backward_and_combined():
    """Measured: forward 120/120 fixed at 0.0110 m, backward 120/120 at 0.0115 m, combined 120/120
    at 0.0111 m (the two passes at most 2.3 cm apart on an epoch)."""
    fwd, _ = solve_rtk_rinex(ROVER, BASE, [NAV])
    bwd, _ = solve_rtk_rinex(ROVER, BASE, [NAV], direction="backward")
    comb, info = solve_rtk_rinex(ROVER, BASE, [NAV], direction="combined")
    assert [s.t_gps for s in bwd] == sorted(s.t_gps for s in bwd) == [s.t_gps for s in fwd]
    for sols in (bwd, comb):
        fixed = [s.r_e for s in sols if s.quality == 1]
        assert len(fixed) >= 115 and _rms(fixed) <= 0.012
    # the backward pass fixes the last epochs first: from its own start
    assert bwd[-1].quality == 1
    assert info["direction"] == "combined" and info["counters"]["combined: both passes fixed"] >= 115
    assert info["counters"]["forward: fixed epochs"] == sum(s.quality == 1 for s in fwd)


@pytest.mark.real_data
def test_a_flagged_slip_resets_the_epoch_before_it_going_backward(monkeypatch):
    """9 L1 and 7 L2 cycles added to G20's rover phase from epoch 60 on (a slip of 3 mm in the
    geometry-free combination, under its 5-cm test), with the receiver's loss-of-lock flag at epoch
    60: forward the flag resets at 60, backward at 59.  Measured: both 120 fixed, at most 3.1 cm
    off; with the flag applied at the epoch that carries it (going backward, one epoch after the
    slip) the backward pass carries the slip into epochs 0-59 and fixes none of them."""
    t_slip = read_rinex_obs(ROVER)[1][60].t_gps
    monkeypatch.setattr(rtk_post, "read_rinex_obs",
                        slipped_reader(read_rinex_obs, t_slip, "G20", {"L1C": 9.0, "L2W": 7.0}, flag=True))
    for direction in ("forward", "backward"):
        sols, info = solve_rtk_rinex(ROVER, BASE, [NAV], direction=direction)
        fixed = [s for s in sols if s.quality == 1]
        worst = max(np.linalg.norm(s.r_e - REF_0759) for s in fixed)
        print(f"{direction}: {len(fixed)} fixed, at most {worst:.3f} m off, {info['counters'].get('slips: loss of lock flag')} flags")
        assert info["counters"].get("slips: geometry-free", 0) == 0          # the GF test cannot see it
        assert info["counters"]["slips: loss of lock flag"] >= 1
        assert len(fixed) >= 110 and worst < 0.06


def test_the_cli_writes_the_solution_type_and_refuses_it_outside_rtk(tmp_path, capsys):
    from companion.cli import main
    pos = tmp_path / "c.pos"
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(BASE), "--mode", "rtk",
                 "--direction", "combined", "--pos", str(pos)]) == 0
    assert "% solution  : combined" in pos.read_text()
    assert "companion gnss rtk (combined): 120/120 epochs solved" in capsys.readouterr().out
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--direction", "backward"]) == 2
    assert "applies to --mode rtk" in capsys.readouterr().err
