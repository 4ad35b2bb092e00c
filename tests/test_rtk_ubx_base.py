"""A u-blox capture as the base (two u-blox receivers logging .ubx, the field's common set-up):
``companion gnss --mode rtk`` and ``--mode dgps`` read its RXM-RAWX and RXM-SFRBX as they read a
rover's.  A .ubx has no surveyed position: ``--base-xyz X,Y,Z`` gives it, or ``--base-xyz spp``
takes the median of the base's own single-point solutions (RTKLIB's "average of single").

A zero baseline on real bytes: the real F9P capture of tests/data/qzsl6tool-hiroshima-rtcm3-ubx
as the base, RTKLIB convbin's RINEX of the same bytes as the rover, so our UBX decoding meets
RTKLIB's in every double difference."""
from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest

from companion.cli import main
from tests._data import data_path

pytestmark = [pytest.mark.real_data,
              pytest.mark.skipif(shutil.which("convbin") is None,
                                 reason="RTKLIB convbin not installed (apt install rtklib)")]

CAPTURE = data_path("qzsl6tool-hiroshima-rtcm3-ubx") / "20230919-114418.ubx"


@pytest.fixture(scope="module")
def rinex(tmp_path_factory):
    d = tmp_path_factory.mktemp("ubx_base")
    obs, nav = d / "r.obs", d / "r.nav"
    subprocess.run(["convbin", "-r", "ubx", "-v", "3.04", "-od", "-os", "-o", str(obs), "-n", str(nav),
                    str(CAPTURE)], check=True, capture_output=True, timeout=120)
    return obs, nav


def test_ubx_base_zero_baseline_with_its_own_single_point_position(rinex, tmp_path, capsys):
    obs, _ = rinex
    out = tmp_path / "zb.json"
    # no --nav: the base capture's RXM-SFRBX brings the ephemerides
    assert main(["gnss", "--rover", str(obs), "--base", str(CAPTURE), "--mode", "rtk", "--base-xyz", "spp",
                 "--json", str(out)]) == 0
    assert "single-point solutions (median" in capsys.readouterr().out
    summary = json.loads(out.read_text())
    assert summary["solved"] == summary["fixed"] >= 35                  # measured 36 of 36, four systems
    assert set(summary["satellites_by_system"]) >= set("GECJ")
    base = np.array(summary["base_antenna_e"])
    r = np.array([s["r_e"] for s in summary["solutions"]])
    assert np.max(np.linalg.norm(r - base, axis=1)) < 0.002             # measured 0.4 mm
    # the median single-point position is metres from the receiver's own (convbin's header): not
    # a survey, but close enough for the baseline
    approx = [float(x) for x in next(ln for ln in obs.read_text().splitlines()
                                     if "APPROX POSITION XYZ" in ln).split()[:3]]
    assert np.linalg.norm(base - approx) < 15.0


def test_ubx_base_without_a_position_says_how_to_give_one(rinex, capsys):
    obs, _ = rinex
    assert main(["gnss", "--rover", str(obs), "--base", str(CAPTURE), "--mode", "rtk"]) == 2
    err = capsys.readouterr().err
    assert "--base-xyz X,Y,Z" in err and "--base-xyz spp" in err
    assert main(["gnss", "--rover", str(obs), "--base", str(CAPTURE), "--mode", "dgps"]) == 2
    assert "--base-xyz X,Y,Z" in capsys.readouterr().err
    assert main(["gnss", "--rover", str(obs), "--base", str(CAPTURE), "--mode", "dgps", "--base-xyz", "spp"]) == 2
    assert "only with --mode rtk" in capsys.readouterr().err


@pytest.mark.parametrize("with_nav", [False, True], ids=["base-ephemerides", "nav-file"])
def test_ubx_base_in_dgps(rinex, tmp_path, with_nav):
    """DGPS against the same capture at the position convbin's header gives it: a zero baseline,
    so the corrected code solutions sit on that position (the header's own error cancels).  The
    base capture's ephemerides count before the systems are chosen: convbin's navigation file
    has no Galileo, the capture's RXM-SFRBX has."""
    obs, nav = rinex
    approx = next(ln for ln in obs.read_text().splitlines() if "APPROX POSITION XYZ" in ln).split()[:3]
    out = tmp_path / "dgps.json"
    assert main(["gnss", "--rover", str(obs), *(["--nav", str(nav)] if with_nav else []), "--base", str(CAPTURE),
                 "--mode", "dgps", "--base-xyz=" + ",".join(approx), "--truth-xyz=" + ",".join(approx),
                 "--json", str(out)]) == 0
    summary = json.loads(out.read_text())
    assert summary["solved"] == 36 and summary["rms_3d_m"] < 0.01              # measured 0.000 m
    assert set(summary["satellites_by_system"]) == set("GECJ")


def test_ubx_base_brings_glonass_from_its_strings(rinex, tmp_path, capsys):
    """GLONASS asked for (`--sys G,R,E,C,J`), no --nav: its orbits and channels come from the base
    capture's RXM-SFRBX strings (tests/test_glonass_sfrbx.py), and it joins as a float (the
    capture has no MON-VER: the model, hence the inter-channel biases, unknown)."""
    obs, _ = rinex
    out = tmp_path / "zb_r.json"
    assert main(["gnss", "--rover", str(obs), "--base", str(CAPTURE), "--mode", "rtk", "--base-xyz", "spp",
                 "--sys", "G,R,E,C,J", "--json", str(out)]) == 0
    assert "GLONASS integers: off" in capsys.readouterr().out
    summary = json.loads(out.read_text())
    assert summary["satellites_by_system"]["R"]["min"] >= 8                    # measured 9
    assert summary["solved"] == summary["fixed"] >= 35                         # measured 36 of 36
    base = np.array(summary["base_antenna_e"])
    r = np.array([s["r_e"] for s in summary["solutions"]])
    assert np.max(np.linalg.norm(r - base, axis=1)) < 0.002
