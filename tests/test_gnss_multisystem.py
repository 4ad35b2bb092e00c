"""Multi-GNSS pieces without recorded data: inter-system biases in SPP (exact on a synthetic
geometry), system time conversions (BDT, GST), BeiDou group delays, signal selection."""
from __future__ import annotations

import datetime as dt
import math

import numpy as np
import pytest

from companion.gnss.ephemeris import satellite_clock
from companion.gnss.prepare import PreparedEpoch, form_pseudorange
from companion.gnss.rinex import calendar_to_t_gps
from companion.gnss.rinex_obs import read_rinex_obs
from companion.gnss.signals import clock_group, frequency_hz, group_delay_m
from companion.gnss.spp import solve_spp
from companion.messages import (SPEED_OF_LIGHT_MPS, SYSTEM_TO_GPS_S, SYSTEM_WEEK_TO_GPS_WEEK, GpsEphemeris,
                                SatObservation, gps_time)
from companion.nav.earth import C_n_e, geodetic_to_ecef

C = SPEED_OF_LIGHT_MPS


def _prepared(r_rx, sats, clock_m, isb_m, el_az_deg):
    """A PreparedEpoch whose pseudoranges follow the SPP model exactly."""
    lat, lon = math.radians(34.4), math.radians(132.4)
    cne = C_n_e(lat, lon)
    r_sat, pr = [], []
    for sat, (el, az) in zip(sats, el_az_deg):
        e, a = math.radians(el), math.radians(az)
        u_n = np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), -math.sin(e)])
        rs = r_rx + cne @ u_n * 2.2e7
        r_sat.append(rs)
        pr.append(np.linalg.norm(rs - r_rx) + clock_m + isb_m.get(clock_group(sat), 0.0))
    n = len(sats)
    z = np.zeros(n)
    return PreparedEpoch(
        t_gps=1e9, signal="L1C", r_approx_e=r_rx + 50.0, sats=list(sats), r_sat_e=np.array(r_sat),
        v_sat_e=np.zeros((n, 3)), pseudorange_m=np.array(pr), sigma_pseudorange_m=np.full(n, 1.0),
        sat_clock_bias_m=z, sat_clock_drift_mps=z, carrier_cycles=z, wavelength_m=np.full(n, np.nan),
        doppler_hz=np.full(n, np.nan), cn0_dbhz=z, lock_time_s=z, half_cycle=np.zeros(n, bool),
        loss_of_lock=np.zeros(n, bool), elevation_rad=np.radians([g[0] for g in el_az_deg]),
        azimuth_rad=np.radians([g[1] for g in el_az_deg]), iode=np.zeros(n, int), dgps_age_s=z, iono_m=z,
        tropo_m=z, sigma_pseudorange_slow_m=z)


GEOM = {"G01": (70, 10), "G02": (30, 100), "G03": (25, 200), "G04": (40, 300), "G05": (15, 45),
        "E01": (55, 150), "E02": (20, 250), "E03": (35, 20), "E04": (12, 330),
        "C01": (45, 190), "C02": (60, 280), "C03": (18, 120),
        "J01": (80, 170), "J02": (28, 60)}


def test_isb_recovery_is_exact_on_a_synthetic_two_and_four_system_geometry():
    r_rx = geodetic_to_ecef(math.radians(34.4), math.radians(132.4), 60.0)
    isb = {"E": -6.3, "C": 9.2}
    p = _prepared(r_rx, list(GEOM), 1234.5, isb, list(GEOM.values()))
    sol = solve_spp(p, raim=True)
    assert np.linalg.norm(sol.r_e - r_rx) < 1e-6 and abs(sol.clock_bias_m - 1234.5) < 1e-6
    assert sol.clock_system == "G" and set(sol.isb_m) == {"E", "C"}             # QZSS on the GPS clock
    assert all(abs(sol.isb_m[k] - v) < 1e-6 for k, v in isb.items())
    assert sol.n_sats_by_system == {"G": 5, "E": 4, "C": 3, "J": 2} and sol.raim_ok
    assert float(np.max(np.abs(sol.residuals_m))) < 1e-6
    # two systems only: GPS + Galileo
    two = [s for s in GEOM if s[0] in "GE"]
    sol2 = solve_spp(_prepared(r_rx, two, -77.0, isb, [GEOM[s] for s in two]))
    assert np.linalg.norm(sol2.r_e - r_rx) < 1e-6 and abs(sol2.isb_m["E"] + 6.3) < 1e-6
    # without GPS, Galileo is the reference and the BeiDou bias is relative to it
    sol3 = solve_spp(_prepared(r_rx, [s for s in GEOM if s[0] in "EC"], 5.0, isb,
                               [GEOM[s] for s in GEOM if s[0] in "EC"]))
    assert sol3.clock_system == "E" and abs(sol3.clock_bias_m - (5.0 - 6.3)) < 1e-6
    assert abs(sol3.isb_m["C"] - (9.2 + 6.3)) < 1e-6
    # an ignored bias is not absorbed: one clock for all systems is wrong by metres
    flat = _prepared(r_rx, list(GEOM), 1234.5, isb, list(GEOM.values()))
    flat.sats = ["G%02d" % i for i in range(len(GEOM))]
    assert np.linalg.norm(solve_spp(flat, raim=False).r_e - r_rx) > 1.0


def test_a_system_with_one_satellite_is_dropped_not_fatal():
    r_rx = geodetic_to_ecef(math.radians(34.4), math.radians(132.4), 60.0)
    sats = ["G01", "G02", "G03", "G04", "C01"]
    p = _prepared(r_rx, sats, 10.0, {"C": 50.0}, [GEOM[s] for s in sats])
    sol = solve_spp(p)
    assert sol is not None and np.linalg.norm(sol.r_e - r_rx) < 1e-6
    assert sol.sats == sats[:4] and sol.excluded["C01"] == "too few satellites of its system"
    # 3 GPS + 2 BeiDou = 5 measurements for 5 unknowns: solvable, not testable
    sats = ["G01", "G02", "G03", "C01", "C02"]
    sol = solve_spp(_prepared(r_rx, sats, 10.0, {"C": 50.0}, [GEOM[s] for s in sats]))
    assert sol is not None and np.linalg.norm(sol.r_e - r_rx) < 1e-5 and sol.raim_ok is None
    # 2 + 2: four measurements, five unknowns -> one system goes, the other is too small
    sats = ["G01", "G02", "C01", "C02"]
    assert solve_spp(_prepared(r_rx, sats, 10.0, {"C": 50.0}, [GEOM[s] for s in sats])) is None


def test_raim_excludes_a_fault_in_a_multi_system_epoch():
    r_rx = geodetic_to_ecef(math.radians(34.4), math.radians(132.4), 60.0)
    p = _prepared(r_rx, list(GEOM), 0.0, {"E": 3.0, "C": -4.0}, list(GEOM.values()))
    rng = np.random.default_rng(1)
    p.pseudorange_m = p.pseudorange_m + rng.normal(0.0, 0.3, p.n)
    k = p.sats.index("E02")
    p.pseudorange_m[k] += 40.0
    sol = solve_spp(p)
    assert sol.excluded["E02"].startswith("RAIM") and sol.raim_ok and np.linalg.norm(sol.r_e - r_rx) < 2.0


def test_system_times():
    # BDT began 2006-01-01 00:00:00 UTC = 00:00:14 GPS time (GPS - UTC was 14 s), GPS week 1356
    assert calendar_to_t_gps(2006, 1, 1, 0, 0, 0) + SYSTEM_TO_GPS_S["C"] == gps_time(1356, 14.0)
    assert SYSTEM_WEEK_TO_GPS_WEEK["C"] == 1356
    # GST week 0 began 1999-08-22 00:00:00 GST (= GPS time), GPS week 1024
    assert (dt.datetime(1999, 8, 22) - dt.datetime(1980, 1, 6)).days == 7 * SYSTEM_WEEK_TO_GPS_WEEK["E"]
    assert calendar_to_t_gps(1999, 8, 22, 0, 0, 0) == gps_time(1024, 0.0)
    # a BeiDou clock is evaluated against its toc in BDT: af1 x (t_gps - 14 - toc_bdt)
    kep = dict(sqrt_a=6493.0, e=0.0, i0_rad=0.96, omega0_rad=0.0, omega_rad=0.0, m0_rad=0.0, delta_n_radps=0.0,
               idot_radps=0.0, omega_dot_radps=0.0, cuc_rad=0.0, cus_rad=0.0, crc_m=0.0, crs_m=0.0, cic_rad=0.0,
               cis_rad=0.0, af0_s=1e-4, af1_sps=1e-9, af2_sps2=0.0)
    bds = GpsEphemeris(sat="C20", week=884 + 1356, toe_s=176400.0, toc_s=176400.0, **kep)
    gps = GpsEphemeris(sat="G20", week=2240, toe_s=176400.0, toc_s=176400.0, **kep)
    t = gps_time(2240, 176400.0 + 100.0)
    assert satellite_clock(bds, t)[0] == pytest.approx(1e-4 + 1e-9 * 86.0, abs=1e-16)
    assert satellite_clock(gps, t)[0] == pytest.approx(1e-4 + 1e-9 * 100.0, abs=1e-16)


def test_rinex3_obs_in_bdt_is_moved_to_gps_time(tmp_path):
    hdr = [
        "     3.04           OBSERVATION DATA    C: BeiDou           RINEX VERSION / TYPE",
        "C    4 C2I L2I C6I L6I                                      SYS / # / OBS TYPES ",
        "  2022    12    13    01    09   22.0000000     BDT         TIME OF FIRST OBS   ",
        "                                                            END OF HEADER       "]
    body = ["> 2022 12 13 01 09 22.0000000  0  1",
            "C19  22264577.158   115907238.122    22264571.000    94184080.869  "]
    p = tmp_path / "bdt.rnx"
    p.write_text("\n".join(hdr + body) + "\n")
    h, eps = read_rinex_obs(p, "C")
    assert h["time_system"] == "BDT"
    assert eps[0].t_gps == calendar_to_t_gps(2022, 12, 13, 1, 9, 22.0) + 14.0
    o = {x.signal: x for x in eps[0].observations}
    assert o["L2I"].wavelength_m == pytest.approx(C / 1561.098e6) and o["L6I"].wavelength_m == pytest.approx(C / 1268.52e6)


def test_beidou_group_delays_and_signal_choice():
    kep = dict(week=2240, toe_s=0.0, toc_s=0.0, sqrt_a=5282.0, e=0.0, i0_rad=0.96, omega0_rad=0.0, omega_rad=0.0,
               m0_rad=0.0, delta_n_radps=0.0, idot_radps=0.0, omega_dot_radps=0.0, cuc_rad=0.0, cus_rad=0.0,
               crc_m=0.0, crs_m=0.0, cic_rad=0.0, cis_rad=0.0, af0_s=0.0, af1_sps=0.0, af2_sps2=0.0)
    c = GpsEphemeris(sat="C20", tgd_s=10e-9, tgd2_s=-4e-9, **kep)
    assert group_delay_m(c, ("L2I",), 1.0) == pytest.approx(C * 10e-9)             # B1I: TGD1
    assert group_delay_m(c, ("L7I",), 1.0) == pytest.approx(C * -4e-9)             # B2I: TGD2
    assert group_delay_m(c, ("L6I",), 1.0) == 0.0                                  # B3I: the clock's code
    g1, g3 = 1561.098e6 ** 2, 1268.52e6 ** 2
    assert group_delay_m(c, ("L2I", "L6I"), 0.0) == pytest.approx(C * g1 * 10e-9 / (g1 - g3))
    e = GpsEphemeris(sat="E11", tgd_s=5e-9, **kep)
    assert group_delay_m(e, ("L1C",), 1.0) == C * 5e-9 and group_delay_m(e, ("L1C", "L7Q"), 0.0) == 0.0
    assert frequency_hz("C20", "L2I") == 1561.098e6 and frequency_hz("R01", "L1C") != frequency_hz("R01", "L1C")
    # single frequency: B1I for BeiDou, E1 for Galileo (any attribute), C/A for GPS and QZSS
    obs = {s: SatObservation(sat="C20", pseudorange_m=2.1e7 + k, signal=s) for k, s in enumerate(("L2I", "L6I", "L7I"))}
    p, o, codes, *_ = form_pseudorange(obs, "L1C", "C")
    assert codes == ("L2I",) and p == 2.1e7
    p, o, codes, tgd_fac, iono_fac, noise = form_pseudorange(obs, "IF", "C")
    assert codes == ("L2I", "L6I") and iono_fac == 0.0 and noise == pytest.approx(3.527, abs=1e-3)
    assert p == pytest.approx((g1 * 2.1e7 - g3 * (2.1e7 + 1)) / (g1 - g3))
    gal = {s: SatObservation(sat="E11", pseudorange_m=2.3e7, signal=s) for s in ("L1X", "L5X", "L7X")}
    assert form_pseudorange(gal, "L1C", "E")[2] == ("L1X",) and form_pseudorange(gal, "IF", "E")[2] == ("L1X", "L7X")
