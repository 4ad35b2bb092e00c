"""BeiDou B1I/B2I navigation messages D1 (MEO/IGSO: subframes 1-3) and D2 (GEO: pages 1-10 of
subframe 1) -> ephemeris and clock (BeiDou SIS ICD B1I 3.0, 5.2 and 5.3).

Input is one u-blox RXM-SFRBX subframe: ten words whose bits 29..0 are the 30 broadcast bits of
a word, MSB first, **parity included** and already de-interleaved: word 1 is 15 unprotected bits
(preamble, spare, FraID, SOW MSBs) then one BCH(15,11) codeword; words 2-10 are 11 + 11
information bits then the 4 + 4 parity bits of the two codewords.  Verified on a real ZED-F9P log
(every B1I and B2I word passes the BCH check, preamble 0x712).  Field positions below are bit
offsets from the start of the 300-bit subframe (ICD bit number - 1), so a field crossing a word
skips the parity bits; each field is a list of (subframe or page, offset, length) parts, MSB first.

Conventions are those of :class:`~companion.messages.GpsEphemeris` and of the RTCM 1042 decoder
(:func:`companion.io.rtcm_eph.beidou_ephemeris`): times of week in BDT, ``week`` = BDT week + 1356
(the week of toe, toe within half a week of subframe 1 / page 1), clock referred to B3I with
``tgd_s`` = TGD1 (B1I) and ``tgd2_s`` = TGD2 (B2I), ``iode`` = AODE, ``iodc`` = AODC, ``health`` =
SatH1, ``ura_m`` from URAI as GPS's.
"""
from __future__ import annotations

from ..io.rtcm_eph import FIT_INTERVAL_BEIDOU_H, PI_ICD
from ..messages import SECONDS_PER_WEEK, SYSTEM_WEEK_TO_GPS_WEEK, GpsEphemeris
from .ephemeris import is_beidou_geo
from .lnav import URA_M, new_ephemeris, toc_near_toe, week_of_toe

PREAMBLE = 0x712
_SC = PI_ICD

# D1: (subframe, offset, length) parts; D2: (page of subframe 1, offset, length)
_D1 = {
    "health": ((1, 42, 1),), "aodc": ((1, 43, 5),), "urai": ((1, 48, 4),), "week": ((1, 60, 13),),
    "toc": ((1, 73, 9), (1, 90, 8)), "tgd1": ((1, 98, 10),), "tgd2": ((1, 108, 4), (1, 120, 6)),
    "af2": ((1, 214, 11),), "af0": ((1, 225, 7), (1, 240, 17)), "af1": ((1, 257, 5), (1, 270, 17)),
    "aode": ((1, 287, 5),),
    "dn": ((2, 42, 10), (2, 60, 6)), "cuc": ((2, 66, 16), (2, 90, 2)), "m0": ((2, 92, 20), (2, 120, 12)),
    "e": ((2, 132, 10), (2, 150, 22)), "cus": ((2, 180, 18),), "crc": ((2, 198, 4), (2, 210, 14)),
    "crs": ((2, 224, 8), (2, 240, 10)), "sqrt_a": ((2, 250, 12), (2, 270, 20)),
    "toe": ((2, 290, 2), (3, 42, 10), (3, 60, 5)),
    "i0": ((3, 65, 17), (3, 90, 15)), "cic": ((3, 105, 7), (3, 120, 11)),
    "omega_dot": ((3, 131, 11), (3, 150, 13)), "cis": ((3, 163, 9), (3, 180, 9)),
    "idot": ((3, 189, 13), (3, 210, 1)), "omega0": ((3, 211, 21), (3, 240, 11)),
    "omega": ((3, 251, 11), (3, 270, 21)),
}
_D2 = {
    "health": ((1, 46, 1),), "aodc": ((1, 47, 5),), "urai": ((1, 60, 4),), "week": ((1, 64, 13),),
    "toc": ((1, 77, 5), (1, 90, 12)), "tgd1": ((1, 102, 10),), "tgd2": ((1, 120, 10),),
    "af0": ((3, 100, 12), (3, 120, 12)), "af1": ((3, 132, 4), (4, 46, 6), (4, 60, 12)),
    "af2": ((4, 72, 10), (4, 90, 1)), "aode": ((4, 91, 5),), "dn": ((4, 96, 16),),
    "cuc": ((4, 120, 14), (5, 46, 4)), "m0": ((5, 50, 2), (5, 60, 22), (5, 90, 8)),
    "cus": ((5, 98, 14), (5, 120, 4)), "e": ((5, 124, 10), (6, 46, 6), (6, 60, 16)),
    "sqrt_a": ((6, 76, 6), (6, 90, 22), (6, 120, 4)), "cic": ((6, 124, 10), (7, 46, 6), (7, 60, 2)),
    "cis": ((7, 62, 18),), "toe": ((7, 80, 2), (7, 90, 15)), "i0": ((7, 105, 7), (7, 120, 14), (8, 46, 6), (8, 60, 5)),
    "crc": ((8, 65, 17), (8, 90, 1)), "crs": ((8, 91, 18),),
    "omega_dot": ((8, 109, 3), (8, 120, 16), (9, 46, 5)), "omega0": ((9, 51, 1), (9, 60, 22), (9, 90, 9)),
    "omega": ((9, 99, 13), (9, 120, 14), (10, 46, 5)), "idot": ((10, 51, 1), (10, 60, 13)),
}
#: unsigned fields (the rest are two's complement)
_UNSIGNED = {"health", "aodc", "urai", "week", "toc", "aode", "e", "sqrt_a", "toe"}
#: D2 pages holding the ephemeris (page 2 is the ionosphere)
D2_PAGES = (1, 3, 4, 5, 6, 7, 8, 9, 10)


def _bch15_ok(codeword: int) -> bool:
    """BCH(15,11,1) codeword (11 information bits then 4 parity bits), g(x) = x^4 + x + 1."""
    r = codeword
    for i in range(14, 3, -1):
        if (r >> i) & 1:
            r ^= 0b10011 << (i - 4)
    return r == 0


def parity_ok(words) -> bool:
    """BCH check of a subframe in the u-blox layout (see module docstring)."""
    if not _bch15_ok(words[0] & 0x7FFF):
        return False
    for w in words[1:]:
        if not (_bch15_ok((((w >> 19) & 0x7FF) << 4) | ((w >> 4) & 0xF))
                and _bch15_ok((((w >> 8) & 0x7FF) << 4) | (w & 0xF))):
            return False
    return True


class Subframe:
    """The 300 bits of one subframe (parity in place) and its header."""

    __slots__ = ("v", "fra_id", "sow", "page")

    def __init__(self, words):
        v = 0
        for w in words:
            v = (v << 30) | (int(w) & 0x3FFFFFFF)
        self.v = v
        self.fra_id = self.u(15, 3)
        self.sow = (self.u(18, 8) << 12) | self.u(30, 12)
        self.page = self.u(42, 4)             # D2 subframe 1 page number (meaningless for D1)

    def u(self, start: int, length: int) -> int:
        return (self.v >> (300 - start - length)) & ((1 << length) - 1)


def _fields(table: dict, parts_of: dict[int, Subframe]) -> dict[str, int]:
    out = {}
    for name, parts in table.items():
        x, n = 0, 0
        for key, start, length in parts:
            x = (x << length) | parts_of[key].u(start, length)
            n += length
        if name not in _UNSIGNED and x >> (n - 1):
            x -= 1 << n
        out[name] = x
    return out


def decode_ephemeris(sat: str, parts_of: dict[int, Subframe], geo: bool) -> GpsEphemeris:
    """Ephemeris from D1 subframes 1-3 (``geo`` False) or D2 pages 1, 3-10 (``geo`` True)."""
    f = _fields(_D2 if geo else _D1, parts_of)
    sow1 = parts_of[1].sow
    toe = f["toe"] * 8.0
    toc = f["toc"] * 8.0
    week = week_of_toe(f["week"], toe, sow1)
    toc_s = toc_near_toe(toc, toe)
    return GpsEphemeris(
        sat=sat, week=week + SYSTEM_WEEK_TO_GPS_WEEK["C"], toe_s=toe, toc_s=toc_s,
        sqrt_a=f["sqrt_a"] * 2.0 ** -19, e=f["e"] * 2.0 ** -33, i0_rad=f["i0"] * 2.0 ** -31 * _SC,
        omega0_rad=f["omega0"] * 2.0 ** -31 * _SC, omega_rad=f["omega"] * 2.0 ** -31 * _SC,
        m0_rad=f["m0"] * 2.0 ** -31 * _SC, delta_n_radps=f["dn"] * 2.0 ** -43 * _SC,
        idot_radps=f["idot"] * 2.0 ** -43 * _SC, omega_dot_radps=f["omega_dot"] * 2.0 ** -43 * _SC,
        cuc_rad=f["cuc"] * 2.0 ** -31, cus_rad=f["cus"] * 2.0 ** -31, crc_m=f["crc"] * 2.0 ** -6,
        crs_m=f["crs"] * 2.0 ** -6, cic_rad=f["cic"] * 2.0 ** -31, cis_rad=f["cis"] * 2.0 ** -31,
        af0_s=f["af0"] * 2.0 ** -33, af1_sps=f["af1"] * 2.0 ** -50, af2_sps2=f["af2"] * 2.0 ** -66,
        tgd_s=f["tgd1"] * 0.1e-9, tgd2_s=f["tgd2"] * 0.1e-9, iode=f["aode"], iodc=f["aodc"],
        health=f["health"], ura_m=URA_M[f["urai"]], fit_interval_h=FIT_INTERVAL_BEIDOU_H)


def _sow_step(a: int, b: int) -> int:
    """b - a in seconds of week, across the week end."""
    return (b - a) % int(SECONDS_PER_WEEK)


class BeidouEphemerisAssembler:
    """Collects D1 subframes 1-3 (MEO/IGSO) or D2 subframe-1 pages (GEO) per satellite; ``add``
    returns a :class:`GpsEphemeris` once per new consistent set, else None.  A set is consistent
    when its parts come from one frame: D1 subframes 6 s apart, D2 pages 3 s apart (their SOWs).
    B1I and B2I carry the same message and fill the same set.  ``geo``: D2 if True; None = from
    the satellite id (:func:`companion.gnss.ephemeris.is_beidou_geo`)."""

    def __init__(self, check_parity: bool = True):
        self.check_parity = check_parity
        self._parts: dict[str, dict[int, Subframe]] = {}
        self._last: dict[str, tuple[int, float, int]] = {}
        self.counters: dict[str, int] = {k: 0 for k in ("subframes", "length", "parity", "preamble",
                                                        "inconsistent", "ephemerides")}

    def add(self, sat: str, words, geo: bool | None = None) -> GpsEphemeris | None:
        if len(words) != 10:
            self.counters["length"] += 1
            return None
        if self.check_parity and not parity_ok(words):
            self.counters["parity"] += 1
            return None
        sf = Subframe(words)
        if (words[0] >> 19) & 0x7FF != PREAMBLE or not 1 <= sf.fra_id <= 5:
            self.counters["preamble"] += 1
            return None
        self.counters["subframes"] += 1
        geo = is_beidou_geo(sat) if geo is None else geo
        store = self._parts.setdefault(sat, {})
        if geo:
            if sf.fra_id != 1 or sf.page not in D2_PAGES:
                return None
            store[sf.page] = sf
            need, step = D2_PAGES, 3
        else:
            if sf.fra_id not in (1, 2, 3):
                return None
            store[sf.fra_id] = sf
            need, step = (1, 2, 3), 6
        if not all(k in store for k in need):
            return None
        sow1 = store[1].sow
        if any(_sow_step(sow1, store[k].sow) != step * (k - 1) for k in need):
            self.counters["inconsistent"] += 1          # parts of different frames: wait
            return None
        return new_ephemeris(decode_ephemeris(sat, store, geo), self._last, self.counters)
