"""Multi-GNSS SPP (GPS, Galileo, BeiDou, QZSS) on real receivers, against truth and RTKLIB.

* NovAtel OEM729 base, Hiroshima, 2022-12-13 01:09, 60 s of RTCM3 MSM7 + ephemerides, converted by
  RTKLIB's convbin to RINEX 3.04; truth = its RTCM 1005 antenna reference point.
* u-blox ZED-F9P, Hiroshima, 2023-09-19 11:44, 35 s of RXM-RAWX + RXM-SFRBX, convbin to RINEX 3.04;
  no truth: compared with rnx2rtkp on the same files and with the iono-free position both tools
  agree on.

RTKLIB reference: ``rnx2rtkp`` 2.4.3 single point, broadcast ephemerides, broadcast Klobuchar
(RTKLIB's default coefficients where the file has none), Saastamoinen, 10 deg mask, the same
systems.  RTKLIB 2.4.3 b34 drops every Galileo satellite of the OEM729 file: its ``uniqeph`` keeps
one record per (satellite, IODnav) and here the F/NAV record sorts first, while its ``seleph`` only
accepts I/NAV; so rnx2rtkp gets the same navigation file without the F/NAV twins (our reader does
the same selection itself: the test checks that both files give it the same ephemerides).

Run:  python -m pytest -q -s tests/test_spp_multignss.py   (prints the table)
"""
from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from companion.gnss.atmosphere import KLOBUCHAR_DEFAULT
from companion.gnss.ephemeris import is_beidou_geo, satellite_state
from companion.gnss.ephemeris_store import EphemerisStore
from companion.gnss.postprocess import ProcessOptions, process, statistics
from companion.gnss.prepare import prepare_epoch
from companion.gnss.rinex import read_rinex_nav, read_rinex_nav_header_iono
from companion.gnss.rinex_obs import read_rinex_obs
from companion.messages import BaseStationPosition
from companion.nav.earth import ecef_to_geodetic, ecef_to_ned
from tests._data import data_path

pytestmark = [pytest.mark.real_data,
              pytest.mark.skipif(shutil.which("convbin") is None or shutil.which("rnx2rtkp") is None,
                                 reason="RTKLIB's convbin/rnx2rtkp not installed (apt install rtklib)")]
DATA = data_path("qzsl6tool-hiroshima-rtcm3-ubx")
ARP = np.array([-3551876.8287, 3887786.8598, 3586946.3873])     # OEM729's RTCM 1005
REPO = Path(__file__).resolve().parents[1]
#: rnx2rtkp's pos1-navsys bits
NAVSYS = {"G": 1, "E": 8, "J": 16, "C": 32}
#: our multi-GNSS SPP may be worse than RTKLIB's by at most this fraction: both use the same broadcast
#: models on the same observations; they differ in weights and RAIM, which move a 60-s RMS by a few
#: cm on an error dominated by the ionospheric model both share (ours 0.6 % better when measured)
MARGIN = 0.05


def _inav_only(src: Path, dst: Path) -> None:
    """Copy of a RINEX 3 navigation file without Galileo F/NAV-only records (see module docstring)."""
    lines = src.read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    out = lines[:i]
    while i < len(lines):
        n = 4 if lines[i][:1] in ("R", "S") else 8
        rec, i = lines[i:i + n], i + n
        if rec[0][:1] == "E":
            src_bits = int(float(rec[5][23:42].replace("D", "E")))
            if src_bits & 0x102 and not src_bits & 0x205:
                continue
        out.extend(rec)
    dst.write_text("\n".join(out) + "\n")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("mgnss")
    subprocess.run(["convbin", "-r", "rtcm3", "-tr", "2022/12/13", "01:09:00", "-od", "-os", "-o", str(d / "base.obs"),
                    "-n", str(d / "base.nav"), str(DATA / "20221213-010900.rtcm")], check=True, capture_output=True)
    subprocess.run(["convbin", "-r", "ubx", "-od", "-os", "-oi", "-o", str(d / "f9p.obs"), "-n", str(d / "f9p.nav"),
                    str(DATA / "20230919-114418.ubx")], check=True, capture_output=True)
    _inav_only(d / "base.nav", d / "base_inav.nav")
    return d


def _rtklib(files: Path, obs: str, nav: str, systems: str, iono: str = "brdc") -> np.ndarray:
    """rnx2rtkp single-point solutions (GPS time of week, x, y, z) rows."""
    tag = f"{obs}_{systems}_{iono}"
    conf = files / f"{tag}.conf"
    conf.write_text("\n".join([
        "pos1-posmode=single", "pos1-elmask=10", f"pos1-ionoopt={iono}", "pos1-tropopt=saas",
        "pos1-sateph=brdc", f"pos1-navsys={sum(NAVSYS[c] for c in systems)}",
        "pos1-frequency=" + ("l1+l2" if iono == "dual-freq" else "l1"),
        "out-solformat=xyz", "out-timeform=tow", ""]))
    out = files / f"{tag}.pos"
    subprocess.run(["rnx2rtkp", "-k", str(conf), "-o", str(out), str(files / obs), str(files / nav)],
                   check=True, capture_output=True)
    rows = [ln.split() for ln in out.read_text().splitlines() if ln and not ln.startswith("%")]
    return np.array([[float(r[1]), float(r[2]), float(r[3]), float(r[4]), float(r[6])] for r in rows])


def _stats(err_ned: np.ndarray) -> dict:
    e3 = np.linalg.norm(err_ned, axis=1)
    return {"n": len(err_ned), "rms_3d_m": float(np.sqrt(np.mean(e3 ** 2))),
            "rms_h_m": float(np.sqrt(np.mean(np.sum(err_ned[:, :2] ** 2, axis=1)))),
            "rms_v_m": float(np.sqrt(np.mean(err_ned[:, 2] ** 2)))}


def _cli(files: Path, obs: str, nav: str, *extra: str) -> dict:
    out = files / f"cli_{obs}_{'_'.join(extra)}.json"
    r = subprocess.run([sys.executable, "-m", "companion", "gnss", "--rover", str(files / obs), "--nav", str(files / nav),
                        "--json", str(out), *extra], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    assert "satellites used per epoch" in r.stdout
    return json.loads(out.read_text())


# ------------------------------------------------------------------------------ navigation
def test_rinex3_nav_of_four_systems(files):
    ephs = read_rinex_nav(files / "base.nav")
    by = {c: [e for e in ephs if e.sat[0] == c] for c in "GECJ"}
    assert {c: len(v) for c, v in by.items()} == {"G": 11, "E": 9, "C": 21, "J": 3}
    # Galileo: one I/NAV record per satellite (its F/NAV twin dropped), the same set as the I/NAV-only file
    assert sorted(e.sat for e in by["E"]) == sorted({e.sat for e in by["E"]})
    assert [(e.sat, e.af0_s, e.tgd_s) for e in by["E"]] == \
        [(e.sat, e.af0_s, e.tgd_s) for e in read_rinex_nav(files / "base_inav.nav") if e.sat[0] == "E"]
    e15 = next(e for e in by["E"] if e.sat == "E15")
    assert e15.tgd_s == pytest.approx(6.05359673500e-09) and e15.ura_m == pytest.approx(3.12) and e15.iode == 33
    # BeiDou: BDT week 884 -> GPS week 2240, toe in BDT seconds, TGD1/TGD2, AODE
    c01 = next(e for e in by["C"] if e.sat == "C01")
    assert c01.week == 884 + 1356 and c01.toe_s == 176400.0 and c01.iode == 1
    assert (c01.tgd_s, c01.tgd2_s) == (pytest.approx(-4.7e-9), pytest.approx(-1.0e-8))
    assert c01.t_oe_gps == 2240 * 604800.0 + 176400.0 + 14.0
    # validity windows: RTKLIB's MAXDTOE (GPS/QZSS 2 h, Galileo 4 h, BeiDou 6 h either side of toe)
    assert {c: {e.fit_interval_h for e in v} for c, v in by.items()} == {"G": {4.0}, "E": {8.0}, "C": {12.0}, "J": {4.0}}
    assert read_rinex_nav(files / "base.nav", systems="G") == by["G"]
    # F9P: GPS has not sent its Klobuchar page in 35 s, QZSS has: QZSA/QZSB are used
    alpha, beta = read_rinex_nav_header_iono(files / "f9p.nav")
    assert alpha[0] == pytest.approx(0.3353e-07) and beta[3] == pytest.approx(0.8520e06)
    assert read_rinex_nav_header_iono(files / "base.nav") is None        # RTCM carries none


def test_satellite_states_are_consistent_and_beidou_geos_sit_at_their_slots(files):
    ephs = read_rinex_nav(files / "base.nav")
    t = 2240 * 604800.0 + 176990.0                     # mid-file
    # orbital slots (deg E) of the BeiDou GEOs tracked: BDS-2 G4 160, G5 58.75, G7 110.5 (C04, C05, C03);
    # BDS-3 G1 140, G2 80 (C59, C60).  A wrong GEO rotation puts them thousands of km off.
    slots = {"C03": 110.5, "C04": 160.0, "C05": 58.75, "C59": 140.0, "C60": 80.0}
    seen = set()
    for e in ephs:
        r, v, b, d = satellite_state(e, t)
        rp, _, bp, _ = satellite_state(e, t + 1.0)
        rm, _, bm, _ = satellite_state(e, t - 1.0)
        assert np.linalg.norm((rp - rm) / 2.0 - v) < 1e-4, e.sat       # central difference: ~1e-5 m/s
        assert abs((bp - bm) / 2.0 - d) < 1e-15, e.sat
        if is_beidou_geo(e.sat):
            lat, lon, h = ecef_to_geodetic(r)
            lat1, lon1, _ = ecef_to_geodetic(satellite_state(e, t + 3600.0)[0])
            assert abs(h - 35786e3) < 100e3 and abs(math.degrees(lat)) < 3.0, e.sat
            assert np.linalg.norm(v) < 200.0 and abs(math.degrees(lon1 - lon)) < 0.1, e.sat
            if e.sat in slots:
                assert abs(math.degrees(lon) - slots[e.sat]) < 1.0, (e.sat, math.degrees(lon))
                seen.add(e.sat)
    assert seen == set(slots)


def test_iono_free_residuals_at_the_arp(files):
    """At the true position the iono-free pseudoranges of every system, GEOs included, agree with the
    geometry up to one clock per system: orbits, clocks, BDT, TGD1 (B1I/B3I) all right."""
    store = EphemerisStore(read_rinex_nav(files / "base.nav"))
    _, epochs = read_rinex_obs(files / "base.obs", "GECJ")
    spread = {c: [] for c in "GECJ"}
    for ep in epochs[5::5]:
        p = prepare_epoch(ep, store, ARP, signal="IF", systems="GECJ")
        res = p.pseudorange_m - np.linalg.norm(p.r_sat_e - ARP, axis=1)
        for c in spread:
            r = res[[i for i, s in enumerate(p.sats) if s[0] == c]]
            spread[c].append(np.max(np.abs(r - np.median(r))))
    worst = {c: float(max(v)) for c, v in spread.items()}
    print("\niono-free residual at the ARP, worst |res - system median| [m]:",
          {c: round(v, 2) for c, v in worst.items()})
    assert all(v < 6.0 for v in worst.values()), worst


# ------------------------------------------------------------------------------ SPP vs truth and RTKLIB
def test_multignss_spp_on_the_oem729_base_against_its_arp_and_rtklib(files):
    store = EphemerisStore(read_rinex_nav(files / "base.nav"))
    _, epochs = read_rinex_obs(files / "base.obs", "GECJ")
    table = {}
    for systems in ("G", "GECJ"):
        for signal, iono in (("L1C", "brdc"), ("IF", "dual-freq")):
            sols = process(epochs, store, ProcessOptions(systems=systems, signal=signal), klobuchar=KLOBUCHAR_DEFAULT)
            solved = [s for s in sols if s is not None]
            ours = _stats(np.array([ecef_to_ned(s.r_e, ARP) for s in solved]))
            ours["by_system"] = {c: float(np.mean([s.n_sats_by_system.get(c, 0) for s in solved])) for c in systems}
            ours["isb_m"] = solved[-1].isb_m
            rt = _rtklib(files, "base.obs", "base_inav.nav", systems, iono)
            ref = _stats(np.array([ecef_to_ned(x[1:4], ARP) for x in rt]))
            ref["ns"] = float(np.mean(rt[:, 4]))
            table[(systems, signal)] = (ours, ref, solved)
    print("\nOEM729 base, 60 s, vs its RTCM 1005 ARP  [m]        ours: 3-D    H     V   | RTKLIB: 3-D    H     V")
    for (systems, signal), (o, r, _) in table.items():
        print(f"  {systems:5s} {signal:4s} sats/epoch {sum(o['by_system'].values()):4.1f} (RTKLIB {r['ns']:4.1f})"
              f"          {o['rms_3d_m']:6.3f} {o['rms_h_m']:5.3f} {o['rms_v_m']:5.3f} |"
              f"        {r['rms_3d_m']:6.3f} {r['rms_h_m']:5.3f} {r['rms_v_m']:5.3f}   by system {o['by_system']}"
              f" ISB {({k: round(v, 2) for k, v in o['isb_m'].items()})}")
    multi, ref_multi, solved = table[("GECJ", "L1C")]
    # every epoch with a full GPS set uses all four constellations (the first one has no GPS yet)
    assert sum(1 for s in solved if len(s.n_sats_by_system) >= 3) >= len(solved) - 1 and multi["n"] == 60
    assert set(multi["isb_m"]) == {"E", "C"}              # QZSS shares the GPS clock
    assert multi["rms_3d_m"] <= (1.0 + MARGIN) * ref_multi["rms_3d_m"]
    assert multi["rms_3d_m"] < table[("G", "L1C")][0]["rms_3d_m"]
    assert table[("GECJ", "IF")][0]["rms_3d_m"] <= (1.0 + MARGIN) * table[("GECJ", "IF")][1]["rms_3d_m"]
    assert table[("G", "L1C")][0]["rms_3d_m"] <= (1.0 + MARGIN) * table[("G", "L1C")][1]["rms_3d_m"]
    # a static antenna: the one-drift Doppler velocity over four systems
    v = np.array([s.v_e for s in solved if s.v_e is not None])
    assert len(v) >= 59 and float(np.sqrt(np.mean(np.sum(v ** 2, axis=1)))) < 0.1


def test_cli_multignss_summary_and_system_selection(files):
    j = _cli(files, "base.obs", "base.nav", f"--truth-xyz={ARP[0]},{ARP[1]},{ARP[2]}")
    assert j["systems"] == "GECJ" and j["constellations_used"] == 4
    assert set(j["satellites_by_system"]) == set("GECJ") and j["satellites_by_system"]["C"]["min"] >= 15
    assert "default coefficients" in j["ionosphere"]
    s = j["solutions"][-1]
    assert sum(s["n_sats_by_system"].values()) == s["n_sats"] and set(s["isb_m"]) == {"E", "C"}
    g = _cli(files, "base.obs", "base.nav", "--sys", "G", f"--truth-xyz={ARP[0]},{ARP[1]},{ARP[2]}")
    assert g["systems"] == "G" and set(g["satellites_by_system"]) == {"G"} and g["rms_3d_m"] > j["rms_3d_m"]
    f = _cli(files, "base.obs", "base.nav", "--freq", "if", "--sys", "E,C", f"--truth-xyz={ARP[0]},{ARP[1]},{ARP[2]}")
    assert f["signal"] == "IF" and set(f["satellites_by_system"]) == {"E", "C"} and f["rms_3d_m"] < 3.0
    r = subprocess.run([sys.executable, "-m", "companion", "gnss", "--rover", str(files / "base.obs"), "--nav",
                        str(files / "base.nav"), "--sys", "G,R"], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0 and " R " in r.stdout         # GLONASS when asked (tests/test_glonass_fused.py)


def test_f9p_multignss_against_rtklib(files):
    """No truth: our SPP and rnx2rtkp's on the same files, L1 and iono-free."""
    ours = {k: _cli(files, "f9p.obs", "f9p.nav", *extra) for k, extra in (("L1C", ()), ("IF", ("--freq", "if")))}
    assert ours["L1C"]["constellations_used"] >= 3 and ours["L1C"]["solved"] == ours["L1C"]["epochs"] == 36
    ref = {"L1C": _rtklib(files, "f9p.obs", "f9p.nav", "GECJ"), "IF": _rtklib(files, "f9p.obs", "f9p.nav", "GECJ", "dual-freq")}
    center = np.mean([x[1:4] for x in ref["IF"]], axis=0)          # a local frame only
    mean = {}
    print("\nF9P, 35 s, GPS+Galileo+BeiDou+QZSS (no Galileo ephemeris in 35 s)")
    for k in ("L1C", "IF"):
        tow = {round(x[0], 1): x[1:4] for x in ref[k]}
        d = np.array([ecef_to_ned(np.array(s["r_e"]), tow[round(s["t_gps"] % 604800.0, 1)])
                      for s in ours[k]["solutions"] if round(s["t_gps"] % 604800.0, 1) in tow])
        st = _stats(d)
        mean[k] = (np.mean([ecef_to_ned(np.array(s["r_e"]), center) for s in ours[k]["solutions"]], axis=0),
                   np.mean([ecef_to_ned(x[1:4], center) for x in ref[k]], axis=0))
        print(f"  {k:4s} ours - RTKLIB per epoch ({st['n']}): RMS 3-D {st['rms_3d_m']:.3f} H {st['rms_h_m']:.3f}"
              f" V {st['rms_v_m']:.3f} m; mean NED ours {np.round(mean[k][0], 2)} RTKLIB {np.round(mean[k][1], 2)}"
              f"; sats/epoch ours {ours[k]['satellites_by_system']} RTKLIB {np.mean(ref[k][:, 4]):.1f}")
    # the two iono-free solutions (no ionospheric model involved) agree
    assert np.linalg.norm(mean["IF"][0] - mean["IF"][1]) < 1.0
    # on L1 the model differs: ours uses QZSS's broadcast Klobuchar (GPS's was not received), RTKLIB
    # its 2004 default; ours stays within 2.5 m of the iono-free position both tools agree on
    if_pos = 0.5 * (mean["IF"][0] + mean["IF"][1])
    print(f"  L1 mean minus the iono-free position: ours {np.linalg.norm(mean['L1C'][0] - if_pos):.2f} m, "
          f"RTKLIB {np.linalg.norm(mean['L1C'][1] - if_pos):.2f} m")
    assert np.linalg.norm(mean["L1C"][0] - if_pos) < 2.5


def test_multignss_dgps_zero_baseline(files):
    """The base against itself: every error cancels, so the position is the ARP and the residuals
    vanish, provided the base's clock estimates are grouped like the rover's clocks (one per system,
    QZSS with GPS; grouping them otherwise left 6-cm residuals and 8-cm position errors)."""
    store = EphemerisStore(read_rinex_nav(files / "base.nav"))
    _, epochs = read_rinex_obs(files / "base.obs", "GECJ")
    sols = process(epochs, store, ProcessOptions(mode="dgps", systems="GECJ"), base_epochs=epochs,
                   base=BaseStationPosition(1, ARP))
    solved = [s for s in sols if s is not None]
    st = statistics(solved, ARP)
    assert len(solved) == 60 and st["max_3d_m"] < 1e-3
    assert all(set(s.n_sats_by_system) == set("GECJ") for s in solved[1:])
    assert max(float(np.max(np.abs(s.residuals_m))) for s in solved) < 1e-3


def test_f9p_capture_read_directly_matches_its_rinex(files, tmp_path):
    """`companion gnss --rover CAPTURE.ubx` (no --nav: RXM-SFRBX brings the ephemerides) solves
    every epoch with GPS, Galileo, BeiDou and QZSS and reports them per epoch.  Its observations
    are convbin's: with the same navigation file and the systems convbin's RINEX holds (G, C, J:
    convbin 2.4.3 reads no F9P Galileo SFRBX), iono-free, the positions of the two paths agree to
    a few millimetres (RINEX rounds to 1 mm and has no lock times for the carrier smoothing)."""
    from companion.gnss.postprocess import load_ubx_capture

    out = tmp_path / "ubx.json"
    r = subprocess.run([sys.executable, "-m", "companion", "gnss", "--rover", str(DATA / "20230919-114418.ubx"),
                        "--json", str(out)], capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 0, r.stderr
    direct = json.loads(out.read_text())
    print("\n" + r.stdout.strip())
    assert direct["solved"] == direct["epochs"] == 36
    assert direct["constellations_used"] == 4 and direct["satellites_by_system"]["E"]["min"] >= 4
    store = EphemerisStore(read_rinex_nav(files / "f9p.nav", "GCJ"))
    _, ubx_epochs, _ = load_ubx_capture(DATA / "20230919-114418.ubx", "GCJ", EphemerisStore())
    _, rinex_epochs = read_rinex_obs(files / "f9p.obs", "GCJ")
    opts = ProcessOptions(signal="IF", systems="GCJ")
    a, b = process(ubx_epochs, store, opts), process(rinex_epochs, store, opts)
    d = [np.linalg.norm(x.r_e - y.r_e) for x, y in zip(a, b)]
    assert len(d) == 36 and max(d) < 0.005, max(d)
    r = subprocess.run([sys.executable, "-m", "companion", "gnss", "--rover", str(files / "f9p.obs")],
                       capture_output=True, text=True, cwd=REPO)
    assert r.returncode == 2 and "--nav is required" in r.stderr
