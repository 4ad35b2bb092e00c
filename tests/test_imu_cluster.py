"""IMU cluster: time alignment, noise-weighted averaging, fault detection (companion.nav.imu_cluster)."""
import math

import numpy as np

from companion.messages import ImuSample
from companion.nav.allan import overlapping_adev
from companion.nav.imu_cluster import ClusterConfig, UnitNoise, fuse

FS = 200.0
DT = 1.0 / FS
NG, NA = 1e-3, 1e-2          # rad/sqrt(s), m/s/sqrt(s)
G_B = np.array([0.0, 0.0, -9.80665])
T0 = 1.4e9


def _units(n, ids=(0, 1, 2), offsets=(0.0, 0.0013, 0.0029), seed=0, fault=None):
    """Static units with independent white noise; ``fault(uid, k, rates) -> rates`` may alter one.
    Returns the samples in arrival (time) order."""
    rng = np.random.default_rng(seed)
    out = []
    for uid, off in zip(ids, offsets):
        g = rng.standard_normal((n, 3)) * NG / math.sqrt(DT)
        a = G_B + rng.standard_normal((n, 3)) * NA / math.sqrt(DT)
        for k in range(n):
            r = np.concatenate([g[k], a[k]])
            if fault is not None:
                r = fault(uid, k, r)
            out.append(ImuSample(T0 + (k + 1) * DT + off, DT, r[:3] * DT, r[3:] * DT, uid))
    out.sort(key=lambda s: s.t_gps)
    return out


def _cfg(ids=(0, 1, 2), **kw):
    return ClusterConfig(noise={i: UnitNoise(NG, NA) for i in ids}, **kw)


def _rates(samples):
    return np.array([np.concatenate([s.dtheta_b, s.dv_b]) / s.dt_s for s in samples])


def test_fused_noise_density_is_one_over_sqrt3():
    samples = _units(12000)
    fused, c = fuse(samples, _cfg())
    assert len(fused) > 11900
    r = _rates(fused) - np.concatenate([np.zeros(3), G_B])
    one = _rates([s for s in samples if s.imu_id == 0]) - np.concatenate([np.zeros(3), G_B])
    # noise density from the Allan deviation at tau = 0.1 s (interpolation only filters near fs/2)
    _, ad_f, _ = overlapping_adev(r, FS, m=[20])
    _, ad_1, _ = overlapping_adev(one, FS, m=[20])
    ratio = float(np.mean(ad_f[0] / ad_1[0]))
    print(f"fused / single noise density {ratio:.4f} (1/sqrt(3) = {1 / math.sqrt(3):.4f})")
    assert abs(ratio * math.sqrt(3) - 1.0) < 0.10
    assert not any("dropped" in k for k in c.counters), c.counters


def test_time_alignment_of_offset_units():
    """A sinusoidal rate seen by three offset units: the fused rate is the rate at the primary's
    interval midpoint, to second order (no noise here)."""
    w, amp = 2 * math.pi * 2.0, 0.5
    out = []
    for uid, off in zip((0, 1, 2), (0.0, 0.0013, 0.0029)):
        for k in range(400):
            t1 = (k + 1) * DT + off
            t0 = t1 - DT
            dth = amp * (math.cos(w * t0) - math.cos(w * t1)) / w      # exact integral of amp sin(w t)
            out.append(ImuSample(T0 + t1, DT, np.array([dth, 0, 0]), np.array([0, 0, -9.8 * DT]), uid))
    out.sort(key=lambda s: s.t_gps)
    fused, _ = fuse(out, _cfg())
    err = []
    for s in fused:
        t1 = s.t_gps - T0
        exact = amp * (math.cos(w * (t1 - DT)) - math.cos(w * t1)) / w / DT
        err.append(s.dtheta_b[0] / DT - exact)
    # linear interpolation of interval means: error ~ amp w^2 dt^2 / 8 = 3e-4 at most
    assert np.max(np.abs(err)) < 1e-3 * amp


def _step_fault(uid_bad, k0, bias, k1=None):
    def f(uid, k, r):
        if uid == uid_bad and k >= k0 and (k1 is None or k < k1):
            r = r.copy()
            r[0] += bias
        return r
    return f


def test_step_bias_is_detected_and_dropped():
    k0, bias = 1000, 0.05     # 0.05 rad/s (~3 deg/s) gyro bias jump on unit 2
    samples = _units(3000, fault=_step_fault(2, k0, bias))
    fused, c = fuse(samples, _cfg())
    drops = [e for e in c.events if e[2] == "dropped"]
    assert [e[1] for e in drops] == [2]
    k_det = int(round((drops[0][0] - T0) / DT)) - 1
    print(f"step bias detected after {k_det - k0} samples")
    assert 0 <= k_det - k0 <= 20
    r = _rates(fused)
    after = r[k_det + 2:, 0]
    sig2 = NG / math.sqrt(DT) / math.sqrt(2)        # two healthy units
    assert abs(np.mean(after)) < 4 * sig2 / math.sqrt(len(after))
    assert abs(np.std(after) / sig2 - 1.0) < 0.1
    # during the detection latency the fused rate is off by at most bias/3 plus noise
    assert np.max(np.abs(r[k0:k_det + 1, 0])) < bias / 3 + 5 * NG / math.sqrt(DT) / math.sqrt(3)


def test_stuck_unit_is_detected():
    k0 = 800

    def freeze(uid, k, r, held={}):
        if uid == 1:
            if k == k0:
                held["r"] = r.copy()
            if k >= k0:
                return held["r"]
        return r
    samples = _units(2000, fault=freeze)
    fused, c = fuse(samples, _cfg())
    drops = [e for e in c.events if e[2] == "dropped"]
    assert [(e[1], e[3]) for e in drops] == [(1, "stuck output")]
    k_det = int(round((drops[0][0] - T0) / DT)) - 1
    assert k_det - k0 <= 10


def test_unit_is_readmitted_after_quiet_period():
    samples = _units(3000, fault=_step_fault(2, 500, 0.05, k1=1000))
    _, c = fuse(samples, _cfg(readmit_quiet_samples=500))
    kinds = [(e[1], e[2]) for e in c.events]
    assert kinds == [(2, "dropped"), (2, "readmitted")]
    t_re = [e[0] for e in c.events if e[2] == "readmitted"][0]
    k_re = int(round((t_re - T0) / DT)) - 1
    assert 1000 + 500 <= k_re <= 1000 + 500 + 25


def test_two_units_disagreement_is_flagged_and_primary_kept():
    samples = _units(2000, ids=(0, 1), offsets=(0.0, 0.0017), fault=_step_fault(0, 700, 0.05))
    fused, c = fuse(samples, _cfg(ids=(0, 1)))
    assert c.counters["ambiguous disagreement (2 units)"] == 1
    assert c.status()[0]["healthy"] and not c.status()[1]["healthy"]
    # the primary (the faulty one here: it cannot be known) is what comes out
    assert abs(np.mean(_rates(fused)[800:, 0]) - 0.05) < 0.005


def test_deterministic():
    samples = _units(500, fault=_step_fault(2, 200, 0.05))
    a, _ = fuse(samples, _cfg())
    b, _ = fuse(samples, _cfg())
    assert all(np.array_equal(x.dtheta_b, y.dtheta_b) and x.t_gps == y.t_gps for x, y in zip(a, b))
