"""Issue 16, "a cheaper GNSS epoch": the fast per-epoch code gives the numbers of the code it
replaced (tests/_gnss_epoch_reference.py, the implementation of commit 3ed8431), and the caches
it added cannot change a result.

* satellite states (companion.gnss.sat_state, and compiled: sat_state_kernel) equal
  companion.gnss.ephemeris's, bit for bit, for
  GPS, Galileo, BeiDou (MEO, IGSO and GEO) and QZSS ephemerides, including week cross-overs;
* prepare_epoch equals the reference field for field (DGPS, standalone with and without
  Klobuchar, iono-free, unknown position, carrier-only satellites, four systems);
* DgpsCorrector.update_base gives the reference's corrections, slopes and clocks;
* the engine over the benchmark's flight (DGPS + base-corrected TDCP) with the fast code and
  with the reference code: the same updates (bounded; bit for bit on x86-64 with numpy 2.4 and
  its OpenBLAS), and two runs of the same input give the same output exactly (the caches warm in
  the second run: replay property).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.gnss import ephemeris, sat_state
from companion.gnss.dgps import DgpsCorrector
from companion.gnss.ephemeris_store import MAX_REMEMBERED_SELECTIONS, EphemerisStore
from companion.gnss.prepare import prepare_epoch
from companion.gnss.rinex import read_rinex_nav, read_rinex_nav_header_iono
from companion.gnss.rinex_obs import read_rinex_obs
from companion.messages import BaseStationPosition, GnssEpoch, GpsEphemeris
from tests import _gnss_epoch_reference as ref
from tests._data import data_path

GEONET = data_path("rtklib-testdata-geonet-2005/rinex")
RTCM = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"


@pytest.fixture(scope="module")
def geonet():
    if not (GEONET / "07590920.05o").is_file():
        pytest.skip("GEONET test data not present")
    store = EphemerisStore(read_rinex_nav(GEONET / "07590920.05n"))
    hr, rover = read_rinex_obs(GEONET / "07590920.05o")
    hb, base = read_rinex_obs(GEONET / "30400920.05o")
    return dict(store=store, klob=read_rinex_nav_header_iono(GEONET / "07590920.05n"), rover=rover[:40],
                base=base[:40], r_rover=hr["approx_position_e"],
                base_pos=BaseStationPosition(3040, hb["approx_position_e"]))


@pytest.fixture(scope="module")
def hiroshima():
    if not RTCM.is_file():
        pytest.skip("Hiroshima RTCM stream not present")
    from companion.io.rtcm import decode_rtcm_file
    msgs, _ = decode_rtcm_file(str(RTCM), week_hint=2240)
    ephs = [m for m in msgs if isinstance(m, GpsEphemeris)]
    epochs = [dataclasses.replace(m, source="rover") for m in msgs if isinstance(m, GnssEpoch)]
    return dict(ephs=ephs, store=EphemerisStore(ephs), epochs=epochs[:20],
                r=np.array([-3551876.8287, 3887786.8598, 3586946.3873]))


def _assert_same_prep(a, b):
    """``a`` ours, ``b`` the reference's.  Since GLONASS is modelled (when asked), an unselected
    GLONASS satellite is 'system not selected' where the reference said 'unsupported system'."""
    assert list(a.__dataclass_fields__) == list(b.__dataclass_fields__)
    for name in a.__dataclass_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if name == "rejected":
            y = {s: "system not selected" if s[0] == "R" and why == "unsupported system" else why
                 for s, why in y.items()}
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, name
            assert np.array_equal(x, y, equal_nan=True), name
        else:
            assert x == y, name


# ------------------------------------------------------------------------------ satellite states
def _check_states(ephs):
    n = 0
    for eph in ephs:
        k = sat_state.orbit_constants(eph)
        for dt in (-7199.0, -3600.0, -1.0, 0.0, 0.0731, 1234.567, 3600.0, 7199.9):
            t = eph.t_oe_gps + dt
            r, v, b, d = ephemeris.satellite_state(eph, t)
            got = sat_state.state(k, t)
            assert got == (*r.tolist(), *v.tolist(), b, d), (eph.sat, dt)
            for p in (2.0e7, 2.35e7, 3.8e7):
                assert sat_state.transmit_time(k, t, p) == ephemeris.transmit_time(t, p, eph), (eph.sat, dt, p)
            n += 1
    return n


def test_satellite_states_equal_the_reference_gps(geonet):
    ephs = [e for sat in geonet["store"].sats for e in geonet["store"].all(sat)]
    assert _check_states(ephs) > 500


def test_satellite_states_equal_the_reference_four_systems(hiroshima):
    ephs = hiroshima["ephs"]
    assert {e.sat[0] for e in ephs} >= set("GECJ")
    assert any(ephemeris.is_beidou_geo(e.sat) for e in ephs)     # the GEO branch is exercised
    assert _check_states(ephs) > 300


def test_satellite_states_across_the_week_boundary(geonet):
    """toe near the end of a week, times in the next week (the half-week fold of both)."""
    eph = geonet["store"].all(geonet["store"].sats[0])[0]
    eph = dataclasses.replace(eph, toe_s=604000.0, toc_s=604000.0)
    k = sat_state.orbit_constants(eph)
    for t in (eph.t_oe_gps + 700.0, eph.t_oe_gps - 302500.0, eph.t_oe_gps + 302500.0):
        r, v, b, d = ephemeris.satellite_state(eph, t)
        assert sat_state.state(k, t) == (*r.tolist(), *v.tolist(), b, d)


def test_orbit_constants_cache_is_bounded_and_exact(geonet, monkeypatch):
    ephs = [e for sat in geonet["store"].sats for e in geonet["store"].all(sat)]
    monkeypatch.setattr(sat_state, "MAX_CACHED", 8)
    sat_state._cache.clear()
    for e in ephs:
        sat_state.orbit_constants(e)
    assert len(sat_state._cache) <= 8
    t = ephs[0].t_oe_gps + 100.0
    cold = sat_state.state(sat_state.OrbitConstants(ephs[0]), t)
    assert sat_state.state(sat_state.orbit_constants(ephs[0]), t) == cold
    # a copy (equal, not identical) has its own entry with the same numbers
    twin = dataclasses.replace(ephs[0])
    assert sat_state.orbit_constants(twin).eph is twin
    assert sat_state.state(sat_state.orbit_constants(twin), t) == cold


@pytest.fixture
def state_kernel():
    """The compiled satellite state (the engine's kernels loaded), or a skip without numba."""
    from companion.gnss import sat_state_kernel
    from companion.nav import imu_kernel
    if imu_kernel.compiled() is None:
        pytest.skip("numba not installed or COMPANION_NUMBA=0")
    kern = sat_state_kernel.compiled()
    assert kern is not None
    return kern


def test_compiled_satellite_state_equals_python(geonet, hiroshima, state_kernel):
    ephs = [e for sat in geonet["store"].sats for e in geonet["store"].all(sat)] + hiroshima["ephs"]
    n = 0
    for eph in ephs:
        k = sat_state.orbit_constants(eph)
        if k.geo:
            continue
        for dt in (-7199.0, -1.0, 0.0731, 3600.0, 7199.9):
            t = eph.t_oe_gps + dt
            t_tx = sat_state.transmit_time(k, t, 2.2e7)
            assert state_kernel(k.vec, t, 2.2e7, math.nan) == (t_tx, *sat_state.state(k, t_tx)), eph.sat
            assert state_kernel(k.vec, t, 0.0, t) == (t, *sat_state.state(k, t)), eph.sat
            n += 1
    assert n > 900


# ------------------------------------------------------------------------------ prepare_epoch
@pytest.mark.parametrize("compiled", [False, True], ids=["python", "compiled"])
def test_prepare_epoch_equals_the_reference_gps(geonet, compiled, request, monkeypatch):
    from companion.gnss import prepare as prepare_mod
    if compiled:
        request.getfixturevalue("state_kernel")
    else:
        monkeypatch.setattr(prepare_mod, "compiled_state", lambda: None)
    store, klob = geonet["store"], geonet["klob"]
    corr = DgpsCorrector()
    r = geonet["r_rover"]
    n = carrier_only = 0
    for e_r, e_b in zip(geonet["rover"], geonet["base"]):
        corr.update_base(e_b, geonet["base_pos"], store)
        # carrier only on two satellites: kept with NaN pseudorange, their own transmit-time branch
        two = list(dict.fromkeys(o.sat for o in e_r.observations))[:2]
        obs = [dataclasses.replace(o, pseudorange_m=math.nan) if o.sat in two else o for o in e_r.observations]
        phase_only = dataclasses.replace(e_r, observations=tuple(obs))
        cases = [dict(dgps=corr), dict(klobuchar=klob), dict(), dict(klobuchar=klob, signal="IF"),
                 dict(klobuchar=klob, signal="L2W"), dict(apply_models=False, elevation_mask_rad=0.0),
                 dict(klobuchar=klob, tropo=False, rx_clock_bias_m=3000.0)]
        carrier_only += int(np.isnan(prepare_epoch(phase_only, store, r).pseudorange_m).sum())
        for kw in cases:
            for ep in (e_r, phase_only):
                _assert_same_prep(prepare_epoch(ep, store, r, **kw), ref.prepare_epoch(ep, store, r, **kw))
                n += 1
        # unknown position: no mask, no models
        _assert_same_prep(prepare_epoch(e_r, store, np.zeros(3)), ref.prepare_epoch(e_r, store, np.zeros(3)))
    assert n > 400 and carrier_only > 20


@pytest.mark.parametrize("compiled", [False, True], ids=["python", "compiled"])
def test_prepare_epoch_equals_the_reference_four_systems(hiroshima, compiled, request, monkeypatch):
    from companion.gnss import prepare as prepare_mod
    if compiled:
        request.getfixturevalue("state_kernel")
    else:
        monkeypatch.setattr(prepare_mod, "compiled_state", lambda: None)
    store, r = hiroshima["store"], hiroshima["r"]
    from companion.gnss.atmosphere import KLOBUCHAR_DEFAULT
    used = set()
    for ep in hiroshima["epochs"]:
        for kw in (dict(systems="GECJ", klobuchar=KLOBUCHAR_DEFAULT), dict(systems="GECJ", signal="IF"),
                   dict(systems="GE", klobuchar=KLOBUCHAR_DEFAULT, elevation_mask_rad=0.0), dict(systems="G")):
            a = prepare_epoch(ep, store, r, **kw)
            _assert_same_prep(a, ref.prepare_epoch(ep, store, r, **kw))
            used |= {s[0] for s in a.sats}
    assert used >= set("GECJ")


# ------------------------------------------------------------------------------ DGPS base
def test_update_base_equals_the_reference(geonet):
    store, base = geonet["store"], geonet["base_pos"]
    fast, slow = DgpsCorrector(), ref.ReferenceDgpsCorrector()
    for e in geonet["base"]:
        assert fast.update_base(e, base, store) == slow.update_base(e, base, store)
        assert fast._prc == slow._prc
        assert fast.base_clocks_m == slow.base_clocks_m and fast._phase == slow._phase
        assert fast.counters == slow.counters
    assert any(rrc != 0.0 for _, _, rrc, _ in fast._prc.values())       # the slopes were formed


# ------------------------------------------------------------------------------ ephemeris store
def test_store_selection_memory_follows_additions(geonet):
    """A remembered selection is dropped when an ephemeris is added (a newer one then wins), and
    the memory stays bounded; every answer is the one a fresh store gives."""
    ephs = [e for sat in geonet["store"].sats for e in geonet["store"].all(sat)]
    sat = max(geonet["store"].sats, key=lambda s: len(geonet["store"].all(s)))
    mine = sorted(geonet["store"].all(sat), key=lambda e: e.t_oe_gps)
    assert len(mine) >= 2
    st = EphemerisStore([e for e in ephs if e is not mine[-1]])
    t = mine[-1].t_oe_gps
    before = st.select_with_reason(sat, t)
    assert before[0] is not mine[-1] and st.select_with_reason(sat, t) is before    # remembered
    st.add(mine[-1])
    assert st.select_with_reason(sat, t)[0] is mine[-1]
    fresh = EphemerisStore(ephs)
    for k in range(3 * MAX_REMEMBERED_SELECTIONS):
        tk = t - 7200.0 + 5.0 * k
        assert st.select_with_reason(sat, tk) == fresh.select_with_reason(sat, tk)
        assert st.select_with_reason(sat, tk, iode=mine[0].iode) == fresh.select_with_reason(sat, tk, iode=mine[0].iode)
    assert len(st._selected) <= MAX_REMEMBERED_SELECTIONS


# ------------------------------------------------------------------------------ engine
def _engine_run(sim, tuning, reference: bool, monkeypatch):
    """The benchmark's GNSS pass (sitl.bench._run): per epoch (dx, P) and the final state."""
    import companion.gnss.dgps as dgps_mod
    import companion.nav.engine as E
    from sitl.bench import _run
    with monkeypatch.context() as m:
        if reference:
            m.setattr(E, "prepare_epoch", ref.prepare_epoch)
            m.setattr(E, "tdcp_batch", ref.tdcp_batch)
            m.setattr(E, "RoverCarrierBook", ref.ReferenceRoverCarrierBook)
            m.setattr(E, "BaseCarrierBook", ref.ReferenceBaseCarrierBook)
            m.setattr(dgps_mod, "DgpsCorrector", ref.ReferenceDgpsCorrector)
        out = []
        orig = E.NavEngine._process_epoch

        def rec(self, epoch):
            rep = orig(self, epoch)
            out.append((None if rep.dx is None else np.array(rep.dx), self.kf.P.copy(), self.r_e.copy(),
                        self.v_e.copy()))
            return rep
        m.setattr(E.NavEngine, "_process_epoch", rec)
        _, _, counters = _run(sim, tuning, True)
    return out, counters


@pytest.fixture(scope="module")
def flight():
    from sitl.bench import bench_workload
    _, sim, tuning = bench_workload(20.0)
    return sim, tuning


def test_engine_fast_epoch_equals_the_reference_and_replays(flight, monkeypatch):
    sim, tuning = flight
    slow, c_slow = _engine_run(*flight, True, monkeypatch)
    fast, c_fast = _engine_run(*flight, False, monkeypatch)
    again, c_again = _engine_run(*flight, False, monkeypatch)      # caches warm now
    assert c_fast == c_slow == c_again
    assert c_fast["tdcp used"] > 100 and c_fast["pseudorange used"] > 100
    assert len(fast) == len(slow) >= 15
    worst = 0.0
    for (dx_f, P_f, r_f, v_f), (dx_s, P_s, r_s, v_s), (dx_a, P_a, r_a, v_a) in zip(fast, slow, again):
        # replay: exactly the same numbers
        assert np.array_equal(r_f, r_a) and np.array_equal(v_f, v_a) and np.array_equal(P_f, P_a)
        assert (dx_f is None and dx_a is None) or np.array_equal(dx_f, dx_a)
        # against the reference: rounding level at most (one BLAS may sum a dot product in another
        # order than another; 1 ulp in a TDCP row grows to ~1e-8 m through 60 s of filter here)
        worst = max(worst, float(np.max(np.abs(r_f - r_s))), float(np.max(np.abs(v_f - v_s))))
        np.testing.assert_allclose(P_f, P_s, rtol=1e-9, atol=1e-15)
    assert worst <= 1e-6
