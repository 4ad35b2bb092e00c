"""GLONASS broadcast ephemerides (companion.gnss.glonass) and GLONASS in the post-processing RTK,
checked against physics and real receivers, since no precise orbit is at hand:

* consecutive broadcast states of one satellite, 30 min apart, meet when one is integrated to the
  other (metres; without J2 or the earth rotation they miss by 160 m and 800 km);
* the pseudoranges of a receiver at a known position fit the modelled ranges as closely as GPS's
  do (a wrong time scale, clock sign or orbit would put them kilometres apart);
* the double-differenced carrier of two real receivers at their reference positions is as steady
  as GPS's (millimetres);
* each satellite's carrier on its own FDMA channel's wavelength follows its pseudorange (the
  neighbouring channel's drifts 3.5e-4 of the range change away).

Then in ``companion gnss --mode rtk``: float GLONASS ambiguities help the float solution; its
integers are fixed between two receivers of one model (closer to the reference) and kept float
between two makes (forced, they are wrong); an RTCM base capture brings its own 1020 ephemerides.
"""
from __future__ import annotations

import dataclasses
import gzip
import json
import shutil

import numpy as np
import pytest

from companion.gnss import glonass
from companion.gnss.double_difference import elevation_rad, model_range_m, receiver_sats
from companion.gnss.ephemeris import satellite_state
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.rinex import read_rinex_nav
from companion.gnss.rinex_obs import read_rinex_obs
from companion.gnss.rtk import RtkConfig
from companion.gnss.rtk_post import antenna_delta_e, solve_rtk_rinex
from companion.rtk_signals import RTK_SIGNALS_BY_SYSTEM, rtk_epoch
from tests._data import data_path

pytestmark = pytest.mark.real_data

CAR = data_path("rokubun-mosaicx5-car-2020")
STATIC = data_path("matrtklib-septentrio-static-2024")
NAVS = (CAR / "nav.rnx.gz", STATIC / "base.nav.gz")
#: tests/test_rtk_septentrio_static.py's reference positions (upstream, PROVENANCE.md)
BASE_XYZ = np.array((-3817681.121326613, 3562839.431140291, 3650159.1593410783))
REF_ROVER = np.array([-3817681.380653759, 3562839.978457426, 3650158.375961049])


def _worst_meeting(ephs) -> tuple[float, float]:
    """(position m, velocity m/s) of the worst meeting of consecutive states 30 min apart."""
    by_sat: dict[str, list] = {}
    for e in ephs:
        by_sat.setdefault(e.sat, []).append(e)
    worst, worst_v, pairs = 0.0, 0.0, 0
    for lst in by_sat.values():
        lst.sort(key=lambda e: e.t_oe_gps)
        for a, b in zip(lst, lst[1:]):
            if b.t_oe_gps - a.t_oe_gps == 1800.0:
                r, v, _, _ = glonass.satellite_state(a, b.t_oe_gps)
                worst = max(worst, float(np.linalg.norm(r - b.r_e)))
                worst_v = max(worst_v, float(np.linalg.norm(v - b.v_e)))
                pairs += 1
    assert pairs >= 9
    return worst, worst_v


@pytest.mark.parametrize("nav", NAVS, ids=["car-2020", "static-2024"])
def test_consecutive_broadcast_states_meet_when_integrated(nav, monkeypatch):
    ephs = read_rinex_nav(nav, "R")
    assert ephs and all(isinstance(e, glonass.GlonassEphemeris) for e in ephs)
    r_m, v_mps = _worst_meeting(ephs)
    assert r_m < 6.0 and v_mps < 0.01                        # measured 3.7 and 4.8 m, 3.8 and 5.6 mm/s
    monkeypatch.setattr(glonass, "J2_GLO", 0.0)
    ephs = read_rinex_nav(nav, "R")                          # fresh: each ephemeris keeps its integrated states
    assert _worst_meeting(ephs)[0] > 100.0                   # the oblateness matters: 164 m


def test_velocity_is_the_derivative_of_the_position_and_the_clock_runs_from_tb():
    e = read_rinex_nav(NAVS[0], "R")[0]
    t = e.t_oe_gps + 300.0
    r, v, bias, drift = satellite_state(e, t)                 # dispatched from the Keplerian module
    fd = satellite_state(e, t + 0.5)[0] - satellite_state(e, t - 0.5)[0]
    assert np.allclose(fd, v, atol=1e-3)
    assert bias == pytest.approx(e.clock_bias_s + e.clock_rate * 300.0) and drift == e.clock_rate
    assert np.array_equal(satellite_state(e, e.t_oe_gps)[0], e.r_e)


def test_rinex_records_read_with_their_channel_and_the_header_leap_seconds(tmp_path):
    ephs = read_rinex_nav(NAVS[0], "GRECJ")
    glo = [e for e in ephs if e.sat[0] == "R"]
    assert len(glo) == 44 and len(ephs) > len(glo)
    assert read_rinex_nav(NAVS[0]) == [e for e in ephs if e.sat[0] != "R"]    # not asked: not read
    r04 = glo[0]
    assert r04.sat == "R04" and r04.frequency_channel == 6 and r04.health == 0
    # 2020-11-29 10:15:00 UTC + 18 s
    assert r04.t_oe_gps == pytest.approx((2134 * 7 + 0) * 86400.0 + 10 * 3600 + 15 * 60 + 18.0)
    assert r04.r_e[0] == pytest.approx(2131593.261719)
    # a RINEX 3.05 record has a fifth line; a file without LEAP SECONDS takes them from the date
    lines = [ln for ln in gzip.open(NAVS[0], "rt").read().splitlines() if "LEAP SECONDS" not in ln]
    text, k = [], 0
    while k < len(lines):
        if lines[k].startswith("R"):
            text += lines[k:k + 4] + ["    " + " 0.000000000000e+00" * 3 + " 1.000000000000e+00"]
            k += 4
        else:
            text.append(lines[k])
            k += 1
    f = tmp_path / "v305.rnx"
    f.write_text("\n".join(text) + "\n")
    again = [e for e in read_rinex_nav(f, "GRECJ") if e.sat[0] == "R"]
    assert len(again) == 44
    assert all(a.t_oe_gps == b.t_oe_gps and np.array_equal(a.r_e, b.r_e) for a, b in zip(again, glo))
    # not asked for, the five-line records are stepped over whole (a four-line step misread them)
    assert read_rinex_nav(f) == read_rinex_nav(NAVS[0])
    # a record with an impossible frequency channel (wrong carriers) or cut short is left out
    k = next(i for i, ln in enumerate(text) if ln.startswith("R04"))
    bad = list(text)
    bad[k + 2] = bad[k + 2][:61] + "9.900000000000e+01" + bad[k + 2][79:]
    last = max(i for i, ln in enumerate(bad) if ln.startswith("R"))
    f.write_text("\n".join(bad[:last + 2]) + "\n")                  # the file ends two lines into it
    left = [e for e in read_rinex_nav(f, "R")]
    assert len(left) == 42 and all(-7 <= e.frequency_channel <= 13 for e in left)


def _as_rinex2_glonass(path, leap_line: bool) -> str:
    """A RINEX 3 file's GLONASS records written as a RINEX 2.11 'G' file (a .g beside a .n, as
    CORS archives still serve them): 'PP YY MM DD HH MM SS.S', fields two columns to the left."""
    lines = gzip.open(path, "rt").read().splitlines()
    out = ["     2.11           G: GLONASS NAV DATA                     RINEX VERSION / TYPE"]
    if leap_line:
        out.append(f"{18:6d}" + " " * 54 + "LEAP SECONDS")
    out.append(" " * 60 + "END OF HEADER")
    for k, ln in enumerate(lines):
        if ln.startswith("R"):
            yy, mo, dd, hh, mi, ss = (int(v) for v in ln[4:23].split())
            out.append(f"{int(ln[1:3]):2d} {yy % 100:02d}{mo:3d}{dd:3d}{hh:3d}{mi:3d}{ss:5.1f}"
                       + ln[23:80].replace("E", "D"))
            out += [ln2[1:].replace("E", "D") for ln2 in lines[k + 1:k + 4]]
    return "\n".join(out) + "\n"


@pytest.mark.parametrize("leap_line", [True, False])
def test_a_rinex2_glonass_navigation_file_reads_as_its_rinex3_records(leap_line, tmp_path):
    """A RINEX 2 GLONASS file (.g) gives the ephemerides the same records give in RINEX 3, leap
    seconds from its header or the date; before, it stopped the run ('not a GPS navigation file')."""
    from companion.cli import main
    v3 = [e for e in read_rinex_nav(NAVS[1], "R")]
    g = tmp_path / "base.24g"
    g.write_text(_as_rinex2_glonass(NAVS[1], leap_line))
    v2 = read_rinex_nav(g, "GRECJ")
    assert len(v2) == len(v3) == 19
    for a, b in zip(v2, v3):
        assert (a.sat, a.t_oe_gps, a.frequency_channel, a.health, a.clock_bias_s, a.clock_rate) == \
            (b.sat, b.t_oe_gps, b.frequency_channel, b.health, b.clock_bias_s, b.clock_rate)
        assert all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("r_e", "v_e", "a_e"))
    assert read_rinex_nav(g, "GECJ") == []                   # GLONASS not asked for
    # beside a GPS file on the command line: SPP with GLONASS on the Septentrio rover
    assert main(["gnss", "--rover", str(STATIC / "rover.crx.gz"), "--nav", str(NAVS[1]), str(g), "--sys", "G,R",
                 "--mode", "spp"]) == 0


def test_leap_seconds_by_date():
    day = 86400.0
    assert glonass.gps_minus_utc_s(2134 * 7 * day) == 18            # 2020
    assert glonass.gps_minus_utc_s(1860 * 7 * day) == 17            # 2015-08
    assert glonass.gps_minus_utc_s(1800 * 7 * day) == 16            # 2014-07
    assert glonass.gps_minus_utc_s(1330 * 7 * day) == 13            # 2005-07 (14 from 2006)
    assert glonass.gps_minus_utc_s(1400 * 7 * day) == 14            # 2006-11


def _static_epochs(systems: str):
    hr, rover = read_rinex_obs(STATIC / "rover.crx.gz", systems)
    hb, base = read_rinex_obs(STATIC / "base.crx.gz", systems)
    store = EphemerisStore(read_rinex_nav(STATIC / "base.nav.gz", systems))
    r_ant = REF_ROVER + antenna_delta_e(REF_ROVER, hr.get("antenna_delta_hen_m"))
    b_ant = BASE_XYZ + antenna_delta_e(BASE_XYZ, hb.get("antenna_delta_hen_m"))
    return rover, base, store, r_ant, b_ant


def _code_spread_m(store, base, b_ant) -> dict:
    spread = {"G": [], "R": []}
    for ep in base[::30]:
        sats = receiver_sats(rtk_epoch(ep), store, b_ant, {k: RTK_SIGNALS_BY_SYSTEM[k] for k in "GR"})
        for sys_ in "GR":
            res = np.array([q.code_m["L1C"] - model_range_m(b_ant, q)[0] for s, q in sats.items()
                            if s[0] == sys_ and "L1C" in q.code_m and elevation_rad(b_ant, q.r_sat_e) > 0.17])
            assert len(res) >= 5
            spread[sys_].append(float(np.std(res - np.median(res))))
    return spread


def test_pseudoranges_fit_as_well_as_gps_at_the_known_position():
    """Code minus modelled range of the base's satellites above 10 degrees, about the epoch's
    median (the receiver clock): GLONASS's spread is GPS's (both are mostly ionosphere)."""
    _, base, store, _, b_ant = _static_epochs("GR")
    spread = _code_spread_m(store, base, b_ant)
    print({k: np.round(v, 2) for k, v in spread.items()})
    assert max(spread["R"]) < max(spread["G"]) + 1.0                  # measured 3.6-4.0 against 4.3-4.4 m
    # the records' UTC epochs taken for GPS time: 18 s of orbit, 70 km along the track
    utc = [dataclasses.replace(e, t_oe_gps=e.t_oe_gps - 18.0) if e.sat[0] == "R" else e
           for sat in store.sats for e in store.all(sat)]
    assert min(_code_spread_m(EphemerisStore(utc), base, b_ant)["R"]) > 100.0


def test_double_differenced_carrier_is_steady_at_the_reference_positions():
    """Per (signal, satellite) the DD carrier minus the DD modelled range over 120 s (an ambiguity
    is a constant, so its std is the phase noise and what the model misses)."""
    rover, base, store, r_ant, b_ant = _static_epochs("R")
    base_by_t = {round(e.t_gps): e for e in base}
    sig = {"R": RTK_SIGNALS_BY_SYSTEM["R"]}
    series: dict = {}
    for ep in rover:
        sr = receiver_sats(rtk_epoch(ep), store, r_ant, sig)
        sb = receiver_sats(rtk_epoch(base_by_t[round(ep.t_gps)]), store, b_ant, sig)
        for code in ("L1C", "L2C"):
            sats = sorted(s for s in sr if s in sb and code in sr[s].phase_cyc and code in sb[s].phase_cyc
                          and elevation_rad(b_ant, sb[s].r_sat_e) > 0.17)
            ref = "R17"                            # the highest all along
            assert ref in sats

            def sd(s):
                return (sr[s].wavelength_m[code] * (sr[s].phase_cyc[code] - sb[s].phase_cyc[code])
                        - (model_range_m(r_ant, sr[s])[0] - model_range_m(b_ant, sb[s])[0]))
            for s in sats:
                if s != ref:
                    series.setdefault((code, s), []).append(sd(s) - sd(ref))
    assert len(series) >= 10 and all(len(v) == 120 for v in series.values())
    std = {k: float(np.std(v)) for k, v in series.items()}
    print({k: round(v * 1000, 1) for k, v in std.items()})
    assert max(std.values()) < 0.005                    # measured 1.4-2.7 mm (GPS L1 C/A: 1.0-2.8 mm)


def _code_minus_carrier_slopes(channel_offset: int) -> list[float]:
    """Per satellite, the slope of one receiver's carrier (m, on the channel's wavelength) minus its
    pseudorange against the carrier's range change over 120 s: twice the ionosphere's change over
    the range's (1e-6), or, on a wrong wavelength, its relative error (3.5e-4 a channel on L1)."""
    _, base, store, _, _ = _static_epochs("R")
    series: dict = {}
    for ep in base:
        for o in rtk_epoch(ep).observations:
            eph = store.select(o.sat, ep.t_gps)
            if eph is not None and o.signal == "L1C" and np.isfinite(o.carrier_cycles) and np.isfinite(o.pseudorange_m):
                lam = glonass.wavelength_m("L1C", eph.frequency_channel + channel_offset)
                series.setdefault(o.sat, []).append((lam * o.carrier_cycles, o.pseudorange_m))
    slopes = []
    for v in series.values():
        carrier, code = np.array(v).T
        if len(v) == 120 and np.ptp(carrier) > 10e3:          # the range changed by 10 km at least
            slopes.append(float(np.polyfit(carrier - carrier[0], carrier - code, 1)[0]))
    assert len(slopes) >= 5
    return slopes


def test_each_satellites_carrier_is_on_its_channels_wavelength():
    assert max(abs(b) for b in _code_minus_carrier_slopes(0)) < 5e-5     # measured 0.1-2.2e-5
    assert min(abs(b) for b in _code_minus_carrier_slopes(1)) > 3e-4     # the next channel: 3.5-3.7e-4


def test_rtk_with_glonass_float_fixes_every_epoch_and_glonass_helps_the_float():
    sols, info = solve_rtk_rinex(STATIC / "rover.crx.gz", STATIC / "base.crx.gz", [STATIC / "base.nav.gz"],
                                 base_xyz=BASE_XYZ, config=RtkConfig(systems="GECJR", glonass_ar="off"))
    assert len(sols) == 120 and all(s.quality == 1 for s in sols)
    assert all(s.n_sats_by_system.get("R", 0) >= 5 for s in sols)
    # GLONASS ambiguities are never among the integers: the fixed count is the other systems'
    d = np.array([s.r_e for s in sols]) - REF_ROVER
    assert float(np.sqrt(np.mean(np.sum(d ** 2, axis=1)))) < 0.004          # measured 0.0018 m
    # float only (no integers): GPS + GLONASS against GPS alone
    never = dict(ratio_threshold=float("inf"))
    err = {}
    for systems in ("G", "GR"):
        fl, _ = solve_rtk_rinex(STATIC / "rover.crx.gz", STATIC / "base.crx.gz", [STATIC / "base.nav.gz"],
                                base_xyz=BASE_XYZ, config=RtkConfig(systems=systems, glonass_ar="off", **never))
        assert len(fl) == 120 and not any(s.quality == 1 for s in fl)
        err[systems] = float(np.mean([np.linalg.norm(s.r_e - REF_ROVER) for s in fl]))
    print(err)
    assert err["GR"] < err["G"]                          # measured 0.30 against 0.35 m


def test_cli_uses_glonass_when_asked_and_where_its_integers_can_be_fixed(tmp_path, capsys):
    from companion.cli import main
    out, pos = tmp_path / "rtk.json", tmp_path / "rtk.pos"
    xyz = "--base-xyz=" + ",".join(map(str, BASE_XYZ))
    files = ["--rover", str(STATIC / "rover.crx.gz"), "--base", str(STATIC / "base.crx.gz"),
             "--nav", str(STATIC / "base.nav.gz")]
    assert main(["gnss", *files, "--mode", "rtk", xyz, "--sys", "G,R", "--json", str(out), "--pos", str(pos)]) == 0
    printed = capsys.readouterr().out
    assert " R " in printed and "120/120 epochs solved, 120 fixed" in printed
    summary = json.loads(out.read_text())
    assert summary["systems"] == "GR" and set(summary["satellites_by_system"]) == {"G", "R"}
    assert "% navi sys  : G,R" in pos.read_text()
    # by default (--sys auto) GLONASS joins when its integers can be fixed: one receiver model at
    # both ends here, two makes on the car (Leica base, Septentrio rover)
    assert main(["gnss", *files, "--mode", "rtk", xyz, "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert set(summary["satellites_by_system"]) == set("GRECJ") and summary["glonass_ar"].startswith("on")
    car = ["--rover", str(CAR / "rover.crx.gz"), "--base", str(CAR / "base.crx.gz"), "--nav", str(CAR / "nav.rnx.gz")]
    assert main(["gnss", *car, "--mode", "rtk", "--base-xyz=4777633.8947,203108.9850,4206595.1487",
                 "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert set(summary["satellites_by_system"]) == set("GEC") and not summary["glonass_ar"]
    # SPP / DGPS take GLONASS when asked (tests/test_glonass_fused.py), never by default
    assert main(["gnss", *files, "--json", str(out)]) == 0
    assert "R" not in json.loads(out.read_text())["satellites_by_system"]


@pytest.mark.skipif(shutil.which("convbin") is None, reason="RTKLIB convbin not installed (apt install rtklib)")
def test_rtcm_base_brings_glonass_ephemerides_and_channels(tmp_path, capsys):
    """A zero baseline: the real Hiroshima base capture (MSM7 of six systems, 1019 and 1020, starting
    mid-frame) as the base, and RTKLIB convbin's RINEX of the same bytes as the rover.  GLONASS's
    orbits come from the capture's 1020 issues, its wavelengths from the MSM's channels."""
    import subprocess
    from companion.cli import main
    from companion.io.rtcm import decode_rtcm_file
    capture = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"
    obs = tmp_path / "h.obs"
    subprocess.run(["convbin", "-r", "rtcm3", "-tr", "2022/12/13", "01:09:00", "-v", "3.04", "-od", "-os",
                    "-o", str(obs), "-n", str(tmp_path / "h.nav"), str(capture)], check=True, capture_output=True,
                   timeout=120)
    _, dec = decode_rtcm_file(str(capture), week_hint=2240)
    assert len(dec.glonass_history) >= 8
    arp = "-3551876.8287,3887786.8598,3586946.3873"                  # the capture's 1005
    out = tmp_path / "zb.json"
    assert main(["gnss", "--rover", str(obs), "--base", str(capture), "--mode", "rtk", "--sys", "R,E",
                 "--truth-xyz=" + arp, "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert summary["satellites_by_system"]["R"]["min"] >= 6
    assert summary["fixed"] == summary["solved"] == 60 and summary["max_3d_m"] < 0.001     # measured 0.1 mm
    # the capture's 1033 names the base's receiver as convbin's header names the rover's: one model,
    # so 'auto' fixes GLONASS's integers (before the 1033 was read: float, the base 'unknown')
    assert summary["base_descriptor"]["receiver"] == "NOV OEM729"
    assert summary["glonass_ar"] == "on (both receivers NOV OEM729)"


def test_glonass_integers_between_receivers_of_one_model():
    """'auto' fixes GLONASS's integers when both headers name the same receiver model (two
    Septentrio mosaic-X5: inter-channel biases equal, they cancel), and keeps them float between a
    Leica base and a Septentrio rover, where fixing them gives wrong fixes."""
    args = (STATIC / "rover.crx.gz", STATIC / "base.crx.gz", [STATIC / "base.nav.gz"])
    on, info = solve_rtk_rinex(*args, base_xyz=BASE_XYZ, config=RtkConfig(systems="GR"))
    off, _ = solve_rtk_rinex(*args, base_xyz=BASE_XYZ, config=RtkConfig(systems="GR", glonass_ar="off"))
    assert info["glonass_ar"] == "on (both receivers SEPT MOSAIC-X5)"
    assert all(s.quality == 1 for s in on + off) and len(on) == len(off) == 120

    def rms(sols):
        return float(np.sqrt(np.mean([np.sum((s.r_e - REF_ROVER) ** 2) for s in sols])))
    # 12 more DD integers an epoch (GLONASS L1 and L2 against each reference), and closer
    assert np.mean([s.n_fixed for s in on]) >= np.mean([s.n_fixed for s in off]) + 10     # measured 37 against 25
    assert rms(on) < rms(off)                                                               # 0.0059 against 0.0073 m
    # the car: two makes, 'auto' keeps GLONASS float and says why
    cargs = (CAR / "rover.crx.gz", CAR / "base.crx.gz", [CAR / "nav.rnx.gz"])
    car_xyz = (4777633.8947, 203108.9850, 4206595.1487)
    _, info = solve_rtk_rinex(*cargs, base_xyz=car_xyz, config=RtkConfig(systems="GR"))
    assert info["glonass_ar"].startswith("off (receivers SEPT MOSAIC-X5 / LEICA GR50")
    # forced on there, its fixes contradict GPS alone's at the same epochs by decimetres (measured
    # 3 of 9, 0.45-0.61 m; the other 6 within 5.4 cm)
    forced, _ = solve_rtk_rinex(*cargs, base_xyz=car_xyz, config=RtkConfig(systems="GR", glonass_ar="on"))
    gps, _ = solve_rtk_rinex(*cargs, base_xyz=car_xyz, config=RtkConfig(systems="G"))
    gps_fix = {round(s.t_gps): s.r_e for s in gps if s.quality == 1}
    apart = [float(np.linalg.norm(s.r_e - gps_fix[round(s.t_gps)])) for s in forced
             if s.quality == 1 and round(s.t_gps) in gps_fix]
    assert sum(d > 0.3 for d in apart) >= 3, apart
