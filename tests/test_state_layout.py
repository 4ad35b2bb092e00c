"""The error-state layout as named blocks (companion.nav.state_layout): indices by name, blocks
added and removed with their covariance, propagation by blocks equal to the dense product."""
import math

import numpy as np
import pytest

from companion.nav.earth import euler_to_dcm, geodetic_to_ecef, gravity_gradient_ecef
from companion.nav.engine import EngineConfig, NavEngine
from companion.nav.filter import LAYOUT, ErrorStateKalmanFilter, ProcessNoise
from companion.nav.state_layout import DEFAULT_LAYOUT, StateLayout, delete_block, insert_block

NOISE = ProcessNoise(3e-4, 3e-3, 1e-5, 1e-4, imu_time_offset_rw_s_per_sqrt_s=1e-4,
                     inter_system_bias_rw_m_per_sqrt_s=1e-2)


def test_standard_layout_names_and_indices():
    L = StateLayout.standard()
    assert L.names == ("attitude", "position", "velocity", "accel_bias", "gyro_bias", "clock", "clock_drift",
                       "dt_imu")
    assert L.n == 18 and L.n_core == 17
    assert L.slice("position") == L.pos == slice(3, 6) and L.slice("velocity") == L.vel == slice(6, 9)
    assert L.index("clock") == L.clk == 15 and L.index("clock_drift") == L.drift == 16
    assert L.index("dt_imu") == L.toff == 17
    assert [b.name for b in L.identity_blocks()] == ["dt_imu"] and L.extra_blocks() == ()
    assert L.clock_columns("E") == (15,)
    with pytest.raises(ValueError, match="3 states"):
        L.index("attitude")
    with pytest.raises(KeyError, match="no state block 'isb_E'"):
        L.slice("isb_E")
    with pytest.raises(RuntimeError, match="frozen"):
        DEFAULT_LAYOUT.add_block("amb G05 L1C", 1)
    assert LAYOUT is DEFAULT_LAYOUT and LAYOUT.n == 18


def test_inter_system_biases_are_configured_and_found_by_name():
    L = StateLayout.standard(("E", "C"))
    assert L.n == 20 and L.index("isb_E") == 18 and L.index("isb_C") == 19
    assert L.clock_columns("E") == (15, 18) and L.clock_columns("G") == (15,) and L.clock_columns("J") == (15,)
    assert [b.name for b in L.extra_blocks()] == ["isb_E", "isb_C"]
    assert StateLayout.standard(("R",)).index("isb_R") == 18         # GLONASS, when fused
    with pytest.raises(ValueError, match="expected one of R, E, C, J"):
        StateLayout.standard(("S",))
    with pytest.raises(ValueError, match="twice"):
        StateLayout.standard(("E", "E"))


def test_add_and_remove_blocks_keep_the_other_blocks_covariance():
    rng = np.random.default_rng(3)
    L0 = StateLayout.standard(("E",))
    A = rng.normal(size=(L0.n, L0.n))
    P0 = A @ A.T
    kf = ErrorStateKalmanFilter(P0, NOISE, layout=L0)
    assert kf.layout is not L0                     # the filter works on its own copy
    kf.add_block("amb G05 L1C", 1, 2.0)
    kf.add_block("amb G07 L1C L2W", 2, [3.0, 4.0], random_walk_psd=1e-6)
    L = kf.layout
    assert L0.n == 19 and L.n == 22
    assert L.index("amb G05 L1C") == 19 and L.slice("amb G07 L1C L2W") == slice(20, 22)
    assert np.array_equal(kf.P[:19, :19], P0)
    assert np.array_equal(np.diag(kf.P)[19:], [4.0, 9.0, 16.0])
    assert not np.any(kf.P[19:, :19]) and not np.any(kf.P[:19, 19:])
    # correlate the new states with the rest, then remove one in the middle: the others keep theirs
    B = rng.normal(size=(L.n, L.n))
    kf.P = B @ B.T
    before = kf.P.copy()
    isb, amb2 = L.index("isb_E"), L.slice("amb G07 L1C L2W")
    keep_before = before[np.ix_(np.r_[0:isb + 1, amb2], np.r_[0:isb + 1, amb2])]
    kf.remove_block("amb G05 L1C")
    L = kf.layout
    assert L.n == 21 and L.slice("amb G07 L1C L2W") == slice(19, 21) and L.index("isb_E") == isb
    assert np.array_equal(kf.P, keep_before)
    with pytest.raises(ValueError, match="cannot be removed"):
        kf.remove_block("dt_imu")
    with pytest.raises(ValueError, match="exists already"):
        kf.add_block("isb_E", 1, 1.0)
    # the helpers on their own
    P = np.arange(16.0).reshape(4, 4)
    Q = insert_block(P, 2, 1, 7.0)
    assert Q.shape == (5, 5) and Q[2, 2] == 7.0 and np.array_equal(delete_block(Q, 2, 1), P)


def _steps(rng, n_steps):
    """IMU-like inputs of a turning, accelerating vehicle (attitude, dv_e, gravity gradient)."""
    r = geodetic_to_ecef(0.6, 2.4, 100.0)
    G = gravity_gradient_ecef(r)
    for k in range(n_steps):
        C = euler_to_dcm(0.1 * math.sin(0.1 * k), 0.05, 0.02 * k)
        dv = np.array([0.01, -0.02, -0.049]) + 0.01 * rng.normal(size=3)
        yield C, dv, G


@pytest.mark.parametrize("dense_max", [0, ErrorStateKalmanFilter.DENSE_MAX_STATES])
def test_block_propagation_equals_the_dense_product(dense_max, monkeypatch):
    """With inter-system biases, dt_imu and 40 ambiguity states present (and with the block path
    forced for every size), P <- Phi P Phi^T + Q by blocks equals the dense product, also after a
    block is added or removed between steps."""
    monkeypatch.setattr(ErrorStateKalmanFilter, "DENSE_MAX_STATES", dense_max)
    rng = np.random.default_rng(11)
    L0 = StateLayout.standard(("E", "C", "J"))
    A = rng.normal(size=(L0.n, L0.n)) * 0.1
    kf = ErrorStateKalmanFilter(A @ A.T + np.eye(L0.n), NOISE, layout=L0)
    for i in range(40):
        kf.add_block(f"amb {i}", 1, 1.0 + i, random_walk_psd=1e-4 * (i % 3))
    M = rng.normal(size=(kf.layout.n, kf.layout.n)) * 0.05
    kf.P = kf.P + M @ M.T                        # cross-covariances everywhere
    P_ref = kf.P.copy()
    for k, (C, dv, G) in enumerate(_steps(rng, 60)):
        tau = 0.005 if k < 30 else 0.0025
        kf.propagate(C, dv, G, tau)
        Phi, Q = kf.transition_matrix(), kf.process_noise_matrix()
        assert np.array_equal(Phi[kf.layout.n_core:, kf.layout.n_core:], np.eye(kf.layout.n - kf.layout.n_core))
        P_ref = Phi @ P_ref @ Phi.T + Q
        assert np.abs(kf.P - P_ref).max() <= 1e-12 * np.abs(P_ref).max()
        if k == 20:
            kf.remove_block("amb 7")
            keep = np.r_[0:kf.layout.n_core + 4 + 7, kf.layout.n_core + 4 + 8:P_ref.shape[0]]
            P_ref = P_ref[np.ix_(keep, keep)]
        if k == 40:
            kf.add_block("amb new", 2, 5.0, random_walk_psd=1e-3)
            P_ref = insert_block(P_ref, P_ref.shape[0], 2, 25.0)
    assert kf.layout.n == 17 + 1 + 3 + 40 - 1 + 2
    assert np.all(np.diag(kf.P) > 0)


def test_dense_path_for_the_default_layout_is_the_old_product():
    """The standard layout is small: the dense product, exactly as before the layout existed."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(18, 18))
    kf = ErrorStateKalmanFilter(A @ A.T, NOISE)
    P = kf.P.copy()
    for C, dv, G in _steps(rng, 5):
        kf.propagate(C, dv, G, 0.005)
        Phi, Q = kf.transition_matrix(), kf.process_noise_matrix()
        P = (Phi @ P) @ Phi.T + Q
    assert np.array_equal(kf.P, P)


def _engine(**kw):
    from tests.test_engine import _straight_line_imu
    t0, r0, v, C, samples, _ = _straight_line_imu(seconds=0.5)
    eng = NavEngine(EngineConfig(noise=NOISE, **kw))
    P0 = dict(att_rad=0.01, pos_m=1.0, vel_mps=0.1, ba_mps2=0.01, bg_radps=1e-3)
    eng.initialize(t0, r0, v, C, P0)
    return eng, samples


def test_engine_with_inter_system_biases_and_run_time_blocks():
    eng, samples = _engine(inter_system_biases=("E",), inter_system_bias_sigma_m=30.0)
    L = eng.layout
    assert L.n == 19 and eng.kf.P[L.index("isb_E"), L.index("isb_E")] == 900.0
    assert set(eng.block_states) == {"isb_E"}
    for s in samples[:50]:
        eng.process_imu(s)
    eng.add_state_block("amb G05 L1C", 1, 10.0, value=123.0)
    P_before = eng.kf.P.copy()
    for s in samples[50:100]:
        eng.process_imu(s)
    assert eng.kf.P.shape == (20, 20) and eng.kf.P[19, 19] == P_before[19, 19]   # a constant
    # feedback reaches the extra blocks by name
    dx = np.zeros(eng.layout.n)
    dx[eng.layout.index("isb_E")] = 2.5
    dx[eng.layout.index("amb G05 L1C")] = -1.0
    eng._feedback(dx)
    assert eng.block_states["isb_E"][0] == 2.5 and eng.block_states["amb G05 L1C"][0] == 122.0
    ins = eng.ins_at(eng.t_gps)
    assert ins.block_states["isb_E"][0] == 2.5
    eng.remove_state_block("amb G05 L1C")
    assert eng.layout.n == 19 and "amb G05 L1C" not in eng.block_states
    # a re-initialisation rebuilds the layout from the configuration
    eng.add_state_block("amb G09 L1C", 1, 10.0)
    eng.initialize(eng.t_gps, eng.r_e, eng.v_e, eng.C_b_e,
                   dict(att_rad=0.01, pos_m=1.0, vel_mps=0.1, ba_mps2=0.01, bg_radps=1e-3))
    assert eng.layout.names[-1] == "isb_E" and set(eng.block_states) == {"isb_E"}


def test_default_engine_layout_is_the_standard_one():
    eng, _ = _engine()
    assert eng.layout.names == DEFAULT_LAYOUT.names and eng.block_states == {}
