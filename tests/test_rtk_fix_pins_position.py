"""A validated integer fix must pin the position (companion.nav.rtk_update, ``max_fixed_sigma_3d_m``).

Seen in a loaded live rtk-gec flight: right after a re-initialisation 31-64 DD ambiguities passed
the ratio test (3.1-6.0) while the position stayed at 0.8 m sigma after the hold, 0.1-1.3 m off
truth, and every solution said "fixed".  Here: integers that are well determined but carry no
information on the position (no correlation with it) must not make a fix; the same integers tied
to the position must."""
from __future__ import annotations

import math
from collections import Counter
from types import SimpleNamespace

import numpy as np

from companion.nav.rtk_update import RtkEpochRows, RtkUpdate, RtkUpdateConfig

N_AMB = 8
POS, VEL = slice(0, 3), slice(3, 6)


def _engine(P):
    return SimpleNamespace(kf=SimpleNamespace(P=P), layout=SimpleNamespace(pos=POS, vel=VEL), t_gps=100.0)


def _problem(tied: bool):
    """States: position (3), velocity (3), N_AMB DD ambiguities (cycles), 0.03 cycles off integers.
    ``tied``: the covariance after one epoch of DD phase (3 mm) and code (5 cm) rows on a random
    geometry, so the ambiguities are known through the position; else the same ambiguity
    variances with no correlation to a position left at 0.8 m."""
    rng = np.random.default_rng(3)
    n = 6 + N_AMB
    amb = slice(6, n)
    lam = 0.19
    if tied:
        G = rng.normal(size=(N_AMB, 3))                         # DD line-of-sight differences
        H = np.zeros((2 * N_AMB, n))
        H[:N_AMB, POS] = G
        H[:N_AMB, amb] = lam * np.eye(N_AMB)
        H[N_AMB:, POS] = G
        R_inv = np.diag([1 / 0.003 ** 2] * N_AMB + [1 / 0.05 ** 2] * N_AMB)
        info = np.diag([1 / 10.0 ** 2] * 3 + [1 / 0.05 ** 2] * 3 + [1 / 30.0 ** 2] * N_AMB) + H.T @ R_inv @ H
        P = np.linalg.inv(info)
        P = 0.5 * (P + P.T)
    else:
        P = np.zeros((n, n))
        P[VEL, VEL] = np.eye(3) * 0.05 ** 2
        P[POS, POS] = np.eye(3) * 0.8 ** 2
        P[amb, amb] = np.eye(N_AMB) * 0.05 ** 2
    a = np.round(rng.normal(size=N_AMB) * 10) + rng.uniform(-0.03, 0.03, N_AMB)
    Tc = np.eye(N_AMB)
    rows = RtkEpochRows(t_gps=100.0, z=np.zeros(N_AMB), H=np.zeros((N_AMB, n)), R=np.eye(N_AMB) * 0.003 ** 2,
                        kinds=["phase"] * N_AMB, labels=[f"dd{i}" for i in range(N_AMB)], refs={},
                        amb_pairs=[], sd_resid={})
    return _engine(P), rows, P[:, amb], Tc, a, P[amb, amb]


def _try(tied: bool, cfg=RtkUpdateConfig()):
    counters = Counter()
    rtk = RtkUpdate(cfg, counters)
    eng, rows, P_idx, Tc, a, Qa = _problem(tied)
    return rtk._try(eng, rows, np.zeros(eng.kf.P.shape[0]), P_idx, Tc, a, Qa), counters


def test_integers_that_leave_the_position_at_decimetres_are_no_fix():
    out, counters = _try(tied=False)
    assert out is None
    assert counters["rtk fixes rejected: position not pinned"] == 1


def test_the_same_integers_tied_to_the_position_fix():
    out, counters = _try(tied=True)
    assert out is not None, dict(counters)
    res, afix = out
    assert res.ratio >= RtkUpdateConfig().ratio_threshold
    assert counters["rtk fixes rejected: position not pinned"] == 0


def test_without_the_guard_the_untied_integers_would_have_fixed():
    """The case above is a real test of the guard: with it switched off the ratio test passes."""
    out, _ = _try(tied=False, cfg=RtkUpdateConfig(max_fixed_sigma_3d_m=math.inf))
    assert out is not None
