"""NMEA 0183 output of the fused solution (GGA, RMC, GST), built by pynmeagps, to UDP or a serial port.

For a ground station, a logger, a second autopilot port or anything that takes a GPS: the same
injection rule as the MAVLink outputs holds.  A solution the service would not inject goes out
as *no fix* (GGA quality 0 and no position, RMC status V), never as a position.

* **GGA** quality: 1 GPS, 2 differential (base corrections reaching the filter), 4 RTK fixed,
  5 RTK float (from ``extras['rtk_fix']``), 6 estimated (coasting on the INS); altitude above
  mean sea level = ellipsoidal height - ``geoid_undulation_m``, with that separation; HDOP is left
  empty (the filter has no DOP; its accuracy is in GST).
* **RMC**: speed over ground (knots) and course from the NED velocity, mode D/A/E/R/F.
* **GST**: the horizontal error ellipse from the filter's sigmas (north/east are the axes of its
  diagonal), latitude/longitude/altitude 1-sigma in metres.

Times are UTC: GPS time minus ``leap_seconds``.  Latitude and longitude carry 7 decimals of a
minute (pynmeagps' high-precision mode: 0.2 mm) so an RTK solution is not rounded to 2 cm.
"""
from __future__ import annotations

import logging
import math
import socket
from datetime import timedelta

import numpy as np

from ..messages import NavSolution
from ..nav.earth import C_n_e, ecef_to_geodetic

log = logging.getLogger(__name__)
KNOTS_PER_MPS = 3600.0 / 1852.0


def _utc(t_gps: float, leap_seconds: int):
    from ..gnss.pos_format import GPS_EPOCH
    return GPS_EPOCH + timedelta(seconds=round(t_gps - leap_seconds, 2))


def gga_quality(sol: NavSolution, differential: bool = False) -> int:
    """NMEA GGA fix quality of a solution (0 when it must not be used); ``differential``: base
    corrections are reaching the filter."""
    x = sol.extras
    if not x.get("inject") or sol.status not in ("nav", "coasting"):
        return 0
    if sol.status == "coasting":
        return 6
    fix = sol.fix_state if sol.fix_state != "none" else x.get("rtk_fix")   # the filter's RTK state
    if fix == "fixed":
        return 4
    if fix == "float":
        return 5
    return 2 if differential else 1


_RMC_MODE = {0: "N", 1: "A", 2: "D", 4: "R", 5: "F", 6: "E"}


def nmea_sentences(sol: NavSolution, *, leap_seconds: int, geoid_undulation_m: float = 0.0, talker: str = "GN",
                   sentences=("GGA", "RMC", "GST"), n_sats: int = 0, differential: bool = False) -> list[bytes]:
    """The requested sentences for one solution, serialized (with checksum and CRLF)."""
    from pynmeagps import GET, NMEAMessage
    t = _utc(sol.t_gps, leap_seconds)
    q = gga_quality(sol, differential)
    lat, lon, h = ecef_to_geodetic(np.asarray(sol.r_e, float))
    lat_d, lon_d = math.degrees(lat), math.degrees(lon)
    pos = {"lat": lat_d, "NS": "N" if lat_d >= 0 else "S", "lon": lon_d, "EW": "E" if lon_d >= 0 else "W"} \
        if q else {"lat": "", "NS": "", "lon": "", "EW": ""}
    out = []
    for name in sentences:
        if name == "GGA":
            kw = dict(time=t.time(), **pos, quality=q, numSV=int(n_sats), HDOP="",
                      alt=round(h - geoid_undulation_m, 4) if q else "", altUnit="M" if q else "",
                      sep=round(geoid_undulation_m, 3) if q else "", sepUnit="M" if q else "",
                      diffAge="", diffStation="")
        elif name == "RMC":
            v_n = C_n_e(lat, lon).T @ np.asarray(sol.v_e, float)
            spd = math.hypot(v_n[0], v_n[1])
            cog = math.degrees(math.atan2(v_n[1], v_n[0])) % 360.0
            kw = dict(time=t.time(), status="A" if q else "V", **pos,
                      spd=round(spd * KNOTS_PER_MPS, 3) if q else "", cog=round(cog, 2) if q and spd > 0.1 else "",
                      date=t.date(), mv="", mvEW="", posMode=_RMC_MODE.get(q, "N"), navStatus="V")
        elif name == "GST":
            if not q:
                continue
            sn, se, sd = (float(v) for v in sol.sigma_r_n_m)
            major, minor, orient = (sn, se, 0.0) if sn >= se else (se, sn, 90.0)
            kw = dict(time=t.time(), rangeRms="", stdMajor=round(major, 4), stdMinor=round(minor, 4),
                      orient=orient, stdLat=round(sn, 4), stdLong=round(se, 4), stdAlt=round(sd, 4))
        else:
            raise ValueError(f"NMEA sentence {name!r} not supported (GGA, RMC, GST)")
        out.append(NMEAMessage(talker, name, GET, hpnmeamode=True, **kw).serialize())
    return out


class NmeaSink:
    """Where the sentences go: ``udp:HOST:PORT`` (one datagram per epoch) or ``DEVICE,BAUD`` (serial)."""

    def __init__(self, destination: str):
        self.destination = destination
        self.counters = {"sentences": 0, "bytes": 0, "errors": 0}
        self._sock = self._serial = None
        if destination.startswith("udp:"):
            host, _, port = destination[4:].rpartition(":")
            self._addr = (host or "127.0.0.1", int(port))
            self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self._sock.setblocking(False)
        else:
            import serial
            dev, _, baud = destination.partition(",")
            self._serial = serial.Serial(dev, int(baud or 115200), timeout=0, write_timeout=0)

    def send(self, sentences: list[bytes]) -> None:
        data = b"".join(sentences)
        try:
            if self._sock is not None:
                self._sock.sendto(data, self._addr)
            else:
                self._serial.write(data)
        except (OSError, ValueError) as exc:       # a full buffer or a vanished port: counted, not fatal
            self.counters["errors"] += 1
            if self.counters["errors"] in (1, 10, 100, 1000):
                log.warning("NMEA output to %s failed (%s); %d failures", self.destination, exc,
                            self.counters["errors"])
            return
        self.counters["sentences"] += len(sentences)
        self.counters["bytes"] += len(data)

    def close(self) -> None:
        for h in (self._sock, self._serial):
            if h is not None:
                try:
                    h.close()
                except OSError:
                    pass


__all__ = ["nmea_sentences", "gga_quality", "NmeaSink"]
