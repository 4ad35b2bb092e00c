"""Horizontal protection level (companion.nav.protection): the K-factor bound holds at its stated
probability on Gaussian errors, solution separation finds a biased satellite, the HPL follows the
covariance while coasting, and the engine's leave-one-out terms are those of explicit subsets."""
import math

import numpy as np
import pytest

from companion.nav.chi2 import chi2_ppf
from companion.nav.protection import (
    ProtectionLevel,
    k_factor_h,
    sigma_major_m,
    solution_separation,
)


def _random_cov(rng, sig_lo=0.2, sig_hi=3.0):
    a = rng.uniform(sig_lo, sig_hi, 2)
    th = rng.uniform(0, math.pi)
    R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
    return R @ np.diag(a ** 2) @ R.T


def test_k_factor_is_the_rayleigh_quantile():
    for p in (1e-2, 1e-3, 1e-5, 1e-7):
        assert k_factor_h(p) == pytest.approx(math.sqrt(-2.0 * math.log(p)), rel=1e-9)
    with pytest.raises(ValueError):
        k_factor_h(0.0)


@pytest.mark.parametrize("p", [1e-2, 1e-3])
def test_bound_holds_at_the_stated_probability_monte_carlo(p):
    """Circular errors exceed K sigma at the stated rate (the bound is tight there); elongated
    ellipses exceed K sigma_major less often (conservative), never more (binomial 4-sigma limits)."""
    rng = np.random.default_rng(1)
    n = 2_000_000
    k = k_factor_h(p)
    e = rng.standard_normal((n, 2))
    frac = float(np.mean(np.hypot(e[:, 0], e[:, 1]) > k))
    tol = 4.0 * math.sqrt(p * (1 - p) / n)
    assert abs(frac - p) < tol, (frac, p)
    # random ellipses: correlated 2-D Gaussian errors, bound on the major axis
    worst = 0.0
    for _ in range(20):
        P = _random_cov(rng)
        Lc = np.linalg.cholesky(P)
        x = rng.standard_normal((n // 20, 2)) @ Lc.T
        frac = float(np.mean(np.hypot(x[:, 0], x[:, 1]) > k * sigma_major_m(P)))
        worst = max(worst, frac)
    assert worst <= p + 4.0 * math.sqrt(p / (n // 20)), worst


def test_sigma_major_is_the_largest_eigenvalue():
    rng = np.random.default_rng(2)
    for _ in range(50):
        P = _random_cov(rng)
        assert sigma_major_m(P) == pytest.approx(math.sqrt(np.linalg.eigvalsh(P).max()), rel=1e-12)


def _epoch(rng, n_sat=8, sigma_pr=0.8, prior_pos_m=2.0):
    """Synthetic pseudorange epoch: state = (north, east, down, clock), unit line-of-sight rows."""
    az = rng.uniform(0, 2 * math.pi, n_sat)
    el = rng.uniform(math.radians(15), math.radians(80), n_sat)
    los = np.c_[np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), -np.sin(el)]
    H = np.c_[-los, np.ones(n_sat)]
    P = np.diag([prior_pos_m ** 2] * 3 + [30.0 ** 2])
    r = np.full(n_sat, sigma_pr ** 2)
    C_h = np.zeros((2, 4))
    C_h[0, 0] = C_h[1, 1] = 1.0
    return H, P, r, C_h


def _update(H, z, r, P):
    S = H @ P @ H.T + np.diag(r)
    K = P @ H.T @ np.linalg.inv(S)
    return K @ z, P - K @ H @ P


def test_separation_equals_explicit_leave_one_out_updates():
    rng = np.random.default_rng(3)
    H, P, r, C_h = _epoch(rng)
    z = rng.standard_normal(len(r)) * np.sqrt(r)
    ss = solution_separation(H, z, r, P, C_h, k_detect=3.29)
    dx0, P0 = _update(H, z, r, P)
    assert np.allclose(ss.P_h_post, C_h @ P0 @ C_h.T)
    for i in range(len(z)):
        keep = np.arange(len(z)) != i
        dxi, Pi = _update(H[keep], z[keep], r[keep], P)
        delta = C_h @ (dx0 - dxi)
        assert ss.separation_m[i] == pytest.approx(np.linalg.norm(delta), rel=1e-8, abs=1e-12)
        assert np.allclose(ss.D_h[i], C_h @ (Pi - P0) @ C_h.T, atol=1e-12)


def test_solution_separation_detects_a_biased_satellite():
    rng = np.random.default_rng(4)
    detected_right = 0
    for _ in range(50):
        H, P, r, C_h = _epoch(rng, n_sat=9)
        z = rng.standard_normal(len(r)) * np.sqrt(r)
        clean = solution_separation(H, z, r, P, C_h, k_detect=math.sqrt(chi2_ppf(0.999, 1)))
        bad = int(rng.integers(len(r)))
        zb = z.copy()
        zb[bad] += 15.0                     # a 15-m pseudorange bias (~19 sigma)
        ss = solution_separation(H, zb, r, P, C_h, k_detect=math.sqrt(chi2_ppf(0.999, 1)))
        assert ss.detected
        detected_right += ss.worst == bad
        assert ss.test_ratio[bad] > 3.0 and ss.test_ratio[bad] > 2.0 * np.max(clean.test_ratio)
    assert detected_right == 50


def test_clean_epochs_rarely_alarm():
    rng = np.random.default_rng(5)
    alarms = 0
    n = 400
    for _ in range(n):
        H, P, r, C_h = _epoch(rng, n_sat=8)
        z = rng.multivariate_normal(np.zeros(len(r)), H @ P @ H.T + np.diag(r))
        alarms += solution_separation(H, z, r, P, C_h, k_detect=math.sqrt(chi2_ppf(0.999, 1))).detected
    assert alarms / n < 0.03          # 8 rows at 1e-3 each: ~0.8 % expected


def test_protection_level_covers_an_undetected_bias_and_grows_while_coasting():
    rng = np.random.default_rng(6)
    H, P, r, C_h = _epoch(rng, n_sat=7)
    pl = ProtectionLevel(integrity_risk=1e-5, missed_detection=1e-3, k_detect=math.sqrt(chi2_ppf(0.999, 1)))
    z = np.zeros(len(r))
    ss = pl.epoch(H, z, r, P, C_h, 100.0)
    lv = pl.levels(ss.P_h_post)
    assert lv.hpl_m >= lv.hpl_cov_m > 0 and lv.hpl_ss_m > 0 and lv.ss_rows == 7
    # the largest bias on each satellite that the separation test (the gate) lets through moves the
    # all-in-view horizontal solution by at most T_i <= HPL
    for i in range(len(r)):
        S = H @ P @ H.T + np.diag(r)
        Lm = np.linalg.inv(S)
        b = 0.999 * ss.threshold_m[i] / np.linalg.norm(C_h @ P @ H.T @ Lm[:, i])
        zb = z.copy()
        zb[i] = b
        dx, _ = _update(H, zb, r, P)
        assert solution_separation(H, zb, r, P, C_h, pl.k_detect).test_ratio[i] == pytest.approx(0.999)
        assert np.linalg.norm(C_h @ dx) <= ss.threshold_m[i] + 1e-9 <= lv.hpl_m
    # coasting: the covariance grows, the HPL with it (the held separation terms stay)
    grown = ss.P_h_post * 16.0
    lv2 = pl.levels(grown)
    assert lv2.hpl_cov_m == pytest.approx(4.0 * lv.hpl_cov_m)
    assert lv2.hpl_m == max(lv2.hpl_cov_m, lv2.hpl_ss_m) > 2.0 * lv.hpl_m
    pl.reset()
    assert math.isnan(pl.levels(grown).hpl_ss_m)


def test_engine_hpl_follows_the_covariance_while_coasting_and_uses_only_fused_pseudoranges():
    """In the engine: no GNSS -> the HPL is the covariance part and grows with the propagated
    covariance; a pseudorange epoch's separation terms are built from the rows it fused (a
    rejected row is left out) and cleared by a re-initialisation."""
    from companion.messages import ImuSample
    from companion.nav.earth import C_n_e, geodetic_to_ecef
    from companion.nav.engine import EngineConfig, NavEngine
    from companion.nav.filter import (
        LAYOUT,
        MeasurementBatch,
        ProcessNoise,
        UpdateReport,
    )
    from companion.nav.measurements import InsPoint
    from companion.nav.strapdown import invert_step
    lat, lon = math.radians(35.0), math.radians(139.0)
    r0 = geodetic_to_ecef(lat, lon, 100.0)
    C = C_n_e(lat, lon)
    v = C @ np.array([10.0, 0.0, 0.0])
    eng = NavEngine(EngineConfig(noise=ProcessNoise(3e-4, 2e-3, 1e-5, 1e-4)))
    t0 = 1.4e9
    eng.initialize(t0, r0, v, C, {"tilt_rad": 1e-2, "heading_rad": 2e-2, "pos_m": 0.5, "vel_mps": 0.1, "ba_mps2": 0.05,
                                      "bg_radps": 1e-3})
    s0 = eng.solution()
    hpl0 = s0.extras["hpl_m"]
    assert hpl0 == s0.extras["hpl_cov_m"] == pytest.approx(k_factor_h(1e-5) * 0.5, rel=1e-6)
    assert math.isnan(s0.extras["hpl_ss_m"])
    r, tau = r0, 0.005
    for k in range(2000):                                   # 10 s of inertial-only navigation
        dth, dv = invert_step(r, v, C, v, C, tau)
        eng.process_imu(ImuSample(t0 + (k + 1) * tau, tau, dth, dv))
        r = r + v * tau
    s1 = eng.solution()
    Ch = C.T[0:2]
    P_h = Ch @ eng.kf.P[LAYOUT.pos, LAYOUT.pos] @ Ch.T
    assert s1.extras["hpl_m"] == pytest.approx(k_factor_h(1e-5) * sigma_major_m(P_h), rel=1e-9)
    assert s1.extras["hpl_m"] > 1.5 * hpl0
    # a pseudorange epoch with one rejected row: the separation covers the fused rows only
    rng = np.random.default_rng(7)
    m = 7
    H = np.zeros((m, LAYOUT.n))
    los = rng.standard_normal((m, 3))
    los /= np.linalg.norm(los, axis=1)[:, None]
    H[:, LAYOUT.pos] = -los
    H[:, LAYOUT.clk] = 1.0
    b = MeasurementBatch("pseudorange", [f"G{i:02d}" for i in range(m)], rng.standard_normal(m), H, np.ones(m))
    acc = np.ones(m, bool)
    acc[3] = False
    rep = UpdateReport("pseudorange", b.labels, b.z, np.ones(m), np.zeros(m), acc)
    ins = InsPoint(eng.t_gps, eng.r_e, eng.v_e, eng.C_b_e, np.zeros(3), 0.0, 0.0)
    eng._separation(ins, [b], [rep], eng.t_gps)
    assert eng.protection.last.labels == [lab for i, lab in enumerate(b.labels) if i != 3]
    s2 = eng.solution()
    assert s2.extras["hpl_m"] == max(s2.extras["hpl_cov_m"], s2.extras["hpl_ss_m"])
    assert s2.extras["hpl_ss_m"] > 0
    eng.initialize(eng.t_gps, eng.r_e, eng.v_e, eng.C_b_e, {"att_rad": 1e-2, "pos_m": 0.5, "vel_mps": 0.1, "ba_mps2": 0.05,
                                                                 "bg_radps": 1e-3})
    assert math.isnan(eng.solution().extras["hpl_ss_m"])
