"""Broadcast ephemeris, RINEX nav parsing, earth conversions and atmosphere models against
independent references (other parsers, other formulas, independent data sets)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.gnss.atmosphere import (iono_free, iono_free_noise_factor, klobuchar_delay_m,
                                       saastamoinen_zenith_m, tropo_delay_m)
from companion.gnss.ephemeris import REL_F, satellite_clock, satellite_state, transmit_time
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.rinex import read_rinex_nav, read_rinex_nav_header_iono
from companion.messages import SECONDS_PER_WEEK, SPEED_OF_LIGHT_MPS
from companion.nav.earth import (GM_M3PS2, OMEGA_IE_RADPS, WGS84_A_M, WGS84_B_M, WGS84_E2, C_n_e, ecef_to_geodetic, ecef_to_ned,
                                 geodetic_to_ecef)
from tests._data import data_path

DATA = data_path("rtklib-testdata-geonet-2005/rinex")
NAV = DATA / "07590920.05n"
needs_data = pytest.mark.real_data


@pytest.fixture(scope="module")
def ephs():
    return read_rinex_nav(NAV)


# ------------------------------------------------------------------------------ RINEX nav
@needs_data
def test_nav_parser_matches_georinex(ephs):
    """Every field we use equals georinex's independent parse of the same file."""
    georinex = pytest.importorskip("georinex")
    nav = georinex.load(NAV)
    pairs = [("sqrt_a", "sqrtA"), ("e", "Eccentricity"), ("i0_rad", "Io"), ("omega0_rad", "Omega0"),
             ("omega_rad", "omega"), ("m0_rad", "M0"), ("delta_n_radps", "DeltaN"), ("idot_radps", "IDOT"),
             ("omega_dot_radps", "OmegaDot"), ("cuc_rad", "Cuc"), ("cus_rad", "Cus"), ("crc_m", "Crc"),
             ("crs_m", "Crs"), ("cic_rad", "Cic"), ("cis_rad", "Cis"), ("af0_s", "SVclockBias"),
             ("af1_sps", "SVclockDrift"), ("af2_sps2", "SVclockDriftRate"), ("tgd_s", "TGD"),
             ("iode", "IODE"), ("iodc", "IODC"), ("health", "health"), ("ura_m", "SVacc")]
    assert len(ephs) == 162
    for e in ephs:
        d = nav.sel(sv=e.sat)
        d = d.where((d.Toe == e.toe_s) & (d.IODE == e.iode), drop=True)
        assert d.sizes["time"] == 1, e.sat
        d = d.isel(time=0)
        for ours, theirs in pairs:
            assert getattr(e, ours) == pytest.approx(float(d[theirs]), rel=1e-12, abs=1e-30), (e.sat, ours)
        assert e.week == int(d["GPSWeek"])
        # toc from the epoch line equals georinex's time coordinate (GPS time, no leap seconds)
        t_geo = (np.datetime64(d.time.values, "ns") - np.datetime64("1980-01-06T00:00:00", "ns")) / np.timedelta64(1, "s")
        assert e.t_oc_gps == pytest.approx(float(t_geo), abs=1e-6)


@needs_data
def test_nav_header_klobuchar():
    alpha, beta = read_rinex_nav_header_iono(NAV)
    np.testing.assert_allclose(alpha, [1.1180e-08, 1.4900e-08, -5.9600e-08, -5.9600e-08])
    np.testing.assert_allclose(beta, [8.8060e+04, 1.6380e+04, -1.9660e+05, -1.3110e+05])


# ------------------------------------------------------------------------------ orbits
@needs_data
def test_orbit_radius_and_velocity_is_derivative_of_position(ephs):
    worst = 0.0
    for e in ephs[::4]:
        for dt in (-7200.0, 0.0, 5400.0):
            t = e.t_oe_gps + dt
            r, v, _, drift = satellite_state(e, t)
            assert 25.8e6 < np.linalg.norm(r) < 27.3e6          # a = 26 560 km, e < 0.03
            # vis-viva on the inertial velocity v + omega x r: |v_i|^2 = mu (2/|r| - 1/a)
            v_i = v + np.cross([0.0, 0.0, OMEGA_IE_RADPS], r)
            vis_viva = math.sqrt(GM_M3PS2 * (2.0 / np.linalg.norm(r) - 1.0 / e.sqrt_a ** 2))
            assert np.linalg.norm(v_i) == pytest.approx(vis_viva, rel=1e-3)
            h = 0.5
            rp, _, bp, _ = satellite_state(e, t + h)
            rm, _, bm, _ = satellite_state(e, t - h)
            worst = max(worst, float(np.linalg.norm((rp - rm) / (2 * h) - v)))
            assert drift == pytest.approx((bp - bm) / (2 * h), abs=1e-15)
    assert worst < 1e-3, worst


@needs_data
def test_consecutive_ephemerides_agree_at_boundary(ephs):
    """Two independent broadcast data sets of one satellite (toe 2 h apart) agree half-way."""
    by: dict[str, list] = {}
    for e in ephs:
        by.setdefault(e.sat, []).append(e)
    n = 0
    worst_r = worst_clk = 0.0
    for lst in by.values():
        lst.sort(key=lambda e: e.t_oe_gps)
        for a, b in zip(lst, lst[1:]):
            if b.t_oe_gps - a.t_oe_gps != 7200.0:
                continue
            t = 0.5 * (a.t_oe_gps + b.t_oe_gps)
            ra, _, ca, _ = satellite_state(a, t)
            rb, _, cb, _ = satellite_state(b, t)
            worst_r = max(worst_r, float(np.linalg.norm(ra - rb)))
            worst_clk = max(worst_clk, abs(ca - cb) * SPEED_OF_LIGHT_MPS)
            n += 1
    print(f"\n{n} ephemeris pairs: worst position jump {worst_r:.3f} m, clock jump {worst_clk:.3f} m")
    assert n >= 50
    assert worst_r < 4.0
    assert worst_clk < 1.5


@needs_data
def test_relativistic_clock_term_equals_minus_2_r_dot_v_over_c2(ephs):
    """dt_rel = F e sqrt(A) sin E must equal the independent form -2 r.v / c^2 (r.v is frame-invariant)."""
    for e in ephs[::7]:
        for dt in (-3600.0, 0.0, 2000.0):
            t = e.t_oe_gps + dt
            r, v, bias, _ = satellite_state(e, t)
            tc = t - e.t_oc_gps
            poly = e.af0_s + e.af1_sps * tc + e.af2_sps2 * tc * tc
            rel = bias - poly
            assert abs(rel) <= abs(REL_F) * e.e * e.sqrt_a + 1e-15
            assert rel == pytest.approx(-2.0 * float(r @ v) / SPEED_OF_LIGHT_MPS ** 2, abs=1e-10)


@needs_data
def test_satellite_clock_alone_is_satellite_states_clock_to_the_bit(ephs):
    """The DD front end takes its first light-time iteration's clock from satellite_clock alone."""
    for e in ephs[::3]:
        for dt in (-7000.0, -1.5e-3, 0.0, 0.07, 3600.0):
            t = e.t_oe_gps + dt
            assert satellite_clock(e, t)[0] == satellite_state(e, t)[2]


@needs_data
def test_week_crossover_is_continuous(ephs):
    """An ephemeris with toe 2 h before the end of the week, evaluated across the week boundary."""
    e0 = ephs[0]
    e = dataclasses.replace(e0, toe_s=597600.0, toc_s=597600.0)
    t_b = (e.week + 1) * SECONDS_PER_WEEK
    r_m, v_m, c_m, d_m = satellite_state(e, t_b - 0.5)
    r_p, v_p, c_p, d_p = satellite_state(e, t_b + 0.5)
    np.testing.assert_allclose(r_p - r_m, 0.5 * (v_m + v_p), atol=1e-3)
    assert c_p - c_m == pytest.approx(0.5 * (d_m + d_p), abs=1e-13)
    # the same instant expressed through the time-of-week difference folds correctly
    r1, _, _, _ = satellite_state(e, e.t_oe_gps + 3600.0)
    assert np.linalg.norm(r1) == pytest.approx(np.linalg.norm(satellite_state(e0, e0.t_oe_gps + 3600.0)[0]), abs=1e-6)
    # clock polynomial referenced to the previous week's toc
    bias, _ = satellite_clock(e, t_b + 100.0)
    assert abs(bias - e.af0_s) < 1e-6


@needs_data
def test_transmit_time_consistent(ephs):
    e = ephs[3]
    t_rx = e.t_oe_gps + 100.0
    p = 22.0e6
    t_tx = transmit_time(t_rx, p, e)
    bias, _ = satellite_clock(e, t_tx)
    assert t_tx + bias == pytest.approx(t_rx - p / SPEED_OF_LIGHT_MPS, abs=1e-12)


@needs_data
def test_ephemeris_store_selection(ephs):
    store = EphemerisStore(ephs)
    n0 = len(store)
    assert not store.add(ephs[0]) and store.rejections["duplicate"] == 1 and len(store) == n0
    t = ephs[0].t_oe_gps + 1000.0
    sel = store.select(ephs[0].sat, t)
    cands = [e for e in ephs if e.sat == ephs[0].sat]
    assert abs(sel.t_oe_gps - t) == min(abs(e.t_oe_gps - t) for e in cands)
    assert store.select("G99", t) is None and store.rejections["no ephemeris"] == 1
    assert store.select(ephs[0].sat, t + 30 * 86400.0) is None
    assert store.rejections["outside fit interval"] == 1
    bad = dataclasses.replace(cands[0], health=1, iode=999)
    s2 = EphemerisStore([bad])
    assert s2.select(bad.sat, bad.t_oe_gps) is None and s2.rejections["unhealthy"] == 1


# ------------------------------------------------------------------------------ earth
def _vermeille(r):
    """Exact closed-form ECEF -> geodetic (Vermeille 2004), independent of earth.py's Bowring + Newton."""
    x, y, z = r
    a, e2 = WGS84_A_M, WGS84_E2
    p = (x * x + y * y) / a ** 2
    q = (1 - e2) / a ** 2 * z * z
    rr = (p + q - e2 ** 2) / 6.0
    s = e2 ** 2 * p * q / (4 * rr ** 3)
    t = (1 + s + math.sqrt(s * (2 + s))) ** (1 / 3)
    u = rr * (1 + t + 1 / t)
    v = math.sqrt(u * u + e2 ** 2 * q)
    w = e2 * (u + v - q) / (2 * v)
    k = math.sqrt(u + v + w * w) - w
    d = k * math.hypot(x, y) / (k + e2)
    lat = 2 * math.atan2(z, d + math.hypot(d, z))
    lon = math.atan2(y, x)
    h = (k + e2 - 1) / k * math.hypot(d, z)
    return lat, lon, h


def test_geodetic_known_points():
    np.testing.assert_allclose(geodetic_to_ecef(0.0, 0.0, 0.0), [WGS84_A_M, 0, 0], atol=1e-9)
    np.testing.assert_allclose(geodetic_to_ecef(math.pi / 2, 0.3, 0.0), [0, 0, WGS84_B_M], atol=1e-6)
    lat, lon, h = ecef_to_geodetic([0.0, 0.0, -WGS84_B_M - 100.0])
    assert lat == pytest.approx(-math.pi / 2) and h == pytest.approx(100.0, abs=1e-6)
    lat, lon, h = ecef_to_geodetic([0.0, WGS84_A_M + 20.0e6, 0.0])
    assert (lat, lon, h) == pytest.approx((0.0, math.pi / 2, 20.0e6), abs=1e-6)
    # GEONET 0759 header position vs the exact closed form
    r = np.array([-3976219.5082, 3382372.5671, 3652512.9849])
    ours, ref = ecef_to_geodetic(r), _vermeille(r)
    assert ours[0] == pytest.approx(ref[0], abs=1e-11) and ours[1] == pytest.approx(ref[1], abs=1e-12)
    assert ours[2] == pytest.approx(ref[2], abs=1e-4)
    assert math.degrees(ours[0]) == pytest.approx(35.16, abs=0.01)     # Kanto, Japan
    assert math.degrees(ours[1]) == pytest.approx(139.61, abs=0.01)


def test_geodetic_round_trip_many_points():
    rng = np.random.default_rng(1)
    lats = np.concatenate([rng.uniform(-math.pi / 2, math.pi / 2, 300), [math.pi / 2 - 1e-9, -math.pi / 2 + 1e-9, 0.0]])
    lons = rng.uniform(-math.pi, math.pi, len(lats))
    hs = np.concatenate([rng.uniform(-400.0, 20.2e6, len(lats) - 3), [0.0, 20.0e6, 20.0e6]])
    for lat, lon, h in zip(lats, lons, hs):
        r = geodetic_to_ecef(lat, lon, h)
        lat2, lon2, h2 = ecef_to_geodetic(r)
        assert np.linalg.norm(geodetic_to_ecef(lat2, lon2, h2) - r) < 1e-4
        assert h2 == pytest.approx(h, abs=1e-4)
        if abs(lat) < math.pi / 2 - 1e-6:
            lv, _, hv = _vermeille(r)
            assert lat2 == pytest.approx(lv, abs=1e-10) and h2 == pytest.approx(hv, abs=1e-3)


def test_ned_frame():
    lat, lon = math.radians(35.0), math.radians(139.0)
    c = C_n_e(lat, lon)
    np.testing.assert_allclose(c.T @ c, np.eye(3), atol=1e-14)
    r0 = geodetic_to_ecef(lat, lon, 50.0)
    np.testing.assert_allclose(ecef_to_ned(geodetic_to_ecef(lat, lon, 150.0), r0), [0, 0, -100.0], atol=1e-6)
    d = ecef_to_ned(geodetic_to_ecef(lat + 1e-5, lon, 50.0), r0)
    assert d[0] > 63.0 and abs(d[1]) < 1e-3          # 1e-5 rad of latitude ~ 63.5 m north


# ------------------------------------------------------------------------------ atmosphere
def test_saastamoinen_zenith_sea_level():
    zhd, zwd = saastamoinen_zenith_m(math.radians(45.0), 0.0)
    assert 2.28 < zhd < 2.33                        # 2.2768 m/1000 hPa x 1013.25 hPa
    assert 2.3 < zhd + zwd < 2.5
    assert tropo_delay_m(math.radians(45.0), 0.0, math.pi / 2) == pytest.approx(zhd + zwd, rel=1e-3)
    # 5 km altitude: about half the pressure; low elevation: ~10x zenith at 5 deg
    assert 1.2 < sum(saastamoinen_zenith_m(0.0, 5000.0)) < 1.4
    assert 9.0 < tropo_delay_m(0.0, 0.0, math.radians(5.0)) / (zhd + zwd) < 12.0


@needs_data
def test_klobuchar_day_and_night():
    alpha, beta = read_rinex_nav_header_iono(NAV)
    lat, lon = math.radians(35.16), math.radians(139.61)
    t0 = 1316 * SECONDS_PER_WEEK + 6 * 86400.0                        # 2005-04-02 00:00 GPS
    # local time = UT + 9.3 h: 14:00 local ~ 04:40 UT (day peak); 02:00 local ~ 16:40 UT (night)
    day = klobuchar_delay_m(t0 + 4.7 * 3600, lat, lon, 0.0, math.pi / 2, alpha, beta)
    night = klobuchar_delay_m(t0 + 16.7 * 3600, lat, lon, 0.0, math.pi / 2, alpha, beta)
    assert night == pytest.approx(SPEED_OF_LIGHT_MPS * 5e-9 * (1 + 16 * (0.53 - 0.5) ** 3), rel=1e-6)
    assert 2.0 < day < 15.0 and day > 1.5 * night
    low = klobuchar_delay_m(t0 + 4.7 * 3600, lat, lon, 0.0, math.radians(10.0), alpha, beta)
    assert 2.0 < low / day < 3.2                      # obliquity factor F at 10 deg ~ 2.5


def test_iono_free():
    f1, f2 = 1575.42e6, 1227.60e6
    rho, i1 = 2.2e7, 5.0
    p1, p2 = rho + i1, rho + i1 * (f1 / f2) ** 2
    assert iono_free(p1, p2) == pytest.approx(rho, abs=1e-6)
    assert iono_free_noise_factor() == pytest.approx(2.978, abs=0.01)


_RINEX3_NAV = """\
     3.04           N: GNSS NAV DATA    M                   RINEX VERSION / TYPE
GPSA   1.1180E-08  1.4900E-08 -5.9600E-08 -5.9600E-08       IONOSPHERIC CORR
GPSB   8.8060E+04  1.6380E+04 -1.9660E+05 -1.3110E+05       IONOSPHERIC CORR
                                                            END OF HEADER
R05 2005 04 02 02 00 00 3.966595977540E-04 1.705302565820E-12 0.000000000000E+00
     1.400000000000E+02-5.218750000000E+01 4.026596389650E-09 2.871534990340E+00
    -2.676621079440E-06 5.957618006510E-03 4.174187779430E-06 5.153636478420E+03
     5.256000000000E+05 1.061707735060E-07-2.493184817740E+00-9.313225746150E-08
G01 2005 04 02 02 00 00 3.966595977540E-04 1.705302565820E-12 0.000000000000E+00
     1.400000000000E+02-5.218750000000E+01 4.026596389650E-09 2.871534990340E+00
    -2.676621079440E-06 5.957618006510E-03 4.174187779430E-06 5.153636478420E+03
     5.256000000000E+05 1.061707735060E-07-2.493184817740E+00-9.313225746150E-08
     9.833919144490E-01 3.093750000000E+02-1.650496813270E+00-7.889971342930E-09
    -8.571785642400E-12 1.000000000000E+00 1.316000000000E+03 0.000000000000E+00
     1.000000000000E+00 0.000000000000E+00-3.259629011150E-09 3.960000000000E+02
     5.195760000000E+05 4.000000000000E+00
"""


@needs_data
def test_rinex3_nav_record_equals_rinex2_record(tmp_path, ephs):
    """The first record of the GEONET file rewritten in RINEX 3 layout (plus a GLONASS record to skip)."""
    p = tmp_path / "brdc.rnx"
    p.write_text(_RINEX3_NAV)
    e3 = read_rinex_nav(p)
    assert len(e3) == 1
    assert e3[0] == ephs[0]
    alpha, beta = read_rinex_nav_header_iono(p)
    np.testing.assert_allclose(alpha, read_rinex_nav_header_iono(NAV)[0])
    np.testing.assert_allclose(beta, read_rinex_nav_header_iono(NAV)[1])
