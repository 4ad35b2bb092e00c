"""Broadcast ephemeris store: deduplication and per-epoch selection.

Selection rule (deterministic): among the satellite's ephemerides whose fit interval covers
``t_gps`` (|t - toe| <= fit_interval/2, at least :data:`MIN_FIT_INTERVAL_H` of its system: Galileo
and BeiDou ephemerides decoded from a stream carry no fit interval), take the one with the nearest toe; ties go to the later
toe, then the higher IODE.  Unhealthy ephemerides (:func:`reports_unhealthy`) are never returned.

Selections are remembered per (satellite, time, IODE) until the next ephemeris is added: the rover
and the base epoch of the same second ask the same questions (and re-preparing an epoch asks them
again).  A remembered answer is the one the rule gives, so it cannot change a result; the memory is
bounded (:data:`MAX_REMEMBERED_SELECTIONS`, cleared when full).
"""
from __future__ import annotations

from collections import Counter
from typing import Iterable

from ..messages import GpsEphemeris
from .glonass import GlonassEphemeris
from .ephemeris import implausible as keplerian_implausible
from .glonass import implausible as glonass_implausible

#: extra margin beyond half the fit interval, s (0 = strict IS-GPS-200 fit interval)
FIT_MARGIN_S = 0.0
#: shortest validity per system, h (RTKLIB's MAXDTOE_GAL 4 h and MAXDTOE_CMP 6 h either side of toe);
#: GPS and QZSS use their broadcast fit interval (4 h standard)
MIN_FIT_INTERVAL_H = {"E": 8.0, "C": 12.0}
MAX_REMEMBERED_SELECTIONS = 1024


def reports_unhealthy(sat: str, health: int) -> bool:
    """Whether a broadcast health word takes the satellite out.  QZSS's LNAV health LSB flags L1C/B
    (formerly LEX), not the signals we use: every QZSS satellite broadcast 1 in 2024 while
    receivers tracked it normally (RTKLIB masks the bit too)."""
    if sat.startswith("J"):
        return (health & ~1) != 0
    return health != 0


class EphemerisStore:
    """Holds GPS, Galileo, BeiDou and QZSS ephemerides by satellite; counts rejected additions and failed selections."""

    def __init__(self, ephemerides: Iterable[GpsEphemeris] = ()):
        self._by_sat: dict[str, list[GpsEphemeris]] = {}
        # per satellite, beside _by_sat: (t_oe_gps, validity half-width s) of each ephemeris
        self._windows: dict[str, list[tuple[float, float]]] = {}
        self._selected: dict[tuple, tuple[GpsEphemeris | None, str]] = {}
        self.rejections: Counter = Counter()   # reason -> count
        for e in ephemerides:
            self.add(e)

    def add(self, eph: GpsEphemeris) -> bool:
        """Add an ephemeris; False (and counted as 'duplicate') if sat+IODE+toe is already held, or
        (counted as 'implausible orbit: <why>' / 'implausible GLONASS state: <why>') a record no
        satellite can have (:func:`.ephemeris.implausible`, :func:`.glonass.implausible`)."""
        why = glonass_implausible(eph) if isinstance(eph, GlonassEphemeris) else keplerian_implausible(eph)
        if why:
            kind = "GLONASS state" if isinstance(eph, GlonassEphemeris) else "orbit"
            self.rejections[f"implausible {kind}: {why}"] += 1
            return False
        lst = self._by_sat.setdefault(eph.sat, [])
        t_oe = eph.t_oe_gps
        for e in lst:
            if e.iode == eph.iode and e.t_oe_gps == t_oe:
                self.rejections["duplicate"] += 1
                return False
        lst.append(eph)
        lst.sort(key=lambda e: (e.t_oe_gps, e.iode))
        min_h = MIN_FIT_INTERVAL_H.get(eph.sat[0], 0.0)
        self._windows[eph.sat] = [(e.t_oe_gps, max(e.fit_interval_h, min_h) * 1800.0 + FIT_MARGIN_S) for e in lst]
        self._selected.clear()
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
        key = (sat, t_gps, iode)
        hit = self._selected.get(key)
        if hit is not None:
            return hit
        lst = self._by_sat.get(sat)
        if not lst:
            return None, "no ephemeris"
        best = None
        best_key = None
        unhealthy = False
        for e, (t_oe, half_s) in zip(lst, self._windows[sat]):
            if iode is not None and e.iode != iode:
                continue
            dt = abs(t_gps - t_oe)
            if dt > half_s:
                continue
            if reports_unhealthy(sat, e.health):
                unhealthy = True
                continue
            k = (dt, -t_oe, -e.iode)
            if best_key is None or k < best_key:
                best, best_key = e, k
        if best is not None:
            out = best, ""
        else:
            out = None, "unhealthy" if unhealthy else ("no ephemeris" if iode is not None else "outside fit interval")
        if len(self._selected) >= MAX_REMEMBERED_SELECTIONS:
            self._selected.clear()
        self._selected[key] = out
        return out

    def select(self, sat: str, t_gps: float, iode: int | None = None) -> GpsEphemeris | None:
        """Best healthy ephemeris for ``sat`` at ``t_gps`` or None (the reason is counted)."""
        eph, reason = self.select_with_reason(sat, t_gps, iode)
        if eph is None:
            self.rejections[reason] += 1
        return eph
