"""Carrier-phase RTK (companion.gnss.rtk) on the real GEONET pair 0759/3040 (3.3 km, GPS L1/L2,
30 s): against the static reference position of 0759 and against RTKLIB's rnx2rtkp on the same
files in the same run."""
from __future__ import annotations

import dataclasses
import shutil
import subprocess

import numpy as np
import pytest

from companion.gnss.pos_format import write_pos
from companion.gnss.rtk import RtkConfig
from companion.gnss.rtk_post import pos_records, solve_rtk_rinex
from tests._data import data_path
from tests._rtklib_pos import rtklib_fixed_xyz

pytestmark = pytest.mark.real_data

D = data_path("rtklib-testdata-geonet-2005/rinex")
ROVER, BASE, NAV = D / "07590920.05o", D / "30400920.05o", D / "07590920.05n"
BASE_HEADER_XYZ = (-3978242.4348, 3382841.1715, 3649902.7667)
#: 0759 relative to 3040's header position: static 1-h RTK (tests/data/README.md)
REF_0759 = np.array([-3976219.6640, 3382372.5415, 3652513.0546])
#: RTKLIB 2.4.3 kinematic, fix-and-hold, 15 deg, on these files (tests/data/README.md), when
#: rnx2rtkp is not installed to measure it
RTKLIB_RMS_3D_M = 0.012


def _rms(points) -> float:
    d = np.asarray(points) - REF_0759
    return float(np.sqrt(np.mean(np.sum(d ** 2, axis=1))))


def _rtklib_fixed(tmp_path, mask_deg: float) -> dict[int, np.ndarray]:
    out = tmp_path / f"rtklib-{mask_deg:g}.pos"
    subprocess.run(["rnx2rtkp", "-p", "2", "-f", "2", "-m", f"{mask_deg:g}", "-h", "-e", "-r",
                    *(f"{v}" for v in BASE_HEADER_XYZ), "-o", str(out), str(ROVER), str(BASE), str(NAV)],
                   check=True, capture_output=True, timeout=120)
    return rtklib_fixed_xyz(out)


def test_kinematic_rtk_fixes_every_epoch_from_the_first_at_centimetre_level():
    sols, info = solve_rtk_rinex(ROVER, BASE, [NAV])
    fixed = [s for s in sols if s.quality == 1]
    print(f"RTK (10 deg): {len(fixed)} of {info['paired_epochs']} fixed, RMS 3-D {_rms([s.r_e for s in fixed]):.4f} m, "
          f"counters {info['counters']}")
    assert info["paired_epochs"] == 120
    assert len(fixed) >= 115 and sols[0].quality == 1 and sols[0].t_gps == min(s.t_gps for s in sols)
    assert _rms([s.r_e for s in fixed]) <= RTKLIB_RMS_3D_M
    # a fixed solution's stated sigma is honest: 3-D errors within 4.5 of their own 3-D sigma
    for s in fixed:
        assert np.linalg.norm(s.r_e - REF_0759) < 4.5 * np.sqrt(np.trace(s.cov_e)) + 0.003


@pytest.mark.skipif(shutil.which("rnx2rtkp") is None, reason="RTKLIB's rnx2rtkp not installed (apt install rtklib)")
def test_as_good_as_rtklib_on_the_same_files(tmp_path):
    """At 15 degrees the last six epochs have five satellites: a fix there would leave a 3-D sigma
    over 10 cm (RtkConfig.max_fixed_sigma_3d_m; 2-11 cm off), so they stay float.  RTKLIB fixes one
    of them (measured: ours 114, RTKLIB 115, both 0.0085 / 0.0084 m on the 114 they share)."""
    sols, _ = solve_rtk_rinex(ROVER, BASE, [NAV], config=RtkConfig(elevation_mask_deg=15.0))
    ours = {round(s.t_gps): s.r_e for s in sols if s.quality == 1}
    theirs = _rtklib_fixed(tmp_path, 15.0)
    common = sorted(set(ours) & set(theirs))
    a, b = _rms([ours[t] for t in common]), _rms([theirs[t] for t in common])
    print(f"15 deg: ours {len(ours)} fixed, RTKLIB {len(theirs)}; on the {len(common)} both fixed: "
          f"ours {a:.4f} m, RTKLIB {b:.4f} m")
    assert len(common) >= 0.95 * len(theirs)
    assert all(s.n_sats <= 5 for s in sols if s.quality != 1)
    assert a <= b + 0.0005


def slipped_reader(read, t_slip: float, sat: str, cycles: dict, flag: bool = False):
    """``read`` (read_rinex_obs) with ``cycles`` (signal -> cycles) added to ``sat``'s phases in the
    rover file from ``t_slip`` on; ``flag``: the receiver's loss-of-lock flag set at ``t_slip``."""
    def reader(path, systems="G", t_gps_window=None):
        h, eps = read(path, systems, t_gps_window)
        if path != ROVER:
            return h, eps
        out = []
        for e in eps:
            if e.t_gps >= t_slip:
                obs = tuple(dataclasses.replace(o, carrier_cycles=o.carrier_cycles + cycles[o.signal],
                                                loss_of_lock=o.loss_of_lock or (flag and e.t_gps == t_slip))
                            if o.sat == sat and o.signal in cycles else o for o in e.observations)
                e = dataclasses.replace(e, observations=obs)
            out.append(e)
        return h, out
    return reader


def test_a_cycle_slip_without_a_flag_is_found_and_the_fix_survives(monkeypatch):
    """7 cycles added to one satellite's rover L1 phase from mid-file on, with no loss-of-lock flag:
    the geometry-free test finds it, the ambiguity restarts, and no epoch fixes wrongly."""
    from companion.gnss import rtk_post
    from companion.gnss.rinex_obs import read_rinex_obs
    t_slip = read_rinex_obs(ROVER)[1][60].t_gps
    monkeypatch.setattr(rtk_post, "read_rinex_obs", slipped_reader(read_rinex_obs, t_slip, "G20", {"L1C": 7.0}))
    sols, info = solve_rtk_rinex(ROVER, BASE, [NAV])
    fixed = [s for s in sols if s.quality == 1]
    assert info["counters"].get("slips: geometry-free", 0) >= 1
    assert len(fixed) >= 110
    assert max(np.linalg.norm(s.r_e - REF_0759) for s in fixed) < 0.15          # no wrong fix
    assert _rms([s.r_e for s in fixed]) <= RTKLIB_RMS_3D_M * 1.5


@pytest.mark.skipif(shutil.which("pos2kml") is None, reason="RTKLIB's pos2kml not installed (apt install rtklib)")
@pytest.mark.parametrize("coords,time_format", [("llh", "gpst"), ("xyz", "week")])
def test_pos_output_is_read_by_rtklib_pos2kml(tmp_path, coords, time_format):
    sols, _ = solve_rtk_rinex(ROVER, BASE, [NAV])
    pos = tmp_path / "rtk.pos"
    write_pos(pos, pos_records(sols), program="companion test", inputs=[str(ROVER), str(BASE), str(NAV)],
              coords=coords, time_format=time_format)
    subprocess.run(["pos2kml", str(pos)], check=True, capture_output=True, timeout=60)
    kml = (tmp_path / "rtk.kml").read_text()
    points = [ln for ln in kml.splitlines() if "<coordinates>" in ln]
    assert len(points) >= len(sols)
    lon, lat, _ = (float(v) for v in points[-1].split("<coordinates>")[1].split("</coordinates>")[0].split(","))
    assert abs(lat - 35.160872) < 1e-5 and abs(lon - 139.613837) < 1e-5


def _shift_header(src, dst, delta_h_m: float):
    """A copy of a RINEX 2 file whose marker is ``delta_h_m`` below the antenna: APPROX POSITION
    moved down along the ellipsoid normal and ANTENNA: DELTA H set, so the antenna stays put."""
    from companion.nav.earth import C_n_e, ecef_to_geodetic
    lines = src.read_text().splitlines()
    out = []
    for ln in lines:
        label = ln[60:].strip()
        if label == "APPROX POSITION XYZ":
            r = np.array([float(ln[0:14]), float(ln[14:28]), float(ln[28:42])])
            lat, lon, _ = ecef_to_geodetic(r)
            r = r + C_n_e(lat, lon) @ np.array([0.0, 0.0, delta_h_m])        # down
            ln = f"{r[0]:14.4f}{r[1]:14.4f}{r[2]:14.4f}" + " " * 18 + "APPROX POSITION XYZ"
        elif label == "ANTENNA: DELTA H/E/N":
            ln = f"{delta_h_m:14.4f}{0.0:14.4f}{0.0:14.4f}" + " " * 18 + "ANTENNA: DELTA H/E/N"
        out.append(ln)
    dst.write_text("\n".join(out) + "\n")


@pytest.mark.parametrize("mode", ["dgps", "rtk"])
def test_base_antenna_delta_is_applied(tmp_path, mode):
    """A base marker 1.5 m below its antenna (the header says so): the same rover solution."""
    import json
    from companion.cli import main
    base2 = tmp_path / "30400920.05o"
    _shift_header(BASE, base2, 1.5)
    res = {}
    for name, b in (("orig", BASE), ("shifted", base2)):
        js = tmp_path / f"{name}.json"
        assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(b), "--mode", mode,
                     "--json", str(js)]) == 0
        res[name] = np.array([s["r_e"] for s in json.loads(js.read_text())["solutions"]])
    assert res["orig"].shape == res["shifted"].shape
    assert np.max(np.linalg.norm(res["orig"] - res["shifted"], axis=1)) < 0.002


def test_cli_rtk_writes_rtklib_pos_with_fix_flags(tmp_path):
    from companion.cli import main
    pos = tmp_path / "rtk.pos"
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(BASE), "--mode", "rtk",
                 "--truth-xyz=" + ",".join(f"{v}" for v in REF_0759), "--pos", str(pos)]) == 0
    rows = [ln.split() for ln in pos.read_text().splitlines() if not ln.startswith("%")]
    assert len(rows) == 120 and sum(r[5] == "1" for r in rows) >= 115
    assert "% navi sys  : G\n" in pos.read_text()          # the systems solved with (GPS-only files)
    assert all(float(r[-1]) >= 3.0 for r in rows if r[5] == "1")        # ratio column of fixed epochs
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--mode", "rtk"]) == 2   # no base


def test_a_success_rate_floor_leaves_the_first_epoch_float():
    """RtkConfig.min_success_rate (off by default): GEONET's first epoch fixes right at ratio 25 with
    a bootstrapped success rate of 0.976, so a 0.999 floor (the engine's) leaves it float."""
    sols, info = solve_rtk_rinex(ROVER, BASE, [NAV])
    assert sols[0].quality == 1 and 0.95 < sols[0].success_rate < 0.999
    sols, info = solve_rtk_rinex(ROVER, BASE, [NAV], config=RtkConfig(min_success_rate=0.999))
    assert sols[0].quality == 2 and info["counters"]["fixes rejected: success rate"] >= 1
    assert sum(s.quality == 1 for s in sols) >= 115


def test_systems_absent_from_the_files_are_a_clear_error():
    with pytest.raises(ValueError, match=r"rover file has no observations of the selected systems \(C\); it has G"):
        solve_rtk_rinex(ROVER, BASE, [NAV], config=RtkConfig(systems="C"))


def test_cli_rtk_on_the_first_frequency_alone(tmp_path):
    """``--freq l1``: each system's first frequency alone (a single-frequency receiver's RTK), said
    in the summary and the .pos header; ``--freq if`` is refused for RTK."""
    import json
    from companion.cli import main
    js, pos = tmp_path / "l1.json", tmp_path / "l1.pos"
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(BASE), "--mode", "rtk",
                 "--freq", "l1", "--json", str(js), "--pos", str(pos),
                 "--truth-xyz=" + ",".join(f"{v}" for v in REF_0759)]) == 0
    summary = json.loads(js.read_text())
    assert "L2W" not in summary["signals"] and "L1C" in summary["signals"]
    assert "% freqs     : L1\n" in pos.read_text()
    print(f"GEONET, L1 alone: {summary['fixed']} of {summary['solved']} fixed, RMS 3-D of the fixed "
          f"{summary['fixed_stats']['rms_3d_m']:.4f} m, at most {summary['fixed_stats']['max_3d_m']:.3f} m")
    assert summary["fixed"] >= 100 and summary["fixed_stats"]["max_3d_m"] < 0.1
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(BASE), "--mode", "rtk",
                 "--freq", "if"]) == 2


@pytest.mark.parametrize("mask_deg,within_m", [(15.0, 0.003), (10.0, 0.005)])
def test_cli_static_survey_lands_on_rtklibs_static_answer(tmp_path, mask_deg, within_m):
    """``--static``: the rover stood still; the last epoch's position, from all 120, is the survey
    result.  The reference itself is RTKLIB 2.4.3's static L1+L2 solution of these files at a
    15-degree mask (tests/data/README.md): measured 1.3 mm from it at 15 degrees, 2.7 mm at 10."""
    import json
    from companion.cli import main
    js, pos = tmp_path / "static.json", tmp_path / "static.pos"
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(BASE), "--mode", "rtk", "--static",
                 "--elevation-mask-deg", str(mask_deg), "--json", str(js), "--pos", str(pos),
                 "--truth-xyz=" + ",".join(f"{v}" for v in REF_0759)]) == 0
    st = json.loads(js.read_text())["static_position"]
    off = float(np.linalg.norm(np.array(st["r_e"]) - REF_0759))
    assert "% pos mode  : static\n" in pos.read_text()
    print(f"static at {mask_deg:g} deg: {1000 * off:.1f} mm from RTKLIB's static solution, sigma "
          f"{[round(1000 * v, 1) for v in st['sigma_ned_m']]} mm")
    assert st["fixed"] and st["epochs"] == 120 and off < within_m and max(st["sigma_ned_m"]) < 0.005
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(BASE), "--mode", "rtk", "--static",
                 "--direction", "combined"]) == 2


def test_cli_rtk_between_start_and_end_and_how_the_fixes_came(tmp_path, capsys):
    """``--start`` / ``--end`` (GPST, RTKLIB's form or ISO) cut the rover's span, the base's follows;
    the summary says the fix rate, the first fix and the longest run without one."""
    import json
    from companion.cli import main
    js = tmp_path / "part.json"
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(BASE), "--mode", "rtk",
                 "--start", "2005/04/02 00:10:00", "--end", "2005-04-02T00:19:30", "--json", str(js)]) == 0
    summary = json.loads(js.read_text())
    assert summary["epochs"] == summary["solved"] == 20 and summary["base_epochs"] >= 20   # (00:19:30 is tagged .001 s)
    assert summary["fix_rate"] == 1.0 and summary["first_fix_s"] == 0.0 and summary["longest_unfixed_epochs"] == 0
    assert "fix: 100.0 % of the epochs, from the first epoch" in capsys.readouterr().out
    assert main(["gnss", "--rover", str(ROVER), "--nav", str(NAV), "--base", str(BASE), "--mode", "rtk",
                 "--start", "2005/04/03 00:00:00"]) == 2
    assert "it covers 2005/04/02 00:00:00 to 00:59:30 GPST" in capsys.readouterr().err
