"""Broadcast ephemeris store: deduplication and per-epoch selection.

Selection rule (deterministic): among the satellite's ephemerides whose fit interval covers
``t_gps`` (|t - toe| <= fit_interval/2, at least :data:`MIN_FIT_INTERVAL_H` of its system: Galileo
and BeiDou ephemerides decoded from a stream carry no fit interval), take the one with the nearest toe; ties go to the later
toe, then the higher IODE.  Unhealthy ephemerides (health != 0) are never returned.
"""
from __future__ import annotations

from collections import Counter
from typing import Iterable

from ..messages import GpsEphemeris

#: extra margin beyond half the fit interval, s (0 = strict IS-GPS-200 fit interval)
FIT_MARGIN_S = 0.0
#: shortest validity per system, h (RTKLIB's MAXDTOE_GAL 4 h and MAXDTOE_CMP 6 h either side of toe);
#: GPS and QZSS use their broadcast fit interval (4 h standard)
MIN_FIT_INTERVAL_H = {"E": 8.0, "C": 12.0}


class EphemerisStore:
    """Holds GPS, Galileo, BeiDou and QZSS ephemerides by satellite; counts rejected additions and failed selections."""

    def __init__(self, ephemerides: Iterable[GpsEphemeris] = ()):
        self._by_sat: dict[str, list[GpsEphemeris]] = {}
        self.rejections: Counter = Counter()   # reason -> count
        for e in ephemerides:
            self.add(e)

    def add(self, eph: GpsEphemeris) -> bool:
        """Add an ephemeris; False (and counted as 'duplicate') if sat+IODE+toe is already held."""
        lst = self._by_sat.setdefault(eph.sat, [])
        t_oe = eph.t_oe_gps
        for e in lst:
            if e.iode == eph.iode and e.t_oe_gps == t_oe:
                self.rejections["duplicate"] += 1
                return False
        lst.append(eph)
        lst.sort(key=lambda e: (e.t_oe_gps, e.iode))
        return True

    def __len__(self) -> int:
        return sum(len(v) for v in self._by_sat.values())

    @property
    def sats(self) -> list[str]:
        return sorted(self._by_sat)

    def all(self, sat: str) -> list[GpsEphemeris]:
        return list(self._by_sat.get(sat, ()))

    def select_with_reason(self, sat: str, t_gps: float, iode: int | None = None
                           ) -> tuple[GpsEphemeris | None, str]:
        """(ephemeris, '') or (None, reason) with reason in 'no ephemeris', 'unhealthy',
        'outside fit interval'.  With ``iode`` only that issue of data is considered."""
        lst = self._by_sat.get(sat)
        if not lst:
            return None, "no ephemeris"
        best = None
        best_key = None
        unhealthy = False
        for e in lst:
            if iode is not None and e.iode != iode:
                continue
            dt = abs(t_gps - e.t_oe_gps)
            if dt > max(e.fit_interval_h, MIN_FIT_INTERVAL_H.get(sat[0], 0.0)) * 1800.0 + FIT_MARGIN_S:
                continue
            if e.health != 0:
                unhealthy = True
                continue
            key = (dt, -e.t_oe_gps, -e.iode)
            if best_key is None or key < best_key:
                best, best_key = e, key
        if best is not None:
            return best, ""
        reason = "unhealthy" if unhealthy else ("no ephemeris" if iode is not None else "outside fit interval")
        return None, reason

    def select(self, sat: str, t_gps: float, iode: int | None = None) -> GpsEphemeris | None:
        """Best healthy ephemeris for ``sat`` at ``t_gps`` or None (the reason is counted)."""
        eph, reason = self.select_with_reason(sat, t_gps, iode)
        if eph is None:
            self.rejections[reason] += 1
        return eph
