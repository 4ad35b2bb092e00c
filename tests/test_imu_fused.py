"""The fused IMU step (companion.nav.imu_fused) against the readable pure-Python path on the same
flight, and the batch entry against one call per sample, to the bit, through the rare branches
too (a time gap, a spike the screen bridges, a repeated and an invalid sample)."""
import dataclasses

import numpy as np
import pytest

from companion.nav import engine as engine_module
from companion.nav import imu_kernel

pytest.importorskip("numba")
pytestmark = pytest.mark.skipif(imu_kernel.compiled() is None, reason="kernels disabled (COMPANION_NUMBA=0)")


@pytest.fixture(scope="module")
def workload():
    from sitl import bench
    _, sim, tuning = bench.bench_workload(20.0)
    imu = list(sim.imu)
    s = imu[1500]                       # a spike of 200 m/s^2 on x: bridged by the screen
    imu[1500] = dataclasses.replace(s, dv_b=s.dv_b + np.array([200.0 * s.dt_s, 0.0, 0.0]))
    del imu[2500:2510]                  # 50 ms of lost samples: a gap bridged by the engine
    imu.insert(3000, imu[2999])         # a repeated tag: dropped
    s = imu[3200]
    imu[3200] = dataclasses.replace(s, dtheta_b=np.array([np.nan, 0.0, 0.0]))   # invalid: dropped
    sim.imu = imu
    return sim, tuning


def _flight(workload, batched, reference=False):
    from sitl import bench
    sim, tuning = workload
    made = []
    orig = engine_module.NavEngine.__init__

    def init(self, *a, **k):
        orig(self, *a, **k)
        made.append(self)
    restore = imu_kernel.use_reference_paths() if reference else None
    try:
        engine_module.NavEngine.__init__ = init
        _, _, counters = bench._run(sim, tuning, True, batched=batched)
    finally:
        engine_module.NavEngine.__init__ = orig
        if restore is not None:
            restore()
    eng = made[-1]
    assert eng._fused is not reference
    return eng, counters


def test_batch_is_per_sample_bit_for_bit(workload):
    a, ca = _flight(workload, batched=False)
    b, cb = _flight(workload, batched=True)
    assert ca == cb
    for name in ("r_e", "v_e", "C_b_e", "b_a", "b_g", "clock_bias_m", "t_gps"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert np.array_equal(a.kf.P, b.kf.P)
    assert np.array_equal(a._hist.rows(), b._hist.rows())
    assert np.array_equal(a._ws, b._ws)


def test_fused_matches_the_reference_path(workload):
    a, ca = _flight(workload, batched=False)
    ref, cr = _flight(workload, batched=False, reference=True)
    assert ca == cr
    # the branches were taken
    assert ca["imu_screen.samples_bridged"] >= 1 and ca["imu time gap"] >= 1
    assert ca["imu sample not after previous (dropped)"] == 1 and ca["imu sample invalid (dropped)"] == 1
    assert ca["zupt used"] > 0                      # the stillness ring fed its test
    # the same compiled pieces and float arithmetic: equal to the bit here (numpy's and scipy's
    # BLAS alike); bounded to rounding in case the two libraries differ
    np.testing.assert_allclose(a.r_e, ref.r_e, rtol=0, atol=1e-6)
    np.testing.assert_allclose(a.v_e, ref.v_e, rtol=0, atol=1e-8)
    np.testing.assert_allclose(a.C_b_e, ref.C_b_e, rtol=0, atol=1e-10)
    scale = np.sqrt(np.outer(np.diag(ref.kf.P), np.diag(ref.kf.P)))
    assert np.all(np.abs(a.kf.P - ref.kf.P) <= 1e-9 * scale + 1e-300)
    ta, tr = a._hist.rows(), ref._hist.rows()
    assert ta.shape == tr.shape
    np.testing.assert_allclose(ta, tr, rtol=1e-14, atol=1e-6)


def test_state_properties_copy_in_and_out(workload):
    a, _ = _flight(workload, batched=True)
    r = a.r_e
    r += 1.0                             # a read is a copy: the engine's state is untouched
    assert not np.array_equal(r, a.r_e)
    a.r_e = r                            # a write copies in
    assert np.array_equal(a.r_e, r)
    pt = a.ins_at(a.t_gps - 0.5)
    assert pt is not None and pt.r_e.shape == (3,) and pt.C_b_e.shape == (3, 3)


def test_stillness_statistics_equal_numpy_on_wrapped_rings():
    """The compiled window statistics (imu_fused.still_window_std) give numpy's std and mean of the
    rates to the bit, on windows that wrap round the ring and windows that do not."""
    from companion.nav import imu_fused as F
    from companion.nav import nav_state as S
    kernels = F.ensure_compiled()
    rng = np.random.default_rng(1)
    wrapped = 0
    for _ in range(100):
        scr_n, cap = int(rng.integers(1, 20)), int(rng.integers(5, 300))
        m, head = int(rng.integers(2, cap + 1)), int(rng.integers(0, cap))
        ws = np.zeros(S.HEADER + 6 * scr_n + 7 * cap)
        ws[S.SCR_N], ws[S.ST_CAP], ws[S.ST_HEAD] = scr_n, cap, head
        ring = ws[S.still_offset(ws):].reshape(cap, 7)
        ring[:, :6] = rng.normal(size=(cap, 6)) * 1e-3 + rng.normal(size=6) * 1e-2
        ring[:, 6] = 0.005 * (1.0 + 0.01 * rng.normal(size=cap))
        rows = ring[head - m:head] if m <= head else np.concatenate((ring[cap - (m - head):], ring[:head]))
        wrapped += m > head
        rates = rows[:, :6] / rows[:, 6:7]
        std = rates.std(axis=0)
        out = np.zeros(5)
        kernels.still_window_std(ws, m, out)
        assert out[0] == std[:3].max() and out[1] == std[3:].max()
        assert np.array_equal(out[2:5], rates[:, :3].mean(axis=0))
    assert wrapped > 10


def test_history_kernels_equal_numpy():
    """The compiled history look-up and correction (imu_fused.history_interpolate, history_correct)
    against InsHistory's numpy versions: interpolation to the bit inside, at a tag and at both ends,
    None outside; the correction to the bit too (a replay runs the path its process has, whichever
    the live service ran)."""
    from companion.nav import imu_fused as F
    from companion.nav import nav_state as S
    kernels = F.ensure_compiled()
    rng = np.random.default_rng(2)
    hists = []
    for kernel in (False, True):
        h = S.InsHistory(S.new_ws(9, 100), capacity=64)
        h.ws[S.HIST_S] = 0.3                  # ~57 live rows of the 64
        if kernel:
            h.correct_kernel, h.interpolate_kernel = kernels.history_correct, kernels.history_interpolate
        hists.append(h)
    t = 100.0
    for _ in range(150):                      # the live rows reach the ring's end and move to the front
        t += 0.005 * (1.0 + 0.1 * rng.random())
        row = np.concatenate(([t], rng.normal(size=6) * 100.0, rng.normal(size=9)))
        for h in hists:
            h.ws[S.T:S.C + 9] = row
            h.push_current()
    ref, fast = hists
    assert len(ref.hist) == 64 and 0 < ref.span()[0] < 64 - ref.span()[1]   # moved, not grown
    ts = ref.times()
    probes = [ts[0], ts[-1], ts[10], ts[0] - 1e-9, ts[-1] + 1e-9] + list(rng.uniform(ts[0], ts[-1], 50))
    for tp in probes:
        a, b = ref.interpolate(tp), fast.interpolate(tp)
        assert (a is None) == (b is None)
        if a is not None:
            for x, y in zip(a, b):
                assert np.array_equal(x, y)
    assert sum(ref.interpolate(tp) is None for tp in probes) == 2
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    before = ref.rows()[:, 7:16].reshape(-1, 3, 3).copy()
    for h in hists:
        h.correct(np.array([0.1, -0.2, 0.3]), np.array([0.01, 0.02, -0.03]), R)
    assert np.array_equal(fast.rows(), ref.rows())
    # and the rotation is R_e C_b_e (against np.matmul, to rounding)
    np.testing.assert_allclose(ref.rows()[:, 7:16].reshape(-1, 3, 3), np.matmul(R, before), rtol=0, atol=1e-12)
