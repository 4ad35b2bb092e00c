"""The compiled IMU-rate kernels (companion.nav.imu_kernel) against the readable pure-Python
references on the same data: strapdown to the bit, covariance propagation to rounding error;
and the engine through each path is deterministic and gives the same flight."""
import math

import numpy as np
import pytest

from companion.nav import imu_kernel
from companion.nav.earth import geodetic_to_ecef, gravity_ecef, gravity_gradient_ecef, rotation_from_rotvec
from companion.nav.filter import ErrorStateKalmanFilter, ProcessNoise
from companion.nav.strapdown import strapdown_step_with_force, strapdown_step_with_force_reference

pytest.importorskip("numba")
pytestmark = pytest.mark.skipif(imu_kernel.compiled() is None, reason="kernels disabled (COMPANION_NUMBA=0)")


def _motion(n: int, seed: int = 1):
    """n IMU intervals of a manoeuvring vehicle (rates up to ~2 rad/s, 3 g), 200 Hz."""
    rng = np.random.default_rng(seed)
    tau = 0.005
    w = rng.normal(scale=1.0, size=(n, 3)).cumsum(axis=0) * 0.02
    f = np.array([0.0, 0.0, -9.8]) + rng.normal(scale=5.0, size=(n, 3))
    return [(tuple(w[k] * tau), tuple(f[k] * tau), tau) for k in range(n)]


def test_strapdown_kernel_is_the_reference_bit_for_bit():
    r = geodetic_to_ecef(math.radians(35.0), math.radians(139.0), 120.0)
    v = np.array([8.0, -3.0, 0.5])
    C = rotation_from_rotvec(np.array([0.3, -1.2, 2.0]))
    states = [(r, v, C), (r.copy(), v.copy(), C.copy())]
    for k, (dth, dv, tau) in enumerate(_motion(2000)):
        if k == 7:
            dth = (0.0, 0.0, 0.0)          # the small-angle branch of Rodrigues
        g = gravity_ecef(states[0][0]) if k % 2 else None
        out = strapdown_step_with_force(*states[0], dth, dv, tau, g)
        ref = strapdown_step_with_force_reference(*states[1], dth, dv, tau, g)
        for a, b in zip(out, ref):
            assert np.array_equal(np.asarray(a), np.asarray(b)), k
        assert isinstance(out[3], tuple) and all(isinstance(x, float) for x in out[3])
        states = [out[:3], ref[:3]]


@pytest.mark.parametrize("extra_states", [0, 40])     # dense (n = 18) and by blocks (n = 58)
def test_propagation_kernel_matches_the_reference(extra_states):
    noise = ProcessNoise(3e-4, 3e-3, 1e-5, 1e-4, imu_time_offset_rw_s_per_sqrt_s=1e-4)
    A = np.random.default_rng(0).normal(size=(18, 18)) * 0.1
    filters = []
    for _ in range(2):
        kf = ErrorStateKalmanFilter(A @ A.T + np.eye(18), noise)
        for i in range(extra_states):
            kf.add_block(f"amb {i}", 1, 1.0, 1e-6 if i % 3 else 0.0)
        filters.append(kf)
    r = geodetic_to_ecef(math.radians(35.0), math.radians(139.0), 120.0)
    C = rotation_from_rotvec(np.array([0.3, -1.2, 2.0]))
    G = gravity_gradient_ecef(r)
    for k, (dth, dv, tau) in enumerate(_motion(1000)):
        if k == 500:
            G = gravity_gradient_ecef(r + 1000.0)     # a refreshed gradient is picked up by both
        C = C @ rotation_from_rotvec(np.array(dth))
        filters[0].propagate(C, dv, G, tau)
        filters[1].propagate_reference(C, dv, G, tau)
    P, P_ref = filters[0].P, filters[1].P
    assert P.shape == P_ref.shape == (18 + extra_states,) * 2
    # the same BLAS products (identical with numpy's and scipy's wheels); rounding at most if the
    # two libraries differ, relative to the matrix's scale
    scale = np.sqrt(np.outer(np.diag(P_ref), np.diag(P_ref)))
    assert np.all(np.abs(P - P_ref) <= 1e-12 * scale)
    np.testing.assert_allclose(np.diag(P), np.diag(P_ref), rtol=1e-12)


def test_engine_replay_is_deterministic_through_the_kernels(monkeypatch):
    from sitl.paper import initial_errors, mode_config
    from sitl.scenario import build_scenario
    from sitl.simulate import simulate
    from sitl.tuning import tuning_for
    from companion.nav.engine import NavEngine
    import dataclasses
    scn = dataclasses.replace(build_scenario("uav"), duration_s=4.0)
    sim = simulate(scn, 0)
    tuning = tuning_for(scn)

    def run():
        eng = NavEngine(mode_config("tdcp_dgps", tuning, sim.lever_arm_b))
        for eph in sim.ephemerides:
            eng.process(eph)
        eng.process(sim.base)
        d_att, d_pos, d_vel = initial_errors(np.random.default_rng(0), tuning.p0, sim.truth.r_e[0])
        eng.initialize(sim.truth.t_gps[0], sim.truth.r_e[0] + d_pos, sim.truth.v_e[0] + d_vel,
                       rotation_from_rotvec(d_att) @ sim.truth.C_b_e[0], tuning.p0)
        i_b = i_r = 0
        for s in sim.imu:
            while i_b < len(sim.base_epochs) and sim.base_epochs[i_b].t_gps <= s.t_gps:
                eng.process(sim.base_epochs[i_b])
                i_b += 1
            while i_r < len(sim.rover_epochs) and sim.rover_epochs[i_r].t_gps <= s.t_gps:
                eng.process(sim.rover_epochs[i_r])
                i_r += 1
            eng.process_imu(s)
        assert eng.counters["gnss epochs"] >= 3
        return eng.r_e.copy(), eng.v_e.copy(), eng.C_b_e.copy(), eng.kf.P.copy()

    a, b = run(), run()
    for x, y in zip(a, b):
        assert np.array_equal(x, y)
    # the pure-Python path on the same data: the same flight to rounding error (the GNSS updates
    # amplify nothing at this level)
    monkeypatch.setattr(imu_kernel, "compiled", lambda: None)
    ref = run()
    assert np.max(np.abs(a[0] - ref[0])) < 1e-6          # m
    assert np.max(np.abs(a[1] - ref[1])) < 1e-8          # m/s
    assert np.max(np.abs(a[2] - ref[2])) < 1e-12
    scale = np.sqrt(np.outer(np.diag(ref[3]), np.diag(ref[3])))
    assert np.all(np.abs(a[3] - ref[3]) <= 1e-9 * scale)


def test_warm_up_compiles_every_kernel():
    from companion.gnss import lambda_kernel, sat_state_kernel
    assert imu_kernel.warm_up() >= 0.0
    k, lk = imu_kernel.compiled(), lambda_kernel.compiled()
    # every dispatcher has a compiled (or cache-loaded) specialisation: the first flight pays nothing
    for disp in (k.strapdown, k.propagate, lk.ldl, lk.reduce_inverse, lk.search, sat_state_kernel.compiled()):
        assert disp.signatures, disp


def test_without_a_cache_directory_the_kernels_compile_in_memory(caplog):
    """numba refuses cache=True when it finds nowhere to write (a read-only install under a
    sandboxed service): the kernels must still come, uncached, with a warning."""
    class NoCacheNumba:
        @staticmethod
        def njit(**options):
            if options.get("cache"):
                raise RuntimeError("cannot cache function 'probe': no locator available for file")
            return lambda f: f
    assert imu_kernel.jit_options(NoCacheNumba) == {"cache": False, "nogil": True}
    assert "NUMBA_CACHE_DIR" in caplog.text
    import numba
    assert imu_kernel.jit_options(numba)["cache"] is True
