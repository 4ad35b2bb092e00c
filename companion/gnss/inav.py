"""Galileo I/NAV (E1-B and E5b-I) ephemeris, clock, group delays and health from word types 1-5
(Galileo OS SIS ICD issue 2.1, 4.3.5 and 5.1).

Input is one u-blox RXM-SFRBX page pair: eight 32-bit words, read MSB first, words 1-4 the even
page part and words 5-8 the odd part.  Bit offsets below are from the start of the even part:

* even part: even/odd flag (0, must be 0), page type (1, 1 = alert page), data 1..112 (2-113);
* odd part (offset 128): even/odd (must be 1), page type, data 113..128 (130-145), reserved 1, SAR,
  spare, then the CRC-24Q (odd bits 82-105) over the even part's first 114 bits and the odd
  part's first 82 bits (ICD 4.3.2.3).  The tails are not part of the CRC.

Verified on a real ZED-F9P log: every E1-B and E5b page passes the CRC with this layout.  The
128 data bits form one *word*: word type (6 bits) then the word's fields (ICD table 40).  E1-B and
E5b carry the same words (in a different order), so pages of both signals fill one set per
satellite.

Conventions are those of :class:`~companion.messages.GpsEphemeris` and of the RTCM 1046 decoder
(:func:`companion.io.rtcm_eph.galileo_ephemeris`): I/NAV clock with ``tgd_s`` = BGD(E1,E5b),
``tgd2_s`` 0, ``iode`` = ``iodc`` = IODnav, ``health`` the RINEX 3 bit field (E1-B DVS bit 0, HS
bits 1-2, E5b DVS bit 6, HS bits 7-8), ``ura_m`` from SISA, ``week`` = GST week + 1024 placed
so that toe is within half a week of the word-5 transmission time.
"""
from __future__ import annotations

from pyrtcm import calc_crc24q

from ..io.rtcm_eph import FIT_INTERVAL_GALILEO_H, PI_ICD, galileo_sisa_m
from ..messages import SYSTEM_WEEK_TO_GPS_WEEK, GpsEphemeris
from .lnav import new_ephemeris, toc_near_toe, week_of_toe

#: ephemeris words (1-4 carry IODnav) and the clock/health word 5
EPHEMERIS_WORDS = (1, 2, 3, 4, 5)
_SC = PI_ICD


class _Bits:
    """Unsigned/signed fields of a big-endian bit string held in an int of ``n`` bits."""

    __slots__ = ("v", "n")

    def __init__(self, v: int, n: int):
        self.v, self.n = v, n

    def u(self, start: int, length: int) -> int:
        return (self.v >> (self.n - start - length)) & ((1 << length) - 1)

    def s(self, start: int, length: int) -> int:
        x = self.u(start, length)
        return x - (1 << length) if x >> (length - 1) else x


def parse_page(words) -> tuple[int, int] | str:
    """(word type, 128-bit data word) of one u-blox I/NAV page pair, or the reason it is not
    usable: 'length', 'even_odd', 'alert', 'crc'."""
    if len(words) != 8:
        return "length"
    v = 0
    for w in words:
        v = (v << 32) | (int(w) & 0xFFFFFFFF)
    page = _Bits(v, 256)
    if page.u(0, 1) != 0 or page.u(128, 1) != 1:
        return "even_odd"
    if page.u(1, 1) or page.u(129, 1):
        return "alert"
    protected = (page.u(0, 114) << 82) | page.u(128, 82)          # 196 bits, 4 zero bits in front
    if calc_crc24q(protected.to_bytes(25, "big")) != page.u(128 + 82, 24):
        return "crc"
    data = (page.u(2, 112) << 16) | page.u(130, 16)
    return data >> 122, data


def decode_ephemeris(sat: str, words: dict[int, int]) -> GpsEphemeris:
    """Ephemeris from the 128-bit data words of types 1-5 (IODnav consistency is the caller's)."""
    w1, w2, w3, w4, w5 = (_Bits(words[k], 128) for k in EPHEMERIS_WORDS)
    toe = w1.u(16, 14) * 60.0
    m0 = w1.s(30, 32) * 2.0 ** -31 * _SC
    e = w1.u(62, 32) * 2.0 ** -33
    sqrt_a = w1.u(94, 32) * 2.0 ** -19
    omega0 = w2.s(16, 32) * 2.0 ** -31 * _SC
    i0 = w2.s(48, 32) * 2.0 ** -31 * _SC
    omega = w2.s(80, 32) * 2.0 ** -31 * _SC
    idot = w2.s(112, 14) * 2.0 ** -43 * _SC
    omega_dot = w3.s(16, 24) * 2.0 ** -43 * _SC
    delta_n = w3.s(40, 16) * 2.0 ** -43 * _SC
    cuc, cus = w3.s(56, 16) * 2.0 ** -29, w3.s(72, 16) * 2.0 ** -29
    crc, crs = w3.s(88, 16) * 2.0 ** -5, w3.s(104, 16) * 2.0 ** -5
    sisa = w3.u(120, 8)
    cic, cis = w4.s(22, 16) * 2.0 ** -29, w4.s(38, 16) * 2.0 ** -29
    toc = w4.u(54, 14) * 60.0
    af0 = w4.s(68, 31) * 2.0 ** -34
    af1 = w4.s(99, 21) * 2.0 ** -46
    af2 = w4.s(120, 6) * 2.0 ** -59
    bgd_e1e5b = w5.s(57, 10) * 2.0 ** -32
    e5b_hs, e1b_hs = w5.u(67, 2), w5.u(69, 2)
    e5b_dvs, e1b_dvs = w5.u(71, 1), w5.u(72, 1)
    wn_gst, tow = w5.u(73, 12), w5.u(85, 20)
    week = week_of_toe(wn_gst, toe, tow)
    toc_s = toc_near_toe(toc, toe)
    iod = w1.u(6, 10)
    return GpsEphemeris(
        sat=sat, week=week + SYSTEM_WEEK_TO_GPS_WEEK["E"], toe_s=toe, toc_s=toc_s, sqrt_a=sqrt_a, e=e,
        i0_rad=i0, omega0_rad=omega0, omega_rad=omega, m0_rad=m0, delta_n_radps=delta_n,
        idot_radps=idot, omega_dot_radps=omega_dot, cuc_rad=cuc, cus_rad=cus, crc_m=crc, crs_m=crs,
        cic_rad=cic, cis_rad=cis, af0_s=af0, af1_sps=af1, af2_sps2=af2, tgd_s=bgd_e1e5b, iode=iod,
        iodc=iod, health=(e5b_hs << 7) | (e5b_dvs << 6) | (e1b_hs << 1) | e1b_dvs,
        ura_m=galileo_sisa_m(sisa), fit_interval_h=FIT_INTERVAL_GALILEO_H)


def decode_nequick(word5: int) -> tuple[float, float, float]:
    """NeQuick G effective-ionisation coefficients (ai0 sfu, ai1 sfu/deg, ai2 sfu/deg^2) of word 5."""
    w = _Bits(word5, 128)
    return w.u(6, 11) * 2.0 ** -2, w.s(17, 11) * 2.0 ** -8, w.s(28, 14) * 2.0 ** -15


class InavEphemerisAssembler:
    """Collects word types 1-5 per satellite (from E1-B and E5b pages alike); ``add`` returns a
    :class:`GpsEphemeris` once per new consistent set (IODnav of words 1-4 equal, word 4's SVID
    the satellite's), else None.  Rejections are counted in ``counters``."""

    def __init__(self):
        self._words: dict[str, dict[int, int]] = {}
        self._last: dict[str, tuple[int, float, int]] = {}
        self.counters: dict[str, int] = {k: 0 for k in ("pages", "length", "even_odd", "alert", "crc",
                                                        "inconsistent", "svid", "ephemerides")}
        self.nequick: tuple[float, float, float] | None = None     # latest ai0, ai1, ai2

    def add(self, sat: str, words) -> GpsEphemeris | None:
        page = parse_page(words)
        if isinstance(page, str):
            self.counters[page] += 1
            return None
        self.counters["pages"] += 1
        word_type, data = page
        if word_type not in EPHEMERIS_WORDS:
            return None
        if word_type == 5:
            self.nequick = decode_nequick(data)
        store = self._words.setdefault(sat, {})
        store[word_type] = data
        if len(store) < len(EPHEMERIS_WORDS):
            return None
        iods = {_Bits(store[k], 128).u(6, 10) for k in (1, 2, 3, 4)}
        if len(iods) != 1:
            self.counters["inconsistent"] += 1      # a set straddling an update: wait for the rest
            return None
        if _Bits(store[4], 128).u(16, 6) != int(sat[1:]):
            self.counters["svid"] += 1
            del store[4]
            return None
        return new_ephemeris(decode_ephemeris(sat, store), self._last, self.counters)
