"""Multi-GNSS observations in the offline simulator (issue 11): the Galileo/BeiDou ephemerides of
the Hiroshima RTCM stream moved onto the simulated epoch (sitl.sky_multignss), the 'uav-gec'
scenario's observables, the companion's SPP on them, and GPS-only scenarios unchanged."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.gnss.ephemeris import is_beidou_geo, satellite_state
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.spp import spp_epoch
from companion.messages import SPEED_OF_LIGHT_MPS, GpsEphemeris
from sitl import sky, sky_multignss
from sitl.scenario import build_scenario
from sitl.simulate import simulate

from tests._data import data_path

C = SPEED_OF_LIGHT_MPS
SHORT_S = 12.0      # simulated seconds: the first epochs of each scenario


def _short(name: str):
    return dataclasses.replace(build_scenario(name), duration_s=SHORT_S)


@pytest.fixture(scope="module")
def gec():
    return simulate(_short("uav-gec"), 3)


def test_moved_ephemerides_reproduce_the_recorded_orbits_and_clocks():
    rec = sky_multignss.recorded_ephemerides()
    t0 = build_scenario("uav").t0_gps
    dt = math.floor(t0) - sky_multignss.RECORDING_T_GPS
    moved = [sky_multignss.move_ephemeris(e, dt) for e in rec]
    assert {e.sat[0] for e in rec} == {"E", "C"} and sum(is_beidou_geo(e.sat) for e in rec) >= 5
    for a, b in zip(rec, moved):
        assert b.week != a.week and 0.0 <= b.toe_s < 604800.0     # the week bookkeeping is exercised
        assert b.t_oe_gps - a.t_oe_gps == pytest.approx(dt, abs=1e-6)
        assert b.t_oc_gps - a.t_oc_gps == pytest.approx(dt, abs=1e-6)
        for tk in (-5400.0, -60.0, 0.0, 977.5, 7200.0):
            ra, va, ca, _ = satellite_state(a, a.t_oe_gps + tk)
            rb, vb, cb, _ = satellite_state(b, b.t_oe_gps + tk)
            # MEO, IGSO and GEO alike, to the node's rounding onto its broadcast grid (2^-31 sc)
            assert np.linalg.norm(rb - ra) < 0.05, (a.sat, tk)
            assert np.linalg.norm(vb - va) < 1e-5
            assert abs(cb - ca) * C < 1e-6
    # Omega0 shifted by omega_e x dt (the naive rule) would miss: omega_e x 1 week is not 0 mod 2 pi
    a = rec[0]
    naive = dataclasses.replace(moved[0], omega0_rad=a.omega0_rad + 7.2921151467e-5 * dt)
    assert np.linalg.norm(satellite_state(naive, naive.t_oe_gps)[0] - satellite_state(a, a.t_oe_gps)[0]) > 1e5


@pytest.mark.real_data
def test_shipped_frames_are_the_streams_ephemerides():
    """sitl/data's ephemeris frames decode to exactly what the whole recording gives."""
    from companion.io.rtcm import decode_rtcm_file
    msgs, _ = decode_rtcm_file(str(data_path("qzsl6tool-hiroshima-rtcm3-ubx/20221213-010900.rtcm")),
                               week_hint=sky_multignss.RECORDING_WEEK)
    full = {m.sat: m for m in msgs if isinstance(m, GpsEphemeris) and m.sat[0] in "EC"}
    shipped = {e.sat: e for e in sky_multignss.recorded_ephemerides()}
    assert shipped == full
    first_epoch = min(m.t_gps for m in msgs if hasattr(m, "observations"))
    assert first_epoch == sky_multignss.RECORDING_T_GPS


def test_uav_gec_sky_has_galileo_and_beidou_with_their_wavelengths(gec):
    scn = gec.scenario
    assert scn.systems == "GEC" and scn.mask_deg == 10.0
    lam = {"G": C / 1575.42e6, "E": C / 1575.42e6, "C": C / 1561.098e6}
    sig = {"G": "L1C", "E": "L1C", "C": "L2I"}
    counts = {s: [] for s in "GEC"}
    for ep in gec.rover_epochs + gec.base_epochs:
        for s in "GEC":
            counts[s].append(sum(o.sat[0] == s for o in ep.observations))
        for o in ep.observations:
            assert o.signal == sig[o.sat[0]] and o.wavelength_m == pytest.approx(lam[o.sat[0]], rel=1e-12)
    assert min(counts["E"]) >= 6 and min(counts["C"]) >= 12 and min(counts["G"]) >= 6
    # carrier and Doppler agree on each satellite's range rate: the right wavelength in both
    # (an E1 wavelength on a B1I carrier would leave 0.9 % of ~700 m/s)
    ep0, ep1 = gec.rover_epochs[3], gec.rover_epochs[4]
    o0 = {o.sat: o for o in ep0.observations}
    for o in ep1.observations:
        tdcp = (o.carrier_cycles - o0[o.sat].carrier_cycles) * o.wavelength_m
        dop = -0.5 * (o.doppler_hz + o0[o.sat].doppler_hz) * o.wavelength_m
        assert abs(tdcp - dop) < 0.3, o.sat
    # the ionosphere scales with (f_L1/f)^2: the code-minus-carrier divergence of a B1I satellite
    # is 2 x 1.0184 x its L1 delay
    err = gec.errors["rover"]
    j = err["sats"].index(next(o.sat for o in ep1.observations if o.sat[0] == "C"))
    k = 4
    o = next(x for x in ep1.observations if x.sat == err["sats"][j])
    cmc = o.pseudorange_m - o.carrier_cycles * o.wavelength_m + err["ambiguity_cycles"][k, j] * o.wavelength_m
    site = err["code_mp_m"][k, j] + err["code_noise_m"][k, j] - err["carrier_mp_m"][k, j] - err["carrier_noise_m"][k, j]
    assert cmc - site == pytest.approx(2.0 * (1575.42 / 1561.098) ** 2 * err["iono_m"][k, j], abs=1e-6)


def test_spp_on_a_uav_gec_epoch_lands_near_the_truth_with_every_system(gec):
    scn = gec.scenario
    store = EphemerisStore(gec.ephemerides)
    klo = (scn.klobuchar_alpha, scn.klobuchar_beta)
    err = gec.errors["rover"]
    for k in (0, 6, 11):
        ep = gec.rover_epochs[k]
        sol = spp_epoch(ep, store, klobuchar=klo, systems="GEC")
        truth = gec.antenna_at(float(err["t_gps"][k]))
        assert np.linalg.norm(sol.r_e - truth) < 4.0
        assert sol.n_sats_by_system["E"] >= 6 and sol.n_sats_by_system["C"] >= 12 and not sol.excluded
        # the estimated inter-system biases are the simulated ones (plus a few metres of the
        # group-delay, orbit and atmosphere residuals common to a system)
        for s in "EC":
            j = next(i for i, x in enumerate(err["sats"]) if x[0] == s and np.isfinite(err["isb_m"][k, i]))
            assert sol.isb_m[s] == pytest.approx(err["isb_m"][k, j], abs=3.0)


def _digest(eps):
    return [(ep.t_gps, len(ep.observations), sum(o.pseudorange_m for o in ep.observations),
             sum(o.carrier_cycles for o in ep.observations),
             sum(o.doppler_hz for o in ep.observations if o.doppler_hz == o.doppler_hz))
            for ep in (eps[0], eps[5], eps[11])]


#: epochs 0, 5, 11 of the 12-s scenarios at seed 3, computed with the simulator before multi-GNSS
#: (commit e00d939): (t_gps, observations, sum of pseudoranges m, carrier cycles, Doppler Hz)
_BEFORE = {
    "uav/rover": [(796436401.0, 7, 155958722.1048938, 818843531.4445589, 1702.6149332454154),
                  (796436406.0, 7, 155957103.32005078, 818835053.0542028, 1680.7992015969376),
                  (796436412.0, 7, 155955156.36313367, 818824819.5115018, 1728.5314291698853)],
    "uav/base": [(796436401.0, 7, 155959172.46131733, 820325948.0967875, 1664.0799253372875),
                 (796436406.0, 7, 155957591.33381516, 820317633.1232717, 1650.839886187656),
                 (796436412.0, 7, 155955721.02873465, 820307810.3118306, 1643.5010451582616)],
    "rtk/rover": [(796436401.0, 14, 311917466.3281654, 1460460574.9390001, 1702.6147472683551),
                  (796436406.0, 14, 311914235.6572849, 1460445489.800141, 1680.7989960433445),
                  (796436412.0, 14, 311910344.85817236, 1460427282.0724013, 1728.5311844632276)],
    "rtk/base": [(796436401.0, 14, 311916928.0108263, 1456438998.159285, 1662.4272646627815),
                 (796436406.0, 14, 311913768.1613156, 1456424218.7203379, 1649.1846903521712),
                 (796436412.0, 14, 311910031.5778815, 1456406759.4251816, 1641.8427562306183)],
    "paper/rover": [(796168801.0, 5, 118047705.1127364, 619192361.9248054, -507.8298796974),
                    (796168806.0, 5, 118048173.76558939, 619194856.398862, -498.1217343027488),
                    (796168812.0, 5, 118048728.61108282, 619197748.7936332, -473.9328620160827)],
    "paper/base": [(796168801.0, 5, 118055015.39902031, 620474911.4122223, -524.6982517924073),
                   (796168806.0, 5, 118055511.2738972, 620477515.4498149, -526.0390320380957),
                   (796168812.0, 5, 118056120.2851056, 620480715.6593004, -526.0418783944579)],
}


@pytest.mark.parametrize("name", ["uav", "rtk", "paper"])
def test_gps_only_scenarios_are_unchanged(name):
    """Any change to a GPS random stream or its arithmetic moves these sums by metres; the
    tolerance only absorbs a libm's last bits on another platform."""
    sim = simulate(_short(name), 3)
    for who, eps in (("rover", sim.rover_epochs), ("base", sim.base_epochs)):
        for got, want in zip(_digest(eps), _BEFORE[f"{name}/{who}"]):
            assert got[:2] == want[:2]
            assert got[2] == pytest.approx(want[2], abs=1e-5)
            assert got[3] == pytest.approx(want[3], abs=1e-4)
            assert got[4] == pytest.approx(want[4], abs=1e-6)


def test_gps_part_of_uav_gec_is_uav_bit_for_bit(gec):
    """Galileo and BeiDou draw from their own streams: the GPS observables of 'uav-gec' are those
    of 'uav' exactly, so the two scenarios compare the systems on the same GPS errors."""
    uav = simulate(_short("uav"), 3)
    for a, b in ((uav.rover_epochs, gec.rover_epochs), (uav.base_epochs, gec.base_epochs)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            assert x.t_gps == y.t_gps
            assert x.observations == tuple(o for o in y.observations if o.sat[0] == "G")


def test_moved_sky_is_japans_at_the_recording():
    """At the scenario start the moved satellites are where they were at the recording plus the
    shift's rounding onto its 120-s grid (to the node's rounding, cm), and the BeiDou GEOs, fixed
    over the equator, are above Hiroshima's horizon as when it tracked them."""
    t0 = math.floor(build_scenario("uav").t0_gps)
    hiro = np.array([-3551876.8287, 3887786.8598, 3586946.3873])     # the stream's 1005 ARP
    rec = {e.sat: e for e in sky_multignss.recorded_ephemerides()}
    late = (t0 - sky_multignss.RECORDING_T_GPS) % sky_multignss.SHIFT_GRID_S
    assert 0.0 <= late < sky_multignss.SHIFT_GRID_S
    for e in sky_multignss.moved_ephemerides(t0):
        r_new = sky.light_time_range(e, t0, sky.GEONET_0759_R_E)[2]
        r_old = sky.light_time_range(rec[e.sat], sky_multignss.RECORDING_T_GPS + late, sky.GEONET_0759_R_E)[2]
        assert np.linalg.norm(r_new - r_old) < 0.05
        if is_beidou_geo(e.sat):
            el = sky.elevation_azimuth(hiro, r_new)[0]
            assert el > 0.0, e.sat
