"""RTK double differences for GPS, Galileo, BeiDou and QZSS (issue 12): each system differenced
within itself, on its own tracking families and wavelengths.

* Signal families per system (companion.rtk_signals): Galileo E1 'L1C' is not GPS L1 C/A.
* Real carriers: the NovAtel OEM729 base stream (Hiroshima, 2022-12-13, 60 s of RTCM3 MSM7 for
  G/R/E/J/C/I + ephemerides) as base, and as rover the same epochs moved by a synthetic 4.3-m
  baseline (the geometric range change added to code and phase, the phase at each signal's
  *nominal* frequency from companion.gnss.signals, independent of the decoder's wavelengths), a
  random integer per (satellite, signal) on the phase, a common receiver clock on everything and
  independent code (0.3 m) and phase (2 mm) noise.  What this checks on real signals: pairing of
  every system's codes, the decoder's wavelengths (equal to the nominal ones; in the fix only
  through the baseline: a B1I carrier taken at L1's wavelength is 0.9 % x 4.3 m = 4 cm off),
  within-system references and integer fixing; not multipath (the same on both sides) nor the
  atmosphere.
* The engine's RTK on the simulated 'rtk-gec' flight: blocks and references per system.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from companion.gnss import glonass
from companion.gnss.double_difference import model_range_m, receiver_sats
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.rtk import Q_FIX, RtkConfig, RtkFilter
from companion.gnss.signals import frequency_hz
from companion.io.rtcm import decode_rtcm_file
from companion.messages import SPEED_OF_LIGHT_MPS, GnssEpoch, GpsEphemeris
from companion.nav.earth import C_n_e, ecef_to_geodetic
from companion.rtk_signals import RTK_SIGNALS, RTK_SIGNALS_BY_SYSTEM, canonical_signal, rtk_epoch, signals_for_system
from tests._data import data_path

RTCM = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20221213-010900.rtcm"
ARP_E = np.array([-3551876.8287, 3887786.8598, 3586946.3873])     # its RTCM 1005
BASELINE_NED_M = np.array([3.0, -2.5, 1.7])


# ------------------------------------------------------------------ families
def test_families_are_per_system():
    assert canonical_signal("G05", "L1C") == "L1C" and canonical_signal("E11", "L1X") == "L1C"
    assert canonical_signal("G05", "L1X") is None                 # GPS L1C (the new civil) is not L1 C/A
    assert canonical_signal("E11", "L1B") is None                 # E1 B data: half a cycle off E1 C
    assert canonical_signal("J02", "L2S") == "L2X" and canonical_signal("J02", "L2W") is None
    assert canonical_signal("C20", "L2I") == "L2I" and canonical_signal("C20", "L6X") == "L6I"
    assert canonical_signal("E11", "L7X") == "L7Q" and canonical_signal("E11", "L5X") == "L5Q"
    assert canonical_signal("R01", "L1C") == "L1C" and canonical_signal("R01", "L2X") is None
    assert canonical_signal("I02", "L5A") is None
    assert RTK_SIGNALS[:3] == ("L1C", "L2X", "L2W")               # GPS's order kept
    assert signals_for_system("C", ("L1C", "L2W")) == ()          # BeiDou without its B1I: not paired
    assert signals_for_system("C", RTK_SIGNALS)[0] == "L2I"
    assert signals_for_system("G", ("L2W", "L1C")) == ("L1C", "L2W")
    for sys, sigs in RTK_SIGNALS_BY_SYSTEM.items():
        for s in sigs:         # GLONASS: by the channel (-7..6); its CDMA L3 on one carrier
            hz = glonass.carrier_hz(s, -7) if sys == "R" else frequency_hz(sys + "01", s)
            assert math.isfinite(hz), (sys, s)


# ------------------------------------------------------------------ real carriers, synthetic baseline
@pytest.fixture(scope="module")
def stream():
    msgs, _ = decode_rtcm_file(str(RTCM), week_hint=2240)
    ephs = [m for m in msgs if isinstance(m, GpsEphemeris)]
    epochs = [rtk_epoch(m) for m in msgs if isinstance(m, GnssEpoch)]
    return ephs, epochs


def test_decoded_wavelengths_are_each_systems_own(stream):
    _, epochs = stream
    seen = set()
    for ep in epochs:
        for o in ep.observations:
            if o.sat[0] == "R" and o.signal == "L1C":     # FDMA: one of the 14 channels' carriers
                k = (SPEED_OF_LIGHT_MPS / o.wavelength_m - glonass.L1_BASE_HZ) / glonass.L1_STEP_HZ
                assert -7 <= round(k) <= 6 and abs(k - round(k)) < 1e-6, (o.sat, k)
                seen.add(("R", o.signal))
            elif canonical_signal(o.sat, o.signal) is not None and o.sat[0] != "R":
                lam = SPEED_OF_LIGHT_MPS / frequency_hz(o.sat, o.signal)
                assert abs(o.wavelength_m - lam) < 1e-9, (o.sat, o.signal, o.wavelength_m, lam)
                seen.add((o.sat[0], o.signal))
    assert {s for s, _ in seen} == set("GECJR") and ("C", "L2I") in seen and ("E", "L7Q") in seen


def _moved_rover(epochs, store, r_rover_e, seed=0):
    """The base epochs as a rover at ``r_rover_e``: + range change on code and phase, + an integer
    per (sat, signal) on the phase, + a common clock (300 m), + independent noise.  Returns the
    epochs and the integers."""
    rng = np.random.default_rng(seed)
    ints: dict = {}
    out = []
    for ep in epochs:
        prim = {sys: sigs[:1] for sys, sigs in RTK_SIGNALS_BY_SYSTEM.items()}
        sb = receiver_sats(ep, store, ARP_E, prim)
        obs = []
        for o in ep.observations:
            if o.sat not in sb or canonical_signal(o.sat, o.signal) is None:
                continue
            q = sb[o.sat]
            d_rho = model_range_m(r_rover_e, q)[0] - model_range_m(ARP_E, q)[0] + 300.0
            lam = SPEED_OF_LIGHT_MPS / frequency_hz(o.sat, o.signal)
            n = ints.setdefault((o.sat, o.signal), int(rng.integers(-50, 51)))
            obs.append(dataclasses.replace(o, pseudorange_m=o.pseudorange_m + d_rho + rng.normal(0, 0.3),
                                           carrier_cycles=o.carrier_cycles + (d_rho + rng.normal(0, 0.002)) / lam + n))
        out.append(dataclasses.replace(ep, observations=tuple(obs), source="rover"))
    return out, ints


def _solve(stream, systems):
    ephs, base = stream
    store = EphemerisStore(ephs)
    lat, lon, _ = ecef_to_geodetic(ARP_E)
    r_rov = ARP_E + C_n_e(lat, lon) @ BASELINE_NED_M
    rover, ints = _moved_rover(base, store, r_rov)
    filt = RtkFilter(ARP_E, store, RtkConfig(systems=systems, elevation_mask_deg=10.0))
    sols = []
    for r, b in zip(rover, base):
        sol = filt.process(r, b, None if filt.initialized else r_rov + np.array([1.0, -1.0, 2.0]))
        if sol is not None:
            sols.append(sol)
    return filt, sols, ints, r_rov


def test_real_multignss_carriers_fix_at_once_with_every_system(stream):
    filt, sols, ints, r_rov = _solve(stream, "GECJ")
    fixed = [s for s in sols if s.quality == Q_FIX]
    err = np.array([np.linalg.norm(s.r_e - r_rov) for s in fixed])
    by_sys = {}
    for sat, s in filt.amb:
        by_sys.setdefault(sat[0], set()).add(s)
    print(f"G+E+C+J: {len(fixed)}/{len(sols)} fixed, first {sols[0].quality}, DD ambiguities "
          f"{sols[-1].n_ambiguities}, 3-D error max {err.max():.4f} m RMS {np.sqrt(np.mean(err ** 2)):.4f} m, "
          f"signals {by_sys}, counters {filt.counters}")
    assert len(sols) >= 58 and sols[0].quality == Q_FIX and len(fixed) == len(sols)
    assert float(err.max()) < 0.005
    # every system with its own signals: GPS L1 C/A, L2C, L2 P(Y), L5; Galileo E1, E5a, E5b;
    # BeiDou B1I, B3I, B2I; QZSS L1 C/A, L2C, L5
    assert by_sys["G"] == {"L1C", "L2X", "L2W", "L5Q"} and by_sys["E"] == {"L1C", "L5Q", "L7Q"}
    assert by_sys["C"] >= {"L2I", "L6I", "L7I"} and by_sys["J"] == {"L1C", "L2X", "L5Q"}
    # the held DD ambiguities are the injected integers (within each system and signal)
    n_checked = 0
    for sys in "GECJ":
        for s in filt.sig[sys]:
            keys = [k for k in filt.amb if k[0][0] == sys and k[1] == s]
            if len(keys) < 2:
                continue
            ref = keys[0]
            for k in keys[1:]:
                dd = filt.x[filt.amb[k]] - filt.x[filt.amb[ref]]
                assert abs(dd - (ints[k] - ints[ref])) < 0.05, (k, ref, dd)
                n_checked += 1
    assert n_checked >= 60


def test_gps_alone_on_the_same_stream_forms_fewer_double_differences(stream):
    _, sols_g, _, r_rov = _solve(stream, "G")
    _, sols_all, _, _ = _solve(stream, "GECJ")
    n_g = np.mean([s.n_ambiguities for s in sols_g])
    n_all = np.mean([s.n_ambiguities for s in sols_all])
    print(f"DD ambiguities per epoch: GPS {n_g:.1f}, G+E+C+J {n_all:.1f}")
    assert n_all > 2.5 * n_g
    assert all(np.linalg.norm(s.r_e - r_rov) < 0.01 for s in sols_g if s.quality == Q_FIX)


# ------------------------------------------------------------------ the engine on rtk-gec
def test_engine_double_differences_within_each_system_on_rtk_gec():
    from sitl.rtk_score import run_rtk
    r = run_rtk(seed=1, duration_s=25.0, scenario_name="rtk-gec", keep_engine=True)
    eng = r["engine"]
    names = [n for n in eng.block_states if n.startswith("amb ")]
    systems = {n.split()[1][0] for n in names}
    sigs = {(n.split()[1][0], n.split()[2]) for n in names}
    print(f"first fix {r['first_fix_s']:.0f} s, {r['fixed_epochs']}/{r['n_epochs']} fixed, "
          f"RMS_h {r['rms_h_after_first_fix_m']:.4f} m, signals {sorted(sigs)}")
    assert systems == set("GEC")
    assert sigs == {("G", "L1C"), ("G", "L2W"), ("E", "L1C"), ("E", "L7Q"), ("C", "L2I"), ("C", "L6I")}
    # every DD row pairs two satellites of one system, one reference per (system, signal) and epoch
    n_rows = 0
    for rep in eng.epoch_reports:
        refs = {}
        for rr in rep.reports:
            if rr.kind != "rtk_phase":
                continue
            for lab in rr.labels:
                pair, sig, _ = lab.split()
                a, b = pair.split("-")
                assert a[0] == b[0], lab
                assert refs.setdefault((b[0], sig), b) == b, lab
                n_rows += 1
    assert n_rows > 0
    assert r["wrong_fixes"] == 0 and r["first_fix_s"] <= 10.0
    assert r["rms_h_after_first_fix_m"] < 0.03


def test_a_wrong_fix_of_one_system_drops_that_system_only():
    """Two held Galileo E1 ambiguities moved by one cycle (and their slip-test memory with them: a
    wrong set of integers, no phase jump): Galileo's rows fail, Galileo's ambiguities start again,
    GPS's and BeiDou's are kept (and fixed), and nothing fixed is wrong."""
    from sitl.rtk_score import run_rtk
    done, after = [], []

    def knock(eng, t_s):
        rtk = eng.rtk
        if done:
            if not after and rtk.status.t_gps > done[0][1]:      # the next epoch has been processed
                t_knock = done[0][1]
                after.append({sys: {k: a.t_added > t_knock for k, a in rtk.amb.items() if k[0][0] == sys}
                              for sys in "GEC"})
            return
        if t_s < 15.0 or not any(k[0][0] == "E" for k in rtk.held):
            return
        keys = sorted(k for k in rtk.held if k[0][0] == "E" and k[1] == "L1C")[:2]
        for key in keys:
            a = rtk.amb[key]
            eng.block_states[a.name] = eng.block_states[a.name] + 1.0
            t_prev, e = rtk._resid[key]
            rtk._resid[key] = (t_prev, e - a.wavelength_m)
        done.append((t_s, eng.t_gps))

    r = run_rtk(seed=0, duration_s=40.0, scenario_name="rtk-gec", hook=knock)
    c = r["counters"]
    print({k: v for k, v in c.items() if k.startswith("rtk")})
    assert done and after and c.get("rtk wrong fixes dropped: phase residuals", 0) == 1
    new = after[0]
    assert new["E"] and all(new["E"].values())                        # Galileo: every ambiguity anew
    assert not any(new["G"].values()) and not any(new["C"].values())  # GPS, BeiDou: kept
    assert not [e for e in r["epochs"] if e[1] == "fixed" and e[4] > 0.1]
    assert all(e[1] == "fixed" for e in r["epochs"] if e[0] > done[0][0] + 5.0)


def test_engine_rtk_on_real_multignss_carriers(stream):
    """The engine's RTK update (an IMU at rest, synthetic, at the moved rover) on the same real
    base/rover pair: every system's DD rows, a fix within the first epochs, mm position."""
    from tests._engine_at_rest import engine_at_rest
    ephs, base = stream
    store = EphemerisStore(ephs)
    lat, lon, _ = ecef_to_geodetic(ARP_E)
    r_rov = ARP_E + C_n_e(lat, lon) @ BASELINE_NED_M
    rover, _ = _moved_rover(base, store, r_rov)
    reps, err = engine_at_rest(ephs, ARP_E, base[1:], rover[1:], r_rov)
    states = [rp.fix_state for rp in reps]
    first = states.index("fixed")
    rows = [lab for rp in reps for rr in rp.reports if rr.kind == "rtk_phase" for lab in rr.labels]
    sig = {(lab.split()[0][0], lab.split()[1]) for lab in rows}
    print(f"engine on real carriers: first fix at epoch {first}, {states.count('fixed')}/{len(states)} fixed, "
          f"n_fixed {reps[-1].n_fixed}, 3-D error after the first fix max {max(err[first:]):.4f} m, "
          f"RMS {np.sqrt(np.mean(np.square(err[first:]))):.4f} m, signals {sorted(sig)}")
    assert first <= 3 and states[first:].count("fixed") >= len(states[first:]) - 1
    assert {s for s, _ in sig} == set("GECJ") and len(sig) >= 12
    assert reps[-1].n_fixed >= 60
    assert max(err[first + 1:]) < 0.015 and np.sqrt(np.mean(np.square(err[first + 1:]))) < 0.006
