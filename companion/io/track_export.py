"""A trajectory as Google Earth KML or GPX 1.1 (standard library XML only).

Points are WGS-84 latitude/longitude in degrees and *ellipsoidal* height in metres, stamped in GPS
time (s since 1980-01-06).  KML: one LineString (``altitudeMode absolute``: KML means heights above
mean sea level, so the line floats by the geoid undulation, as RTKLIB's pos2kml without a geoid
model does) and, when the points carry RTKLIB's quality flag, one time-stamped point per epoch
styled by it (fix green, float yellow, DGPS blue, single red, as rtkplot colours them) so Google
Earth's time slider plays the flight.  GPX: one ``trkseg``, UTC ``time``, ``ele`` (ellipsoidal;
GPX does not say which height it means), ``fix`` and ``sat`` when known.

GPS to UTC uses the leap-second table below (GPS - UTC by date) unless a fixed offset is given.
"""
from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

GPS_EPOCH = datetime(1980, 1, 6, tzinfo=timezone.utc)
KML_NS = "http://www.opengis.net/kml/2.2"
GPX_NS = "http://www.topografix.com/GPX/1/1"
# UTC dates from which GPS - UTC was one second more (IERS Bulletin C; none since 2017)
_LEAP_DATES_UTC = ("1981-07-01", "1982-07-01", "1983-07-01", "1985-07-01", "1988-01-01", "1990-01-01",
                   "1991-01-01", "1992-07-01", "1993-07-01", "1994-07-01", "1996-01-01", "1997-07-01",
                   "1999-01-01", "2006-01-01", "2009-01-01", "2012-07-01", "2015-07-01", "2017-01-01")
_LEAP_STEPS_GPS_S = tuple((datetime.fromisoformat(d).replace(tzinfo=timezone.utc) - GPS_EPOCH).total_seconds() + k
                          for k, d in enumerate(_LEAP_DATES_UTC, start=1))
# RTKLIB Q -> KML style (aabbggrr) and GPX <fix>
QUALITY_STYLE = {1: ("fix", "ff00ff00"), 2: ("float", "ff00ffff"), 3: ("sbas", "ffff00ff"),
                 4: ("dgps", "ffff0000"), 5: ("single", "ff0000ff"), 6: ("ppp", "ffffffff")}
QUALITY_GPX_FIX = {1: "dgps", 2: "dgps", 3: "dgps", 4: "dgps", 5: "3d", 6: "3d"}


@dataclass(frozen=True)
class TrackPoint:
    t_gps: float
    lat_deg: float
    lon_deg: float
    h_ellipsoid_m: float
    quality: int | None = None      # RTKLIB Q (1 fix ... 6 PPP), None = not known
    n_sats: int | None = None


def gps_minus_utc_s(t_gps: float) -> int:
    """Leap seconds (GPS - UTC) in force at GPS time ``t_gps``."""
    return sum(1 for step in _LEAP_STEPS_GPS_S if t_gps >= step)


def gps_to_utc_iso(t_gps: float, leap_seconds: int | None = None) -> str:
    """ISO 8601 UTC (millisecond) of a GPS time; ``leap_seconds`` None = from the table."""
    leap = gps_minus_utc_s(t_gps) if leap_seconds is None else leap_seconds
    t = GPS_EPOCH + timedelta(seconds=round(t_gps - leap, 3))
    return t.strftime("%Y-%m-%dT%H:%M:%S.") + f"{t.microsecond // 1000:03d}Z"


def points_from_ecef(samples) -> list[TrackPoint]:
    """``(t_gps, r_e, quality, n_sats)`` tuples (ECEF metres) -> points; non-finite positions dropped."""
    from ..nav.earth import ecef_to_geodetic          # numpy: only when there is something to convert
    out = []
    for t, r_e, q, ns in samples:
        if not all(math.isfinite(float(x)) for x in r_e):
            continue
        lat, lon, h = ecef_to_geodetic(r_e)
        out.append(TrackPoint(float(t), math.degrees(lat), math.degrees(lon), float(h), q, ns))
    return out


def points_from_pos_records(records) -> list[TrackPoint]:
    """:class:`companion.gnss.pos_format.PosRecord` s -> points (the same epochs the .pos file has)."""
    return points_from_ecef((r.t_gps, r.r_e, r.quality, r.n_sats) for r in records)


def kml_document(points, name: str, *, leap_seconds: int | None = None) -> ET.ElementTree:
    ET.register_namespace("", KML_NS)
    k = f"{{{KML_NS}}}"
    kml = ET.Element(f"{k}kml")
    doc = ET.SubElement(kml, f"{k}Document")
    ET.SubElement(doc, f"{k}name").text = name
    with_q = any(p.quality is not None for p in points)
    if with_q:
        for q, (label, colour) in QUALITY_STYLE.items():
            st = ET.SubElement(doc, f"{k}Style", {"id": f"q{q}"})
            icon = ET.SubElement(st, f"{k}IconStyle")
            ET.SubElement(icon, f"{k}color").text = colour
            ET.SubElement(icon, f"{k}scale").text = "0.4"
            ET.SubElement(ET.SubElement(icon, f"{k}Icon"), f"{k}href").text = \
                "http://maps.google.com/mapfiles/kml/shapes/shaded_dot.png"
            ET.SubElement(ET.SubElement(st, f"{k}LabelStyle"), f"{k}scale").text = "0"
    pm = ET.SubElement(doc, f"{k}Placemark")
    ET.SubElement(pm, f"{k}name").text = "track"
    ls = ET.SubElement(pm, f"{k}LineString")
    ET.SubElement(ls, f"{k}altitudeMode").text = "absolute"
    ET.SubElement(ls, f"{k}coordinates").text = " ".join(_kml_coord(p) for p in points)
    if with_q:
        folder = ET.SubElement(doc, f"{k}Folder")
        ET.SubElement(folder, f"{k}name").text = "epochs"
        for p in points:
            e = ET.SubElement(folder, f"{k}Placemark")
            ET.SubElement(ET.SubElement(e, f"{k}TimeStamp"), f"{k}when").text = gps_to_utc_iso(p.t_gps, leap_seconds)
            if p.quality in QUALITY_STYLE:
                ET.SubElement(e, f"{k}styleUrl").text = f"#q{p.quality}"
            pt = ET.SubElement(e, f"{k}Point")
            ET.SubElement(pt, f"{k}altitudeMode").text = "absolute"
            ET.SubElement(pt, f"{k}coordinates").text = _kml_coord(p)
    return ET.ElementTree(kml)


def _kml_coord(p: TrackPoint) -> str:
    return f"{p.lon_deg:.9f},{p.lat_deg:.9f},{p.h_ellipsoid_m:.4f}"


def gpx_document(points, name: str, *, leap_seconds: int | None = None) -> ET.ElementTree:
    ET.register_namespace("", GPX_NS)
    g = f"{{{GPX_NS}}}"
    gpx = ET.Element(f"{g}gpx", {"version": "1.1", "creator": "companion"})
    trk = ET.SubElement(gpx, f"{g}trk")
    ET.SubElement(trk, f"{g}name").text = name
    seg = ET.SubElement(trk, f"{g}trkseg")
    for p in points:
        pt = ET.SubElement(seg, f"{g}trkpt", {"lat": f"{p.lat_deg:.9f}", "lon": f"{p.lon_deg:.9f}"})
        # GPX 1.1 schema order: ele, time, ..., fix, sat
        ET.SubElement(pt, f"{g}ele").text = f"{p.h_ellipsoid_m:.4f}"
        ET.SubElement(pt, f"{g}time").text = gps_to_utc_iso(p.t_gps, leap_seconds)
        if p.quality in QUALITY_GPX_FIX:
            ET.SubElement(pt, f"{g}fix").text = QUALITY_GPX_FIX[p.quality]
        if p.n_sats is not None:
            ET.SubElement(pt, f"{g}sat").text = str(int(p.n_sats))
    return ET.ElementTree(gpx)


def write_kml(path, points, name: str, *, leap_seconds: int | None = None) -> None:
    kml_document(list(points), name, leap_seconds=leap_seconds).write(path, encoding="utf-8", xml_declaration=True)


def write_gpx(path, points, name: str, *, leap_seconds: int | None = None) -> None:
    gpx_document(list(points), name, leap_seconds=leap_seconds).write(path, encoding="utf-8", xml_declaration=True)


def write_solution_files(solutions, *, name: str, pos=None, kml=None, gpx=None, inputs=(),
                         options: dict | None = None, leap_seconds: int | None = None) -> int:
    """Fused solutions (:class:`companion.messages.NavSolution`) to any of RTKLIB .pos, KML and
    GPX, the same epochs in each ('init' and non-finite ones left out; Q from the RTK fix state,
    :func:`companion.gnss.pos_format.pos_records_from_nav_solutions`).  Returns the epoch count."""
    from ..gnss.pos_format import pos_records_from_nav_solutions, write_pos
    records = pos_records_from_nav_solutions(solutions)
    if pos:
        write_pos(pos, records, program=name, inputs=inputs, options=options)
    if kml or gpx:
        points = points_from_pos_records(records)
        if kml:
            write_kml(kml, points, name, leap_seconds=leap_seconds)
        if gpx:
            write_gpx(gpx, points, name, leap_seconds=leap_seconds)
    return len(records)


__all__ = ["TrackPoint", "write_solution_files", "gps_minus_utc_s", "gps_to_utc_iso", "points_from_ecef",
           "points_from_pos_records", "kml_document", "gpx_document", "write_kml", "write_gpx"]
