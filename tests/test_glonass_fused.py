"""GLONASS beside the CDMA systems where it was left out: SPP and DGPS (``companion gnss --sys``
with R) and the tightly coupled engine (``[filter] systems`` with R: pseudoranges with their own
inter-system bias, float DD ambiguities in its RTK), on the real Septentrio mosaic-X5 pair of
tests/data/matrtklib-septentrio-static-2024 (1 m apart, 120 s at 1 Hz, 7 GLONASS satellites).

The reference is the pair's fixed multi-GNSS RTK position (tests/test_rtk_septentrio_static.py).
RINEX gives GLONASS observations no wavelength; they come from the navigation file's channels
(companion.gnss.glonass.with_fdma_wavelengths)."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from companion.gnss.glonass import frequency_channels, with_fdma_wavelengths
from companion.gnss.rinex import read_rinex_nav
from companion.gnss.rinex_obs import read_rinex_obs
from companion.rtk_signals import rtk_epoch
from tests._data import data_path
from tests._engine_at_rest import engine_at_rest

pytestmark = pytest.mark.real_data

D = data_path("matrtklib-septentrio-static-2024")
ROVER, BASE, NAV = D / "rover.crx.gz", D / "base.crx.gz", D / "base.nav.gz"
BASE_XYZ = (-3817681.121326613, 3562839.431140291, 3650159.1593410783)
REF_ROVER = np.array([-3817681.380653759, 3562839.978457426, 3650158.375961049])


def _gnss(tmp_path, mode: str, systems: str) -> dict:
    from companion.cli import main
    out = tmp_path / f"{mode}-{systems.replace(',', '')}.json"
    args = ["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--mode", mode, "--sys", systems,
            "--truth-xyz=" + ",".join(map(str, REF_ROVER)), "--json", str(out)]
    if mode != "spp":
        args += ["--base", str(BASE), "--base-xyz=" + ",".join(map(str, BASE_XYZ))]
    assert main(args) == 0
    return json.loads(out.read_text())


def test_spp_and_dgps_position_with_glonass_alone_and_beside_the_others(tmp_path):
    """Measured: GLONASS alone 3.55 m (SPP, L1, Klobuchar; GPS alone 4.11 m) and 0.72 m (DGPS);
    all five systems' DGPS 0.327 m against 0.349 m without GLONASS.  An orbit integrated from the
    wrong t_b (UTC read as GPS time: 18 s, ~70 km along track) or a wrong channel would put
    GLONASS alone tens of metres off."""
    spp = _gnss(tmp_path, "spp", "R")
    dgps = _gnss(tmp_path, "dgps", "R")
    without = _gnss(tmp_path, "dgps", "G,E,C,J")
    both = _gnss(tmp_path, "dgps", "G,R,E,C,J")
    print(f"GLONASS alone: SPP {spp['rms_3d_m']:.3f} m, DGPS {dgps['rms_3d_m']:.3f} m; DGPS of G,E,C,J "
          f"{without['rms_3d_m']:.3f} m, with GLONASS {both['rms_3d_m']:.3f} m")
    assert spp["solved"] == dgps["solved"] == both["solved"] == 120
    assert spp["satellites_by_system"]["R"]["min"] >= 6
    assert spp["rms_3d_m"] < 5.0 and dgps["rms_3d_m"] < 1.0
    assert both["satellites_by_system"]["R"]["mean"] >= 6
    assert both["rms_3d_m"] <= without["rms_3d_m"] + 0.02


def _epochs():
    navs = read_rinex_nav(NAV, "GRECJ")
    channels = frequency_channels(navs)
    rover = [rtk_epoch(e) for e in with_fdma_wavelengths(read_rinex_obs(ROVER, "GRECJ")[1], channels)]
    base = [dataclasses.replace(rtk_epoch(e), source="base")
            for e in with_fdma_wavelengths(read_rinex_obs(BASE, "GRECJ")[1], channels)]
    return navs, base, rover


def _rows_of(reps, kind: str, system: str) -> tuple[int, int]:
    """(rows made, rows accepted) of one kind of update for one system's satellites."""
    made = accepted = 0
    for rp in reps:
        for rr in rp.reports:
            if rr.kind == kind:
                mine = np.array([lab.startswith(system) for lab in rr.labels], bool)
                made += int(mine.sum())
                accepted += int(np.count_nonzero(rr.accepted[mine]))
    return made, accepted


def test_engine_fuses_glonass_double_differences_as_floats_beside_fixed_cdma_integers():
    """The engine with every system: GLONASS's DD phase rows pass the gate (each against its
    reference on another FDMA carrier: lambda_i phi_i - lambda_ref phi_ref), its ambiguities stay
    float, the CDMA systems fix from the first epoch.  Measured: 1440 GLONASS phase rows, all
    accepted; 120/120 fixed, 2.7 mm RMS (2.8 mm without GLONASS).  GLONASS alone stays float and
    converges to 0.27 m RMS over the 2 minutes."""
    navs, base, rover = _epochs()
    reps, err = engine_at_rest(navs, BASE_XYZ, base, rover, REF_ROVER, systems="GRECJ")
    states = [rp.fix_state for rp in reps]
    made, accepted = _rows_of(reps, "rtk_phase", "R")
    print(f"engine GRECJ: {states.count('fixed')}/{len(states)} fixed, GLONASS phase rows {accepted}/{made} "
          f"accepted, 3-D RMS {np.sqrt(np.mean(np.square(err[1:]))):.4f} m")
    assert made >= 6 * len(rover) and accepted >= 0.99 * made
    assert states[0] == "fixed" and states.count("fixed") >= len(states) - 1
    assert np.sqrt(np.mean(np.square(err[1:]))) < 0.006
    # the integers fixed are the CDMA systems' DD ambiguities only
    last_cdma = sum(1 for rr in reps[-1].reports if rr.kind == "rtk_phase" for lab in rr.labels if lab[0] != "R")
    assert 0 < reps[-1].n_fixed <= last_cdma

    reps_r, err_r = engine_at_rest(navs, BASE_XYZ, base, rover, REF_ROVER, systems="R")
    made_r, accepted_r = _rows_of(reps_r, "rtk_phase", "R")
    print(f"engine R alone: {[rp.fix_state for rp in reps_r].count('fixed')} fixed, phase rows "
          f"{accepted_r}/{made_r}, last error {err_r[-1]:.3f} m")
    assert {rp.fix_state for rp in reps_r} == {"float"}
    assert accepted_r >= 0.99 * made_r > 0
    assert err_r[-1] < 0.5 and np.mean(err_r[-20:]) < np.mean(err_r[:20])


def test_the_service_hands_glonass_ephemerides_to_the_engine():
    """Real bytes through the service's pipeline: a ZED-F9P's RXM-SFRBX strings become GLONASS
    ephemerides in the engine's store, each issue once, with their frequency channels."""
    from companion.config import config_from_dict
    from companion.pipeline import NavPipeline
    pipe = NavPipeline(config_from_dict({"filter": {"systems": ["G", "R"]}}))
    data = (data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20230919-114418.ubx").read_bytes()
    for i in range(0, len(data), 1024):
        pipe.feed("ubx", 1_000_000 * i, data[i:i + 1024])
    store = pipe.engine.ephemerides
    glonass = [s for s in store.sats if s[0] == "R"]
    print(f"GLONASS ephemerides of {len(glonass)} satellites")
    assert len(glonass) >= 6
    assert all(len(store.all(s)) == len({e.t_oe_gps for e in store.all(s)}) for s in glonass)
    assert all(-7 <= store.all(s)[0].frequency_channel <= 6 for s in glonass)
    assert not any(k.startswith("pipeline exceptions") for k in pipe.counters)


def test_rtcm_1020_is_emitted_once_per_issue():
    """A real base capture's 1020 messages (repeated every few seconds) leave the decoder as
    GLONASS ephemerides once per (satellite, t_b), as the other systems' ephemerides do."""
    from companion.gnss.glonass import GlonassEphemeris
    from companion.io.rtcm import decode_rtcm_file
    msgs, dec = decode_rtcm_file(str(data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"),
                                 week_hint=2240)
    emitted = [(m.sat, m.t_oe_gps) for m in msgs if isinstance(m, GlonassEphemeris)]
    assert emitted and len(emitted) == len(set(emitted)) == len(dec.glonass_history)


def test_engine_takes_glonass_from_a_real_rtcm_base_stream():
    """The live path's inputs: the real Hiroshima base stream (MSM7 of six systems, 1005, 1019 /
    1020 ...) decoded as the service decodes it, its GLONASS wavelengths from the MSM7 channels and
    its orbits from the 1020 issues, as the base and, relabelled, as the rover (a zero baseline):
    the engine forms GLONASS DD phase rows beside the others and stays at the station."""
    from companion.io.rtcm import decode_rtcm_file
    from companion.messages import BaseStationPosition, GnssEpoch, GpsEphemeris
    from companion.gnss.glonass import GlonassEphemeris
    msgs, _ = decode_rtcm_file(str(data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"),
                               week_hint=2240)
    ephs = [m for m in msgs if isinstance(m, (GpsEphemeris, GlonassEphemeris))]
    station = next(m for m in msgs if isinstance(m, BaseStationPosition)).r_e
    base = [dataclasses.replace(rtk_epoch(m), source="base") for m in msgs if isinstance(m, GnssEpoch)]
    base = [b for b in base if any(o.sat[0] == "R" for o in b.observations)]
    rover = [dataclasses.replace(b, source="rover") for b in base]
    reps, err = engine_at_rest(ephs, station, base, rover, station, systems="GRECJ")
    made, accepted = _rows_of(reps, "rtk_phase", "R")
    print(f"RTCM base, zero baseline: {len(rover)} epochs, GLONASS phase rows {accepted}/{made}, "
          f"fixed {[rp.fix_state for rp in reps].count('fixed')}, last error {err[-1]:.4f} m")
    assert len(rover) >= 30 and made >= 4 * len(rover) and accepted == made
    assert err[-1] < 0.01


def test_engine_fixes_glonass_integers_when_told_the_receivers_are_one_model():
    """``[filter] rtk_glonass_integers = true`` (two receivers of one model, as the two mosaic-X5
    here): GLONASS's DD ambiguities join the integer search (each row lambda_i (N_i - N_j) +
    (lambda_i - lambda_j) N_j).  Measured: 120/120 fixed, 3.1 mm RMS (2.7 mm float); at the end 98 DD
    ambiguities fixed against 86 with GLONASS float (12 of them GLONASS's).  GLONASS alone fixes
    from the third epoch and ends 3.1 mm off."""
    from companion.config import config_from_dict
    assert config_from_dict({"filter": {"rtk_glonass_integers": True}}).engine_config().rtk_config() \
        .float_only_systems == ""
    navs, base, rover = _epochs()
    reps, err = engine_at_rest(navs, BASE_XYZ, base, rover, REF_ROVER, systems="GRECJ", glonass_integers=True)
    states = [rp.fix_state for rp in reps]
    last_cdma = sum(1 for rr in reps[-1].reports if rr.kind == "rtk_phase" for lab in rr.labels if lab[0] != "R")
    print(f"engine GRECJ, GLONASS integers: {states.count('fixed')}/{len(states)} fixed, n_fixed {reps[-1].n_fixed} "
          f"(CDMA rows {last_cdma}), 3-D RMS {np.sqrt(np.mean(np.square(err[1:]))):.4f} m")
    assert states[0] == "fixed" and states.count("fixed") >= len(states) - 1
    assert reps[-1].n_fixed > last_cdma
    assert np.sqrt(np.mean(np.square(err[1:]))) < 0.006

    # GLONASS alone: fixed from the third epoch (float alone: 0.31 m after 2 minutes)
    reps_r, err_r = engine_at_rest(navs, BASE_XYZ, base, rover, REF_ROVER, systems="R", glonass_integers=True)
    states_r = [rp.fix_state for rp in reps_r]
    print(f"GLONASS alone, integers: first fix at epoch {states_r.index('fixed')}, {states_r.count('fixed')} fixed, "
          f"last error {err_r[-1]:.4f} m")
    assert states_r.index("fixed") <= 5 and states_r.count("fixed") >= len(states_r) - 5
    assert err_r[-1] < 0.01

