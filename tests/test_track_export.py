"""KML and GPX tracks (companion.io.track_export; `companion gnss --kml/--gpx`, issue 15): parsed back
with xml.etree, the coordinates, times and quality flags come round; on real RINEX the tracks hold
the .pos file's epochs, and RTKLIB's pos2kml, reading that .pos, draws the same points."""
from __future__ import annotations

import shutil
import subprocess
import xml.etree.ElementTree as ET
from datetime import datetime, timedelta, timezone

import numpy as np
import pytest

from companion.io.track_export import (GPS_EPOCH, TrackPoint, gps_minus_utc_s, gps_to_utc_iso, points_from_ecef,
                                       write_gpx, write_kml)
from companion.nav.earth import geodetic_to_ecef
from tests._data import data_path

KML = "{http://www.opengis.net/kml/2.2}"
GPX = "{http://www.topografix.com/GPX/1/1}"


def _kml_line(path):
    root = ET.parse(path).getroot()
    text = root.find(f".//{KML}LineString/{KML}coordinates").text
    return np.array([[float(v) for v in c.split(",")] for c in text.split()]), root


def _gpx_points(path):
    root = ET.parse(path).getroot()
    return root.findall(f".//{GPX}trkseg/{GPX}trkpt")


def _points(n=40):
    rng = np.random.default_rng(7)
    t0 = 1.38e9
    return [TrackPoint(t0 + 0.2 * k, -35.3 + rng.normal(0, 1e-3), 149.1 + rng.normal(0, 1e-3),
                       580.0 + rng.normal(0, 5.0), quality=[1, 2, 4, 5][k % 4], n_sats=10 + k % 5)
            for k in range(n)]


def test_kml_and_gpx_round_trip(tmp_path):
    pts = _points()
    write_kml(tmp_path / "t.kml", pts, "test")
    write_gpx(tmp_path / "t.gpx", pts, "test")
    line, root = _kml_line(tmp_path / "t.kml")
    want = np.array([[p.lon_deg, p.lat_deg, p.h_ellipsoid_m] for p in pts])
    assert line.shape == want.shape
    assert np.max(np.abs(line[:, :2] - want[:, :2])) <= 0.6e-9 and np.max(np.abs(line[:, 2] - want[:, 2])) <= 0.6e-4
    epochs = root.findall(f".//{KML}Folder/{KML}Placemark")
    assert [e.find(f"{KML}styleUrl").text for e in epochs] == [f"#q{p.quality}" for p in pts]
    assert epochs[0].find(f".//{KML}when").text == gps_to_utc_iso(pts[0].t_gps)
    trkpts = _gpx_points(tmp_path / "t.gpx")
    got = np.array([[float(e.get("lon")), float(e.get("lat")), float(e.find(f"{GPX}ele").text)] for e in trkpts])
    assert np.max(np.abs(got[:, :2] - want[:, :2])) <= 0.6e-9 and np.max(np.abs(got[:, 2] - want[:, 2])) <= 0.6e-4
    assert [e.find(f"{GPX}sat").text for e in trkpts] == [str(p.n_sats) for p in pts]
    assert {e.find(f"{GPX}fix").text for e in trkpts} == {"dgps", "3d"}
    # GPX time: UTC, 18 leap seconds in 2023
    t = datetime.strptime(trkpts[3].find(f"{GPX}time").text, "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=timezone.utc)
    assert (t - GPS_EPOCH).total_seconds() == pytest.approx(pts[3].t_gps - 18, abs=1e-3)


def test_points_from_ecef_and_no_quality_means_a_line_only(tmp_path):
    lat, lon, h = np.radians(34.4), np.radians(132.5), 50.0
    r = geodetic_to_ecef(lat, lon, h)
    pts = points_from_ecef([(1.0e9, r, None, None), (1.0e9 + 1, np.full(3, np.nan), None, None)])
    assert len(pts) == 1                                               # the non-finite one dropped
    assert pts[0].lat_deg == pytest.approx(34.4, abs=1e-9) and pts[0].h_ellipsoid_m == pytest.approx(50.0, abs=1e-4)
    write_kml(tmp_path / "l.kml", pts, "line")
    _, root = _kml_line(tmp_path / "l.kml")
    assert root.find(f".//{KML}Folder") is None and root.find(f".//{KML}Style") is None


def test_leap_seconds_by_date():
    def gps(y, mo, d, leap):
        return (datetime(y, mo, d, tzinfo=timezone.utc) - GPS_EPOCH).total_seconds() + leap
    assert gps_minus_utc_s(0.0) == 0
    assert gps_minus_utc_s(gps(2005, 4, 2, 13)) == 13                  # the GEONET 2005 data
    step = gps(2017, 1, 1, 18)
    assert gps_minus_utc_s(step) == 18 and gps_minus_utc_s(step - 2) == 17
    assert gps_to_utc_iso(step) == "2017-01-01T00:00:00.000Z"
    assert gps_to_utc_iso(step - 2) == "2016-12-31T23:59:59.000Z"
    assert gps_to_utc_iso(step, leap_seconds=0) == (GPS_EPOCH + timedelta(seconds=step)).strftime(
        "%Y-%m-%dT%H:%M:%S.000Z")


@pytest.mark.real_data
def test_companion_gnss_rtk_tracks_match_its_pos_file_and_pos2kml(tmp_path):
    from companion.cli import main
    d = data_path("rtklib-testdata-geonet-2005/rinex")
    pos, kml, gpx = tmp_path / "r.pos", tmp_path / "r.kml", tmp_path / "r.gpx"
    assert main(["gnss", "--rover", str(d / "07590920.05o"), "--nav", str(d / "07590920.05n"), "--base",
                 str(d / "30400920.05o"), "--mode", "rtk", "--pos", str(pos), "--kml", str(kml),
                 "--gpx", str(gpx)]) == 0
    rows = [ln.split() for ln in pos.read_text().splitlines() if not ln.startswith("%")]
    pos_llh = np.array([[float(r[3]), float(r[2]), float(r[4])] for r in rows])      # lon, lat, h
    line, root = _kml_line(kml)
    assert len(line) == len(rows) > 100
    # both printed from the same doubles: .pos 9 decimals / 4 for h, the tracks too
    assert np.max(np.abs(line - pos_llh)) <= 1.1e-4 and np.max(np.abs(line[:, :2] - pos_llh[:, :2])) <= 1.1e-9
    styles = [e.find(f"{KML}styleUrl").text for e in root.findall(f".//{KML}Folder/{KML}Placemark")]
    assert styles == [f"#q{r[5]}" for r in rows]
    trkpts = _gpx_points(gpx)
    assert len(trkpts) == len(rows)
    t0 = datetime.strptime(trkpts[0].find(f"{GPX}time").text, "%Y-%m-%dT%H:%M:%S.%fZ")
    assert t0 == datetime.strptime(" ".join(rows[0][:2]), "%Y/%m/%d %H:%M:%S.%f") - timedelta(seconds=13)
    if shutil.which("pos2kml") is None:
        return
    ref = tmp_path / "pos2kml.kml"
    subprocess.run(["pos2kml", "-a", "-o", str(ref), str(pos)], check=True, capture_output=True, timeout=30)
    ns = {"k": "http://earth.google.com/kml/2.1"}
    ref_root = ET.parse(ref).getroot()
    ref_line = np.array([[float(v) for v in c.split(",")] for c in
                         ref_root.find(".//k:LineString/k:coordinates", ns).text.split()])
    assert ref_line.shape == line.shape
    # pos2kml prints heights with 3 decimals
    assert np.max(np.abs(ref_line[:, :2] - line[:, :2])) <= 1.1e-9
    assert np.max(np.abs(ref_line[:, 2] - line[:, 2])) <= 6e-4
    ref_styles = [e.text for e in ref_root.findall(".//k:Placemark/k:styleUrl", ns)]
    assert [s.replace("#P", "#q") for s in ref_styles] == styles
