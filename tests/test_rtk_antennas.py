"""Receiver antenna calibrations in the RTK (companion.gnss.antenna_calibration, ``--antennas``): the
NGS and ANTEX readers, the phase-centre geometry, and the same shift as RTKLIB's rnx2rtkp on the
real GEONET pair when the rover is declared another antenna."""
from __future__ import annotations

import json
import math
import shutil
import subprocess

import numpy as np
import pytest

from companion.cli import main
from companion.gnss.antenna_calibration import (FrequencyCalibration, find_antenna, largest_change_m,
                                                read_antenna_file, receiver_antenna)
from companion.gnss.rtk import RtkConfig
from companion.gnss.rtk_post import solve_rtk_rinex
from companion.nav.earth import ecef_to_ned
from tests._data import data_path
from tests._rtklib_pos import rtklib_fixed_xyz

pytestmark = pytest.mark.real_data

D = data_path("rtklib-testdata-geonet-2005/rinex")
ROVER, BASE, NAV = D / "07590920.05o", D / "30400920.05o", D / "07590920.05n"
BASE_HEADER_XYZ = (-3978242.4348, 3382841.1715, 3649902.7667)
REF_0759 = np.array([-3976219.6640, 3382372.5415, 3652513.0546])
NGS = data_path("ngs-antenna-calibrations/ngs_abs_excerpt.pcv")
IGS05 = data_path("rtklib-igs05-antex/igs05_excerpt.atx")
MASK = RtkConfig(elevation_mask_deg=15.0)


def _antex_text(antennas: dict) -> str:
    """An ANTEX 1.4 file of ``antennas``: type -> (dazi, {code: (north/east/up mm, NOAZI mm at
    zenith 0..90 by 5, {azimuth: mm row} or None)})."""
    def line(body: str, label: str) -> str:
        return f"{body:<60}{label}"
    out = [line("     1.4            M", "ANTEX VERSION / SYST"), line("A", "PCV TYPE / REFANT"), line("", "END OF HEADER")]
    for name, (dazi, freqs) in antennas.items():
        out += [line("", "START OF ANTENNA"), line(f"{name:<20}", "TYPE / SERIAL NO"),
                line("FIELD               companion tests          0    05-DEC-26", "METH / BY / # / DATE"),
                line(f"  {dazi:6.1f}", "DAZI"), line(f"  {0.0:6.1f}{90.0:6.1f}{5.0:6.1f}", "ZEN1 / ZEN2 / DZEN"),
                line(f"{len(freqs):6d}", "# OF FREQUENCIES")]
        for code, (neu, noazi, rows) in freqs.items():
            out += [line(f"   {code}", "START OF FREQUENCY"), line("".join(f"{v:10.2f}" for v in neu), "NORTH / EAST / UP"),
                    "   NOAZI" + "".join(f"{v:8.2f}" for v in noazi)]
            out += [f"{az:8.1f}" + "".join(f"{v:8.2f}" for v in vals) for az, vals in (rows or {}).items()]
            out.append(line(f"   {code}", "END OF FREQUENCY"))
        out.append(line("", "END OF ANTENNA"))
    return "\n".join(out) + "\n"


def _as_antex(cals: dict, names) -> dict:
    """NGS calibrations of ``names`` in _antex_text's form (the same numbers)."""
    out = {}
    for name in names:
        cal = find_antenna(cals, name)
        out[cal.entry] = (0.0, {code: ((1e3 * f.pco_enu_m[[1, 0, 2]]).tolist(), (1e3 * f.pcv_noazi_m).tolist(), None)
                                for code, f in cal.frequencies.items()})
    return out


def _fixed(sols) -> dict[int, np.ndarray]:
    return {round(s.t_gps): s.r_e for s in sols if s.quality == 1}


def _mean_shift(a: dict, b: dict) -> np.ndarray:
    """Mean b - a over the epochs both fixed (ECEF m)."""
    common = sorted(set(a) & set(b))
    assert len(common) >= 100
    return np.mean([b[t] - a[t] for t in common], axis=0)


def _rnx2rtkp(tmp_path, tag: str, antfile=None, rover_type: str = "*") -> dict[int, np.ndarray]:
    """RTKLIB 2.4.3's kinematic fix-and-hold of the GEONET pair, 15 deg, with the calibrations of
    ``antfile`` (offsets and variations: pos1-posopt2) for the header's types or ``rover_type``."""
    conf = tmp_path / f"{tag}.conf"
    conf.write_text("\n".join(["pos1-posmode=kinematic", "pos1-frequency=l1+l2", "pos1-elmask=15",
                               "pos2-armode=fix-and-hold", "ant2-postype=xyz", "out-solformat=xyz", "out-timeform=tow",
                               *(f"ant2-pos{i + 1}={v!r}" for i, v in enumerate(BASE_HEADER_XYZ)),
                               *([f"file-rcvantfile={antfile}", "pos1-posopt2=on", f"ant1-anttype={rover_type}",
                                  "ant2-anttype=*"] if antfile else [])]) + "\n")
    out = tmp_path / f"{tag}.pos"
    subprocess.run(["rnx2rtkp", "-k", str(conf), "-o", str(out), str(ROVER), str(BASE), str(NAV)],
                   check=True, capture_output=True, timeout=120)
    return rtklib_fixed_xyz(out)


def test_ngs_reader_and_the_phase_centre_geometry():
    cals = read_antenna_file(NGS)
    assert set(cals) == {("AERAT2775_150", "NONE"), ("TRM29659.00", "NONE"), ("TRM29659.00", "SCIS"),
                         ("TRM29659.00", "SCIT"), ("TRM29659.00", "UNAV")}
    trm = find_antenna(cals, "TRM29659.00")
    l1, l2 = trm.frequencies["G01"], trm.frequencies["G02"]
    # the file's north/east/up in mm, kept east/north/up in m
    np.testing.assert_allclose(l1.pco_enu_m, [0.0, 0.0018, 0.0910])
    np.testing.assert_allclose(l2.pco_enu_m, [0.0, 0.0011, 0.1201])
    # at the zenith the range is shorter by the offset up; at 30 deg elevation by the offset along
    # the line of sight, plus the variation (-5.9 mm in the file's row of 40..0 deg)
    assert l1.range_offset_m(np.array([0.0, 0.0, 1.0])) == pytest.approx(-0.0910)
    u = np.array([0.0, math.cos(math.radians(30.0)), 0.5])
    assert l1.range_offset_m(u) == pytest.approx(-(0.0018 * u[1] + 0.0910 * 0.5) - 0.0059)
    # between the grid's 5-degree steps: linear (elevation 32.5 deg, half-way between -7.1 and -5.9)
    el = math.radians(32.5)
    u = np.array([0.0, math.cos(el), math.sin(el)])
    assert l1.range_offset_m(u) == pytest.approx(-(0.0018 * u[1] + 0.0910 * u[2]) - 0.0065)
    # a frequency the calibration lacks takes GPS's nearest, and says so
    assert trm.range_offset_m("E", "5", np.array([0.0, 0.0, 1.0])) == pytest.approx(-0.1201)
    assert trm.range_offset_m("R", "1", np.array([0.0, 0.0, 1.0])) == pytest.approx(-0.0910)
    assert trm.notes == ["E05 from G02", "R01 from G01"]
    # a substitute is the file's own frequency, never another substitute
    trm.range_offset_m("G", "5", np.array([0.0, 0.0, 1.0]))
    trm.range_offset_m("J", "5", np.array([0.0, 0.0, 1.0]))
    assert trm.notes[2:] == ["G05 from G02", "J05 from G02"]
    # an uncalibrated radome falls back to the bare model, said; an unknown type is None
    assert find_antenna(cals, "TRM29659.00     SCIS").frequencies["G01"].pco_enu_m[2] == pytest.approx(0.0877)
    assert find_antenna(cals, "TRM29659.00 JPLA").notes == ["radome JPLA not calibrated: TRM29659.00 without one used"]
    assert find_antenna(cals, "LEIAR25.R4 NONE") is None
    # the receivers: a type asked for and missing is an error; a header's missing is said
    with pytest.raises(ValueError, match="LEIAR25.R4.*not in"):
        receiver_antenna(cals, "LEIAR25.R4 NONE", "TRM29659.00", "rover", str(NGS))
    cal, info = receiver_antenna(cals, None, "Unknown", "rover", str(NGS))
    assert cal is None and "phase centres taken at the ARP" in info["notes"][0]


def test_antex_reader_gives_the_ngs_numbers_and_interpolates_in_azimuth(tmp_path):
    cals = read_antenna_file(NGS)
    atx = tmp_path / "same.atx"
    grid = {0.0: [1.0] * 19, 90.0: [3.0] * 19, 180.0: [5.0] * 19, 270.0: [7.0] * 19, 360.0: [1.0] * 19}
    freqs = {"G01": ([0.0, 0.0, 100.0], [0.0] * 19, None), "E05": ([10.0, -20.0, 50.0], [2.0] * 19, None)}
    sats = {"BLOCK IIA           G01                 G032      1992-079A": (0.0, freqs)}
    atx.write_text(_antex_text({**_as_antex(cals, ["TRM29659.00", "AERAT2775_150 NONE"]), **sats,
                                "TEST            NONE": (90.0, {"G01": ([0.0, 0.0, 0.0], [2.0] * 19, grid)}),
                                "TEST2           NONE": (0.0, freqs)}))
    atxs = read_antenna_file(atx)
    assert ("BLOCK IIA", "NONE") not in atxs               # a satellite's antenna is not a receiver's
    for name in ("TRM29659.00", "AERAT2775_150 NONE"):
        a, b = find_antenna(cals, name), find_antenna(atxs, name)
        for code in ("G01", "G02"):
            np.testing.assert_allclose(a.frequencies[code].pco_enu_m, b.frequencies[code].pco_enu_m)
            np.testing.assert_allclose(a.frequencies[code].pcv_noazi_m, b.frequencies[code].pcv_noazi_m)
    # the azimuth grid, when given, rather than NOAZI: north 1 mm, east 3, south 5, west 7
    f = find_antenna(atxs, "TEST").frequencies["G01"]
    horizon = [np.array([math.sin(math.radians(a)), math.cos(math.radians(a)), 0.0]) for a in (0, 45, 90, 315)]
    assert [round(1e3 * f.range_offset_m(u), 6) for u in horizon] == [1.0, 2.0, 3.0, 4.0]
    # a system's own frequency is used when the file has it (Galileo E5a here, not GPS L2's)
    t2 = find_antenna(atxs, "TEST2")
    assert t2.range_offset_m("E", "5", np.array([0.0, 0.0, 1.0])) == pytest.approx(-0.050 + 0.002)
    assert isinstance(f, FrequencyCalibration) and t2.notes == []


def test_a_real_antex_file_with_azimuth_grids():
    """IGS05 as RTKLIB ships it: a satellite's antenna skipped, the robot calibrations' azimuth
    grids read and used, the numbers as the file prints them."""
    cals = read_antenna_file(IGS05)
    assert set(cals) == {("JAVRINGANT_DM", "NONE"), ("LEIAR25.R4", "NONE"), ("TRM29659.00", "NONE")}
    l1 = find_antenna(cals, "TRM29659.00").frequencies["G01"]
    np.testing.assert_allclose(l1.pco_enu_m, [-0.00091, -0.00006, 0.09195])
    assert len(l1.zenith_deg) == 19 and l1.pcv_m.shape == (73, 19) and l1.azimuth_deg[-1] == 360.0
    assert l1.pcv_noazi_m[1] == pytest.approx(-0.00024) and l1.pcv_m[2, 7] == pytest.approx(-0.00738)
    # at azimuth 10 deg, zenith 35 deg: the file's row 10.0, eighth value
    u = np.array([math.sin(math.radians(35.0)) * math.sin(math.radians(10.0)),
                  math.sin(math.radians(35.0)) * math.cos(math.radians(10.0)), math.cos(math.radians(35.0))])
    assert l1.range_offset_m(u) == pytest.approx(-(l1.pco_enu_m @ u) - 0.00738)
    # a RINEX header's 20 columns: model 'Tallysman TW7972' (16), radome NONE; not in the file
    cal, info = receiver_antenna(cals, None, "Tallysman TW7972NONE", "rover", str(IGS05))
    assert cal is None and info["notes"] == ["not in the file: phase centres taken at the ARP"]
    jav = find_antenna(cals, "JAVRINGANT_DM   JVDM")
    assert jav.name == "JAVRINGANT_DM   NONE" and jav.notes == ["radome JVDM not calibrated: JAVRINGANT_DM without "
                                                             "one used"]


def test_the_largest_change_between_two_calibrations(tmp_path):
    """What the engine widens its position by when the base's calibration changes: the most the
    modelled range moves over the sky, on the bands of the systems used (GPS L1 and L2 unless told)."""
    atx = tmp_path / "up.atx"
    atx.write_text(_antex_text({"TESTANT_UP100   NONE": (0.0, {c: ([0.0, 0.0, 100.0], [0.0] * 19, None)
                                                                for c in ("G01", "G02")})}))
    up100 = find_antenna(read_antenna_file(atx), "TESTANT_UP100")
    assert largest_change_m(None, up100) == pytest.approx(0.100)      # at the zenith
    assert largest_change_m(up100, up100) == 0.0 and largest_change_m(None, None) == 0.0
    # on the bands the engine uses: GPS L1/L2 alike, Galileo E5a raised by 10 cm (E1 from GPS L1)
    atx = tmp_path / "e5.atx"
    atx.write_text(_antex_text({"TESTANT_E5UP    NONE": (0.0, {"G01": ([0.0] * 3, [0.0] * 19, None),
                                                              "G02": ([0.0] * 3, [0.0] * 19, None),
                                                              "E05": ([0.0, 0.0, 100.0], [0.0] * 19, None)})}))
    e5up = find_antenna(read_antenna_file(atx), "TESTANT_E5UP")
    assert e5up is not None
    assert largest_change_m(None, e5up) == 0.0                              # GPS L1/L2 alone
    assert largest_change_m(None, e5up, {"G": "12", "E": "15"}) == pytest.approx(0.100)
    # the engine asks for the bands its RTK rows use (companion.rtk_signals), per system it fuses
    from companion.config import config_from_dict
    from companion.nav.engine import NavEngine
    eng = NavEngine(config_from_dict({"corrections": {"source": "file", "file": {"path": "base.rtcm"}},
                                      "filter": {"rtk_enabled": True, "systems": ["G", "E"]}}).engine_config())
    assert eng._rtk_bands() == {"G": "125", "E": "157"}
    igs = read_antenna_file(IGS05)
    leica, trimble = find_antenna(igs, "LEIAR25.R4"), find_antenna(igs, "TRM29659.00")
    # the two choke rings' L1/L2 offsets differ by 2-7 cm up, with their variations a few mm more
    assert 0.02 < largest_change_m(trimble, leica) < 0.10
    assert largest_change_m(trimble, leica) == pytest.approx(largest_change_m(leica, trimble))


def test_a_declared_offset_moves_the_solution_by_it(tmp_path):
    """Physics: a rover antenna declared with its phase centres 10 cm above the ARP on every
    frequency puts the ARP, which is what is solved, 10 cm lower; horizontally nothing moves."""
    atx = tmp_path / "up10.atx"
    atx.write_text(_antex_text({"UP10CM          NONE": (0.0, {c: ([0.0, 0.0, 100.0], [0.0] * 19, None)
                                                               for c in ("G01", "G02")})}))
    plain, _ = solve_rtk_rinex(ROVER, BASE, [NAV], config=MASK)
    up10, info = solve_rtk_rinex(ROVER, BASE, [NAV], config=MASK, antennas=str(atx), rover_antenna="UP10CM")
    assert info["antennas"]["base"]["calibration"] is None      # TRM29659.00 is not in this file
    a, b = _fixed(plain), _fixed(up10)
    shift_ned = ecef_to_ned(REF_0759 + _mean_shift(a, b), REF_0759)
    print(f"declared 10 cm up: the solution moved north/east/down {1e3 * shift_ned} mm")
    assert shift_ned[2] == pytest.approx(0.100, abs=0.002)
    assert np.hypot(*shift_ned[:2]) < 0.002


def test_one_antenna_type_at_both_ends_cancels():
    """GEONET's two TRM29659.00 choke rings 3.3 km apart see each satellite at almost the same
    elevation: their calibrations cancel to a fraction of a millimetre."""
    plain, _ = solve_rtk_rinex(ROVER, BASE, [NAV], config=MASK)
    both, info = solve_rtk_rinex(ROVER, BASE, [NAV], config=MASK, antennas=str(NGS))
    assert [info["antennas"][w]["calibration"] for w in ("rover", "base")] == ["ngs_abs_excerpt.pcv: TRM29659.00     NONE"] * 2
    shift = _mean_shift(_fixed(plain), _fixed(both))
    print(f"both ends calibrated: mean shift {1e3 * shift} mm")
    assert np.linalg.norm(shift) < 0.001


@pytest.mark.skipif(shutil.which("rnx2rtkp") is None, reason="RTKLIB's rnx2rtkp not installed (apt install rtklib)")
def test_the_same_shift_as_rtklib_for_another_rover_antenna(tmp_path):
    """The rover declared an AERAT2775_150 (a 64.5-mm L1 offset against the choke ring's 91 mm,
    with its own variations): RTKLIB and ours move the solution alike, with the NGS file and with
    the same numbers as ANTEX (which checks that both read ANTEX alike); and declared a
    LEIAR25.R4 in IGS05's real ANTEX, whose azimuth grids ours uses and RTKLIB 2.4.3 does not
    (measured: 0.5-0.6 mm apart per axis, 0.1-0.3 mm with ours on NOAZI too)."""
    atx = tmp_path / "same.atx"
    atx.write_text(_antex_text(_as_antex(read_antenna_file(NGS), ["TRM29659.00", "AERAT2775_150 NONE"])))
    ours0 = _fixed(solve_rtk_rinex(ROVER, BASE, [NAV], config=MASK)[0])
    theirs0 = _rnx2rtkp(tmp_path, "plain")
    for antfile, rover in ((NGS, "AERAT2775_150"), (atx, "AERAT2775_150"), (IGS05, "LEIAR25.R4 NONE")):
        ours = _fixed(solve_rtk_rinex(ROVER, BASE, [NAV], config=MASK, antennas=str(antfile),
                                      rover_antenna=rover)[0])
        theirs = _rnx2rtkp(tmp_path, antfile.stem, antfile, rover)
        a, b = _mean_shift(ours0, ours), _mean_shift(theirs0, theirs)
        print(f"{antfile.name}, rover {rover}: shift ours {1e3 * a} mm, RTKLIB {1e3 * b} mm")
        assert np.linalg.norm(a) > 0.03
        assert np.all(np.abs(a - b) < 0.001)


def test_cli_says_which_antennas_and_writes_them(tmp_path, capsys):
    pos, js = tmp_path / "a.pos", tmp_path / "a.json"
    args = ["gnss", "--mode", "rtk", "--rover", str(ROVER), "--base", str(BASE), "--nav", str(NAV),
            "--elevation-mask-deg", "15"]
    assert main([*args, "--rover-antenna", "AERAT2775_150"]) == 2
    assert "--antennas FILE" in capsys.readouterr().err
    assert main(["gnss", "--mode", "dgps", "--rover", str(ROVER), "--base", str(BASE), "--nav", str(NAV),
                 "--antennas", str(NGS)]) == 2
    assert "--antennas applies to --mode rtk" in capsys.readouterr().err
    assert main([*args, "--antennas", str(NGS), "--rover-antenna", "LEIAR25.R4 NONE"]) == 2
    assert "'LEIAR25.R4 NONE' is not in" in capsys.readouterr().err
    assert main([*args, "--antennas", str(NGS), "--rover-antenna", "AERAT2775_150", "--pos", str(pos),
                 "--json", str(js)]) == 0
    out = capsys.readouterr().out
    assert "antennas (ngs_abs_excerpt.pcv): rover AERAT2775_150 (calibrated); base TRM29659.00 (calibrated)" in out
    assert "GLONASS" not in out                 # GPS-only files: no word of GLONASS's integers
    head = [ln for ln in pos.read_text().splitlines() if ln.startswith("% antenna")]
    assert head == ["% antenna1  : AERAT2775_150 (calibrated)", "% antenna2  : TRM29659.00 (calibrated)"]
    summary = json.loads(js.read_text())
    assert summary["antennas"]["rover"]["from"] == "asked" and summary["antennas"]["base"]["from"] == "header"


def test_without_calibrations_two_different_antennas_are_pointed_out(capsys):
    """The 5.3-km car's headers name a JAVRINGANT_DM rover and a TRM159900.00 base: without
    --antennas the run says that their offsets go into the height and what calibrates them;
    GEONET's two TRM29659.00 are not pointed out."""
    car = data_path("cssrlib-fujisawa-car-2021")
    assert main(["gnss", "--mode", "rtk", "--rover", str(car / "rover.crx.gz"), "--base", str(car / "base.crx.gz"),
                 "--nav", str(car / "nav.rnx.gz"), "--base-xyz=-3959400.631,3385704.533,3667523.111",
                 "--start", "2021/09/22 06:31:00", "--end", "2021/09/22 06:31:10"]) == 0
    assert "antennas: rover JAVRINGANT_DM   JVDM, base TRM159900.00    SCIS" in capsys.readouterr().out
    assert main(["gnss", "--mode", "rtk", "--rover", str(ROVER), "--base", str(BASE), "--nav", str(NAV)]) == 0
    assert "antennas:" not in capsys.readouterr().out


def test_a_real_rover_antenna_calibrated_on_the_real_car():
    """The 5.3-km car's rover is a JAVRINGANT_DM (radome JVDM, which IGS05 lacks: its NONE
    calibration, L1 89 mm and L2 120 mm above the ARP); the base's TRM159900.00 is not in IGS05.
    Calibrated, the fixed track (the ARP now, not the phase centres) moves down by an offset
    between the two frequencies', nothing sideways, and fixes as many epochs (measured: 104 mm
    down, 0.7 mm sideways; 358 -> 359 fixed)."""
    car = data_path("cssrlib-fujisawa-car-2021")
    args = dict(base_xyz=(-3959400.631, 3385704.533, 3667523.111), config=RtkConfig(systems="GEJ"))
    files = (car / "rover.crx.gz", car / "base.crx.gz", [car / "nav.rnx.gz"])
    plain = _fixed(solve_rtk_rinex(*files, **args)[0])
    sols, info = solve_rtk_rinex(*files, **args, antennas=str(IGS05))
    calibrated = _fixed(sols)
    assert info["antennas"]["base"]["calibration"] is None
    assert info["antennas"]["rover"]["notes"][0] == "radome JVDM not calibrated: JAVRINGANT_DM without one used"
    common = sorted(set(plain) & set(calibrated))
    shift = np.mean([ecef_to_ned(calibrated[t], plain[t]) for t in common], axis=0)
    print(f"JAVRINGANT_DM calibrated: {len(plain)} -> {len(calibrated)} fixed, the track moved north/east/down "
          f"{1e3 * shift} mm")
    assert 0.089 < shift[2] < 0.120 and np.hypot(*shift[:2]) < 0.003
    assert len(calibrated) >= len(plain) - 2
