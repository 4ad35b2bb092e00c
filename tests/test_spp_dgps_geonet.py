"""SPP and code DGPS on real GEONET data (Trimble 5700, 2005-04-02 00:00-01:00 GPST, 30 s).

Rover 0759, base 3040 (3.34 km), truth = each file's header APPROX POSITION XYZ.
Acceptance: SPP RMS 3-D <= 1.6 m, DGPS RMS 3-D <= 1.0 m (RTKLIB 2.4.3: 1.62 m and 1.09 m).
Run:  python -m pytest -q -s tests/test_spp_dgps_geonet.py   (prints the measured table)
"""
from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from companion.gnss.dgps import DgpsCorrector
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.postprocess import ProcessOptions, process, statistics
from companion.gnss.prepare import prepare_epoch
from companion.gnss.rinex import read_rinex_nav, read_rinex_nav_header_iono
from companion.gnss.rinex_obs import read_rinex_obs
from companion.gnss.spp import solve_spp, spp_epoch
from companion.messages import BaseStationPosition, GnssEpoch, SatObservation
from tests._data import data_path

DATA = data_path("rtklib-testdata-geonet-2005/rinex")
ROVER, BASE = DATA / "07590920.05o", DATA / "30400920.05o"
NAV_R, NAV_B = DATA / "07590920.05n", DATA / "30400920.05n"
pytestmark = pytest.mark.real_data
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def data():
    store = EphemerisStore(read_rinex_nav(NAV_R))
    klob = read_rinex_nav_header_iono(NAV_R)
    hr, rover = read_rinex_obs(ROVER)
    hb, base = read_rinex_obs(BASE)
    return dict(store=store, klob=klob, hr=hr, rover=rover, hb=hb, base=base,
                truth=hr["approx_position_e"], base_pos=BaseStationPosition(3040, hb["approx_position_e"]))


def _run(d, **kw):
    opts = ProcessOptions(**kw)
    sols = process(d["rover"], d["store"], opts, klobuchar=d["klob"], base_epochs=d["base"], base=d["base_pos"])
    return sols, statistics(sols, d["truth"])


def _same(a, b) -> bool:
    a, b = float(a), float(b)
    return a == b or (math.isnan(a) and math.isnan(b))


# ------------------------------------------------------------------------------ RINEX obs
def test_obs_reader_matches_georinex(data):
    georinex = pytest.importorskip("georinex")
    t0 = time.perf_counter()
    hdr, epochs = read_rinex_obs(ROVER)
    dt = time.perf_counter() - t0
    print(f"\nread_rinex_obs: {len(epochs)} epochs in {dt * 1e3:.0f} ms")
    assert dt < 3.0
    assert hdr["marker"] == "0759" and hdr["interval_s"] == 30.0 and len(epochs) == 120
    np.testing.assert_allclose(hdr["approx_position_e"], [-3976219.5082, 3382372.5671, 3652512.9849])
    assert hdr["obs_types"]["G"] == ["L1C", "C1C", "L2W", "C2W"]
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        obs = georinex.load(ROVER)
    t_geo = (obs.time.values - np.datetime64("1980-01-06T00:00:00", "ns")) / np.timedelta64(1, "s")
    np.testing.assert_allclose([e.t_gps for e in epochs], t_geo, atol=1e-6)
    n = 0
    for k, ep in enumerate(epochs):
        for o in ep.observations:
            row = obs.isel(time=k).sel(sv=o.sat)
            if o.signal == "L1C":
                assert _same(o.pseudorange_m, row.C1) and _same(o.carrier_cycles, row.L1)
            else:
                assert o.signal == "L2W"
                assert _same(o.pseudorange_m, row.P2) and _same(o.carrier_cycles, row.L2)
                assert o.wavelength_m == pytest.approx(299792458.0 / 1227.6e6)
            n += 1
    n_geo = int((np.isfinite(obs.C1.values) | np.isfinite(obs.L1.values)).sum()
                + (np.isfinite(obs.P2.values) | np.isfinite(obs.L2.values)).sum())
    assert n == n_geo


# ------------------------------------------------------------------------------ prepare
def test_prepared_pseudorange_model_at_truth(data):
    """At the true position, corrected pseudoranges minus geometric range are one common clock
    (to the model's accuracy); the DGPS ones much more tightly than the standalone ones."""
    store, truth = data["store"], data["truth"]
    dg = DgpsCorrector()
    spreads_sa, spreads_dg = [], []
    for ep_r, ep_b in list(zip(data["rover"], data["base"]))[::10]:
        assert abs(ep_r.t_gps - ep_b.t_gps) < 0.01
        dg.update_base(ep_b, data["base_pos"], store)
        for dgps, spreads in ((None, spreads_sa), (dg, spreads_dg)):
            p = prepare_epoch(ep_r, store, truth, dgps=dgps, klobuchar=data["klob"])
            assert p.n >= 6
            res = p.pseudorange_m - np.linalg.norm(p.r_sat_e - truth, axis=1)
            spreads.append(np.std(res - np.median(res)))
            if dgps is None:
                assert np.all(p.iono_m > 0) and np.all(p.tropo_m > 2.3) and np.all(np.isnan(p.dgps_age_s))
                assert np.all(p.elevation_rad >= math.radians(10.0))
            else:
                assert np.all(np.abs(p.dgps_age_s) < 0.01)
                sa = prepare_epoch(ep_r, store, truth, klobuchar=data["klob"])
                assert sa.sats == p.sats and np.all(p.sigma_pseudorange_m < sa.sigma_pseudorange_m)
    print(f"\nrms spread of corrected pseudorange residuals at truth: standalone {np.mean(spreads_sa):.2f} m, "
          f"DGPS {np.mean(spreads_dg):.2f} m")
    assert np.mean(spreads_sa) < 2.0
    assert np.mean(spreads_dg) < 0.6 and np.mean(spreads_dg) < 0.8 * np.mean(spreads_sa)


def test_sagnac_rotation_is_applied(data):
    """Without the earth-rotation correction the residuals at truth would scatter by ~10-30 m."""
    ep = data["rover"][0]
    truth = data["truth"]
    p = prepare_epoch(ep, data["store"], truth, klobuchar=data["klob"])
    tau = np.linalg.norm(p.r_sat_e - truth, axis=1) / 299792458.0
    assert np.all((0.064 < tau) & (tau < 0.09))
    res = p.pseudorange_m - np.linalg.norm(p.r_sat_e - truth, axis=1)
    w = 7.2921151467e-5
    # undo the rotation (back to the transmit-time frame)
    unrot = np.array([[math.cos(w * t) * x - math.sin(w * t) * y, math.sin(w * t) * x + math.cos(w * t) * y, z]
                      for t, (x, y, z) in zip(tau, p.r_sat_e)])
    res_unrot = p.pseudorange_m - np.linalg.norm(unrot - truth, axis=1)
    assert np.std(res) < 2.0 < np.std(res_unrot)


def test_prepare_rejections_phase_only_and_speed(data):
    store, truth = data["store"], data["truth"]
    ep = max(data["rover"], key=lambda e: len(e.observations))
    extra = (SatObservation(sat="G31", pseudorange_m=2.2e7),                         # no ephemeris
             SatObservation(sat="E11", pseudorange_m=2.4e7))                         # a system not selected
    obs = list(ep.observations) + list(extra)
    # make one satellite phase-only
    victim = next(o for o in obs if o.signal == "L1C")
    obs = [dataclasses.replace(o, pseudorange_m=float("nan")) if o is victim else o for o in obs]
    p = prepare_epoch(GnssEpoch(ep.t_gps, tuple(obs)), store, truth, klobuchar=data["klob"], elevation_mask_rad=0.0)
    assert p.rejected["G31"] == "no ephemeris" and p.rejected["E11"] == "system not selected"
    i = p.sats.index(victim.sat)
    assert np.isnan(p.pseudorange_m[i]) and np.isfinite(p.carrier_cycles[i])
    full = prepare_epoch(ep, store, truth, klobuchar=data["klob"], elevation_mask_rad=0.0)
    j = full.sats.index(victim.sat)
    # the geometric transmit-time route agrees with the pseudorange route once the receiver clock
    # (here ~4 ms: the receiver time tags are steered to within a few ms) is given
    clk = solve_spp(full).clock_bias_m
    assert abs(clk) > 1e4
    p_clk = prepare_epoch(GnssEpoch(ep.t_gps, tuple(obs)), store, truth, klobuchar=data["klob"],
                          elevation_mask_rad=0.0, rx_clock_bias_m=clk)
    assert np.linalg.norm(p_clk.r_sat_e[i] - full.r_sat_e[j]) < 0.01
    assert np.linalg.norm(p.r_sat_e[i] - full.r_sat_e[j]) > 10 * np.linalg.norm(p_clk.r_sat_e[i] - full.r_sat_e[j])
    sol = solve_spp(p)
    assert victim.sat not in sol.sats and sol.excluded[victim.sat] == "no pseudorange"
    # empty epoch
    empty = prepare_epoch(GnssEpoch(ep.t_gps, ()), store, truth)
    assert empty.n == 0 and empty.r_sat_e.shape == (0, 3) and solve_spp(empty) is None
    # speed (one satellite per SatObservation pair L1C+L2W)
    n = 200
    t0 = time.perf_counter()
    for _ in range(n):
        prepare_epoch(ep, store, truth, klobuchar=data["klob"], elevation_mask_rad=0.0)
    dt = (time.perf_counter() - t0) / n
    print(f"\nprepare_epoch: {full.n} satellites in {dt * 1e3:.2f} ms")
    assert dt < 3e-3


# ------------------------------------------------------------------------------ DGPS corrector
def test_dgps_corrector_age_iode_and_phase(data):
    store = data["store"]
    dg = DgpsCorrector(max_age_s=30.0)
    dg.update_base(data["base"][0], data["base_pos"], store)
    dg.update_base(data["base"][1], data["base_pos"], store)
    sat = dg.sats[0]
    iode = dg.iode(sat)
    t_b = data["base"][1].t_gps
    prc0, age0, why = dg.correction(sat, t_b, iode)
    assert why == "" and age0 == 0.0 and abs(prc0) < 30.0
    prc1, age1, why = dg.correction(sat, t_b + 20.0, iode)
    assert why == "" and age1 == 20.0 and prc1 != prc0          # extrapolated with the RRC
    assert abs(prc1 - prc0) < 20.0 * 0.5
    _, _, why = dg.correction(sat, t_b + 31.0, iode)
    assert why == "DGPS correction too old" and dg.counters["DGPS correction too old"] == 1
    _, _, why = dg.correction(sat, t_b, iode + 1)
    assert why == "IODE mismatch"
    _, _, why = dg.correction("G32", t_b, 0)
    assert why == "no DGPS correction"
    t_ph, cyc, wl = dg.base_phase(sat)
    assert t_ph == t_b and np.isfinite(cyc) and wl == pytest.approx(0.1903, abs=1e-4)
    # the PRCs have the base clock removed: their weighted centre is ~0 and they are metres, not km
    prcs = [dg.correction(s, t_b, dg.iode(s))[0] for s in dg.sats]
    assert max(abs(x) for x in prcs) < 30.0
    # rover epoch prepared 40 s after the last base epoch: all refused, with the reason
    p = prepare_epoch(GnssEpoch(t_b + 40.0, data["rover"][1].observations), store, data["truth"], dgps=dg)
    assert p.n == 0 and set(p.rejected.values()) <= {"DGPS correction too old", "below elevation mask",
                                                     "no DGPS correction"}


# ------------------------------------------------------------------------------ RAIM
def test_raim_excludes_a_faulty_satellite(data):
    store, truth = data["store"], data["truth"]
    ep = data["rover"][40]
    good = spp_epoch(ep, store, klobuchar=data["klob"], r_init_e=truth)
    assert good is not None and good.raim_ok and good.n_sats >= 7
    bad_sat = good.sats[2]
    obs = tuple(dataclasses.replace(o, pseudorange_m=o.pseudorange_m + 60.0) if o.sat == bad_sat and o.signal == "L1C"
                else o for o in ep.observations)
    sol = spp_epoch(GnssEpoch(ep.t_gps, obs), store, klobuchar=data["klob"], r_init_e=truth)
    assert bad_sat in sol.excluded and sol.excluded[bad_sat].startswith("RAIM")
    assert sol.raim_ok and np.linalg.norm(sol.r_e - good.r_e) < 1.0
    no_raim = spp_epoch(GnssEpoch(ep.t_gps, obs), store, klobuchar=data["klob"], r_init_e=truth, raim=False)
    assert np.linalg.norm(no_raim.r_e - truth) > np.linalg.norm(sol.r_e - truth) + 2.0
    assert good.gdop >= good.pdop >= good.vdop > 0 and good.pdop ** 2 == pytest.approx(good.hdop ** 2 + good.vdop ** 2)
    assert good.v_e is None                                         # no Doppler in these files


def test_cold_start_from_earth_centre(data):
    sol = spp_epoch(data["rover"][0], data["store"], klobuchar=data["klob"])
    assert sol is not None and np.linalg.norm(sol.r_e - data["truth"]) < 5.0
    assert abs(sol.clock_bias_m) < 3e5                              # receiver clock within 1 ms


# ------------------------------------------------------------------------------ acceptance
def test_acceptance_spp_and_dgps(data):
    rows = {}
    for name, kw in [("SPP  L1 Klobuchar, no smoothing", dict(mode="spp", smoothing=False)),
                     ("SPP  L1 Klobuchar, smoothed (default)", dict(mode="spp")),
                     ("SPP  iono-free C1/P2, smoothed", dict(mode="spp", signal="IF")),
                     ("SPP  L1, mask 15 deg, no smoothing", dict(mode="spp", smoothing=False,
                                                                  elevation_mask_rad=math.radians(15.0))),
                     ("DGPS L1, no smoothing", dict(mode="dgps", smoothing=False)),
                     ("DGPS L1, smoothed (default)", dict(mode="dgps")),
                     ("DGPS iono-free, smoothed", dict(mode="dgps", signal="IF"))]:
        sols, st = _run(data, **kw)
        rows[name] = (sum(s is not None for s in sols), st)
    print("\nGEONET 0759 (base 3040), 120 epochs, truth = header position; RTKLIB 2.4.3: SPP 1.62 m, DGPS 1.09 m")
    print(f"{'configuration':40s} solved  rms3d   rmsH   rmsV   p95    max  [m]")
    for name, (n, st) in rows.items():
        print(f"{name:40s} {n:4d}  {st['rms_3d_m']:6.3f} {st['rms_h_m']:6.3f} {st['rms_v_m']:6.3f} "
              f"{st['p95_3d_m']:6.3f} {st['max_3d_m']:6.3f}")
    spp_default = rows["SPP  L1 Klobuchar, smoothed (default)"]
    dgps_default = rows["DGPS L1, smoothed (default)"]
    assert spp_default[0] == 120 and dgps_default[0] == 120
    assert spp_default[1]["rms_3d_m"] <= 1.6
    assert dgps_default[1]["rms_3d_m"] <= 1.0
    # the acceptance also holds without carrier smoothing
    assert rows["SPP  L1 Klobuchar, no smoothing"][1]["rms_3d_m"] <= 1.6
    assert rows["DGPS L1, no smoothing"][1]["rms_3d_m"] <= 1.0


# ------------------------------------------------------------------------------ CLI
def test_cli_end_to_end(tmp_path):
    out = tmp_path / "dgps.json"
    pos = tmp_path / "dgps.pos"
    cmd = [sys.executable, "-m", "companion", "gnss", "--mode", "dgps", "--rover", str(ROVER), "--nav", str(NAV_R),
           "--nav", str(NAV_B), "--base", str(BASE), "--truth-xyz=-3976219.5082,3382372.5671,3652512.9849",
           "--json", str(out), "--pos", str(pos)]
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 0, r.stderr
    assert "RMS 3-D" in r.stdout
    j = json.loads(out.read_text())
    for key in ("epochs", "solved", "rms_3d_m", "rms_h_m", "p95_3d_m", "max_3d_m", "solutions"):
        assert key in j
    assert j["epochs"] == 120 and j["solved"] == len(j["solutions"]) == 120
    truth = np.array([-3976219.5082, 3382372.5671, 3652512.9849])
    e3 = np.array([np.linalg.norm(np.array(s["r_e"]) - truth) for s in j["solutions"]])
    assert j["rms_3d_m"] == pytest.approx(float(np.sqrt(np.mean(e3 ** 2))), rel=1e-9)
    assert j["max_3d_m"] == pytest.approx(float(e3.max()), rel=1e-9)
    assert j["rms_3d_m"] <= 1.0 and j["rms_h_m"] <= j["rms_3d_m"] <= j["max_3d_m"]
    s0 = j["solutions"][0]
    assert {"t_gps", "r_e", "clock_bias_m", "n_sats", "sats"} <= set(s0)
    assert abs(s0["t_gps"] - 796435200.0) < 1e-6                    # 2005-04-02 00:00:00 GPS
    # RTKLIB's .pos: GPST calendar time, lat/lon/height, Q 4 (DGPS), ns
    lines = [ln.split() for ln in pos.read_text().splitlines() if not ln.startswith("%")]
    assert len(lines) == 120 and lines[0][:2] == ["2005/04/02", "00:00:00.000"]
    assert all(ln[5] == "4" for ln in lines) and int(lines[0][6]) == s0["n_sats"]
    assert float(lines[0][2]) == pytest.approx(35.1608, abs=1e-3) and float(lines[0][3]) == pytest.approx(139.6138, abs=1e-3)
    # clear errors with non-zero exit
    r = subprocess.run([sys.executable, "-m", "companion", "gnss", "--rover", str(tmp_path / "missing.05o"),
                        "--nav", str(NAV_R)], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode != 0 and "file not found" in r.stderr
    r = subprocess.run([sys.executable, "-m", "companion", "gnss", "--mode", "dgps", "--rover", str(ROVER),
                        "--nav", str(NAV_R)], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode != 0 and "--base" in r.stderr


def test_pseudorange_sigma_tells_its_slow_part_and_the_unmodelled_ionosphere(data):
    """Standalone without an ionosphere model the variance carries the whole delay budget; with
    Klobuchar only its residual.  The slow part (everything but code noise) is reported apart, for
    the filter's covariance floor (companion.nav.slow_errors)."""
    from companion.gnss.prepare import IONO_NO_MODEL_SIGMA_M
    ep, store, truth = data["rover"][0], data["store"], data["truth"]
    with_model = prepare_epoch(ep, store, truth, klobuchar=data["klob"])
    without = prepare_epoch(ep, store, truth, klobuchar=None)
    assert with_model.sats == without.sats and with_model.n >= 4
    assert np.all(without.sigma_pseudorange_slow_m >= IONO_NO_MODEL_SIGMA_M)
    assert np.all(with_model.sigma_pseudorange_slow_m < without.sigma_pseudorange_slow_m)
    for p in (with_model, without):
        assert np.all(p.sigma_pseudorange_slow_m > 0) and np.all(p.sigma_pseudorange_slow_m < p.sigma_pseudorange_m)
