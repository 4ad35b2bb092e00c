"""``companion gnss --mode rtk`` with an RTCM 3 capture as the base (what an NTRIP user logs beside
the rover): MSM7 observations, the 1005 antenna reference point as the base position, decoded as
the service decodes its caster's stream.

The capture is made here from the real Septentrio base of tests/data/matrtklib-septentrio-static-2024:
its GPS (L1 C/A, L2 P(Y), L2C, L5), Galileo (E1, E5a, E5b) and BeiDou (B1I, B2I, B3I) observations
encoded as MSM7 (sitl.rtcm_msm, decoded back by pyrtcm in its own tests), each signal's lock time
counted from the first epoch and restarted at a loss-of-lock flag, with a 1005 of the base
position; no Doppler.  The RINEX base with the same signals must give the same solutions (MSM7
rounds the pseudorange to 0.6 mm and the phase to 0.14 mm).  And a real single-frequency capture
(legacy 1002) in a zero baseline."""
from __future__ import annotations

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest

from companion.gnss.rinex_obs import read_rinex_obs
from sitl.caster import encode_1005, encode_1033
from sitl.rtcm_msm import Msm7Encoder
from tests.test_rtk_septentrio_static import BASE, BASE_XYZ, NAV, REF_ROVER, ROVER

pytestmark = pytest.mark.real_data

#: per system: RINEX code -> the MSM code it goes out as
CODES = {"G": {"L1C": ("1C",), "L2W": ("2W",), "L2L": ("2L",), "L5Q": ("5Q",)},
         "E": {"L1C": ("1C",), "L5Q": ("5Q",), "L7Q": ("7Q",)},
         "C": {"L2I": ("2I",), "L7I": ("7I",), "L6I": ("6I",)}}


def _msm7_capture(path, station: bool = True, antenna: str | None = None) -> None:
    """``antenna``: the IGS type a 1033 after the 1005 names (none without)."""
    _, epochs = read_rinex_obs(BASE, "GEC")
    encoders = [Msm7Encoder(7, codes=CODES[s], system=s) for s in "GEC"]
    lock_start: dict = {}
    with open(path, "wb") as fh:
        if station:
            fh.write(encode_1005(7, BASE_XYZ))
        if antenna is not None:
            fh.write(encode_1033(7, antenna=antenna))
        for e in epochs:
            obs = []
            for o in e.observations:
                key = (o.sat, o.signal)
                if key not in lock_start or o.loss_of_lock:
                    lock_start[key] = e.t_gps
                # no Doppler (RTK does not use it; a cell's range rate off its first frequency's by
                # more than MSM7's fine field spans, 1.6 m/s, would not encode)
                obs.append(dataclasses.replace(o, lock_time_s=e.t_gps - lock_start[key] + 1.0, doppler_hz=math.nan))
            e = dataclasses.replace(e, observations=tuple(obs))
            todo = [enc for enc in encoders if enc.has_observations(e)]
            fh.write(b"".join(enc.encode(e, more_follow=i < len(todo) - 1) for i, enc in enumerate(todo)))


def test_an_rtcm_base_gives_the_solutions_of_the_same_observations_in_rinex(tmp_path):
    from companion.cli import main
    rtcm = tmp_path / "base.rtcm3"
    _msm7_capture(rtcm)
    out = {}
    # the RTCM run takes the base position from its 1005; the RINEX run is given the same one
    for name, base, extra in (("rtcm", rtcm, []), ("rinex", BASE, ["--base-xyz=" + ",".join(f"{v}" for v in BASE_XYZ)])):
        js = tmp_path / f"{name}.json"
        assert main(["gnss", "--rover", str(ROVER), "--base", str(base), "--nav", str(NAV), "--sys", "G,E,C",
                     "--mode", "rtk", "--json", str(js), *extra]) == 0
        out[name] = json.loads(js.read_text())
    a, b = out["rtcm"]["solutions"], out["rinex"]["solutions"]
    assert len(a) == len(b) == 120 and all(s["q"] == 1 for s in a)
    assert [s["n_fixed"] for s in a] == [s["n_fixed"] for s in b]
    ra = np.array([s["r_e"] for s in a])
    d = np.linalg.norm(ra - np.array([s["r_e"] for s in b]), axis=1)
    rms = float(np.sqrt(np.mean(np.sum((ra - REF_ROVER) ** 2, axis=1))))
    print(f"RTCM base: 120/120 fixed, RMS 3-D {rms:.4f} m; at most {d.max() * 1e3:.2f} mm from the RINEX base")
    assert rms < 0.004 and d.max() < 0.002


def test_the_base_antenna_a_1033_names_is_calibrated(tmp_path, capsys):
    """--antennas finds the base's type in its 1033 (an RTCM base has no RINEX header): a type
    declared with its phase centres 100 mm above the ARP raises the base, and the rover with it, by
    that; the rover's header says 'Unknown', which stays uncalibrated and is said to."""
    from companion.cli import main
    from companion.nav.earth import ecef_to_ned
    from tests.test_rtk_antennas import _antex_text
    rtcm, atx = tmp_path / "base.rtcm3", tmp_path / "up.atx"
    _msm7_capture(rtcm, antenna="TESTANT_UP100 NONE")
    atx.write_text(_antex_text({"TESTANT_UP100   NONE": (0.0, {c: ([0.0, 0.0, 100.0], [0.0] * 19, None)
                                                                for c in ("G01", "G02", "G05")})}))
    out = {}
    for name, extra in (("plain", []), ("calibrated", ["--antennas", str(atx)])):
        js = tmp_path / f"{name}.json"
        assert main(["gnss", "--rover", str(ROVER), "--base", str(rtcm), "--nav", str(NAV), "--sys", "G,E,C",
                     "--mode", "rtk", "--end", "2024/06/24 08:20:29", "--json", str(js), *extra]) == 0
        out[name] = json.loads(js.read_text())
        assert len(out[name]["solutions"]) == 30
    assert "base TESTANT_UP100 NONE (calibrated; " in capsys.readouterr().out
    ant = out["calibrated"]["antennas"]
    assert ant["base"]["from"] == "header" and ant["rover"]["calibration"] is None
    # Galileo's and BeiDou's frequencies took GPS's nearest, and that is said
    assert {"E01 from G01", "E05 from G05", "C02 from G01"} <= set(ant["base"]["notes"])
    a, b = (np.array([s["r_e"] for s in out[k]["solutions"]]) for k in ("plain", "calibrated"))
    shift = ecef_to_ned(REF_ROVER + (b - a).mean(axis=0), REF_ROVER)
    print(f"base declared 100 mm up: the rover moved north/east/down {1e3 * shift} mm")
    assert shift[2] == pytest.approx(-0.100, abs=0.002) and np.hypot(*shift[:2]) < 0.002


def test_what_an_rtcm_base_lacks_is_said(tmp_path, capsys):
    """This capture carries no ephemeris; one without its 1005 has no base position either (it
    used to run with the base at NaN: every satellite "below the mask", no word of why)."""
    from companion.cli import main
    rtcm = tmp_path / "base.rtcm3"
    _msm7_capture(rtcm)
    assert main(["gnss", "--rover", str(ROVER), "--base", str(rtcm), "--mode", "rtk"]) == 2
    assert "neither capture brings them" in capsys.readouterr().err
    _msm7_capture(rtcm, station=False)
    assert main(["gnss", "--rover", str(ROVER), "--base", str(rtcm), "--nav", str(NAV), "--mode", "rtk"]) == 2
    assert "an RTCM 1005/1006" in capsys.readouterr().err


@pytest.mark.skipif(shutil.which("convbin") is None, reason="RTKLIB convbin not installed (apt install rtklib)")
def test_a_real_single_frequency_base_capture_zero_baseline(tmp_path):
    """A real Emlid Reach (u-blox M8T) capture: legacy 1002 (GPS L1 only) with 1006 and 1019,
    starting mid-frame, as the base; RTKLIB convbin's RINEX of the same bytes as the rover.  A zero
    baseline: L1-only RTK through the 1002 decoder and the capture's own ephemerides, no --nav."""
    import subprocess
    from companion.cli import main
    from tests._data import data_path
    capture = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20190529hiroshima.rtcm"
    assert capture.read_bytes()[0] != 0xD3
    obs = tmp_path / "r.obs"
    subprocess.run(["convbin", "-r", "rtcm3", "-tr", "2019/05/29", "00:00:00", "-v", "3.04", "-od", "-os",
                    "-o", str(obs), "-n", str(tmp_path / "r.nav"), str(capture)], check=True, capture_output=True,
                   timeout=120)
    arp = next(ln for ln in obs.read_text().splitlines() if "APPROX POSITION XYZ" in ln).split()[:3]
    out = tmp_path / "zb.json"
    assert main(["gnss", "--rover", str(obs), "--base", str(capture), "--mode", "rtk",
                 "--truth-xyz=" + ",".join(arp), "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert summary["satellites_by_system"]["G"]["min"] >= 5
    assert summary["solved"] >= 40 and summary["fixed"] == summary["solved"]     # measured 41 of 41
    assert summary["max_3d_m"] < 0.001                                          # 0.3 mm (RINEX's rounding)
