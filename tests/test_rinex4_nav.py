"""RINEX 4 navigation files (tests/data/georust-rinex4-nav-kms3-2022: a real one from Septentrio's
sbf2rin): every record sits under a '> EPH G02 LNAV' line, and ION / STO records, CNAV ephemerides,
GLONASS and SBAS records of other lengths come between.  The reader read 19 of its 123 Keplerian
ephemerides before (the '>' lines taken for records), silently."""
from __future__ import annotations

import dataclasses
import gzip
from collections import Counter

import numpy as np
import pytest

from companion.gnss.ephemeris import satellite_state
from companion.gnss.rinex import read_rinex_nav
from tests._data import data_path

pytestmark = pytest.mark.real_data

NAV4 = data_path("georust-rinex4-nav-kms3-2022/KMS300DNK_R_20221591000_01H_MN.rnx.gz")
KEPLER = {("G", "LNAV"), ("J", "LNAV"), ("E", "INAV"), ("E", "FNAV"), ("C", "D1"), ("C", "D2")}


def _as_rinex3(tmp_path):
    """The same file laid out as RINEX 3: the Keplerian records without their '>' lines, every
    other record left out, the version 3.04."""
    lines = gzip.decompress(NAV4.read_bytes()).decode().splitlines()
    head = next(i for i, ln in enumerate(lines) if "END OF HEADER" in ln) + 1
    out = ["     3.04" + lines[0][9:]] + lines[1:head]
    keep = False
    for ln in lines[head:]:
        if ln.startswith(">"):
            f = ln[1:].split()
            keep = f[0] == "EPH" and (f[1][:1], f[2]) in KEPLER
            continue
        if keep:
            out.append(ln)
    p = tmp_path / "as_rinex3.rnx"
    p.write_text("\n".join(out) + "\n")
    return p, Counter((ln[1:].split()[1][:1], ln[1:].split()[2]) for ln in lines[head:] if ln.startswith("> EPH"))


def test_every_keplerian_record_is_read_as_its_rinex3_twin(tmp_path):
    v3_file, markers = _as_rinex3(tmp_path)
    v4, v3 = read_rinex_nav(NAV4), read_rinex_nav(v3_file)
    assert markers[("R", "FDMA")] > 0 and markers[("S", "SBAS")] > 0      # records skipped on the way
    assert [dataclasses.astuple(e) for e in v4] == [dataclasses.astuple(e) for e in v3]
    by_sys = Counter(e.sat[0] for e in v4)
    # every GPS, BeiDou and QZSS record; Galileo's F/NAV ones only where no I/NAV twin exists
    assert by_sys["G"] == markers[("G", "LNAV")] == 30
    assert by_sys["C"] == markers[("C", "D1")] + markers[("C", "D2")] == 36
    assert by_sys["J"] == markers[("J", "LNAV")] == 1
    assert markers[("E", "INAV")] <= by_sys["E"] < markers[("E", "INAV")] + markers[("E", "FNAV")]


def test_the_orbits_are_orbits():
    """Each ephemeris at its own reference time: MEO at 25.5-29.7e6 m from the earth's centre
    (GPS, Galileo, BeiDou MEO; Galileo E14 and E18, left in eccentric orbits by their launch,
    23-33e6 m), BeiDou IGSO/GEO at ~42.2e6 m and QZSS's quasi-zenith orbits (eccentricity 0.075)
    39-45.4e6 m, speeds of at most a few km/s."""
    for e in read_rinex_nav(NAV4):
        r, v, _, _ = satellite_state(e, e.t_oe_gps)
        radius = float(np.linalg.norm(r))
        meo = (23.0e6, 33.0e6) if e.sat in ("E14", "E18") else (25.5e6, 29.7e6)
        high = (38.9e6, 45.5e6) if e.sat[0] == "J" else (41.5e6, 43.0e6)
        assert meo[0] < radius < meo[1] or high[0] < radius < high[1], (e.sat, radius)
        assert 0.0 <= float(np.linalg.norm(v)) < 4.1e3, e.sat


def test_systems_not_asked_for_are_skipped():
    assert {e.sat[0] for e in read_rinex_nav(NAV4, systems="E")} == {"E"}
    assert read_rinex_nav(NAV4, systems="R") == []
