"""GPS LNAV (L1 C/A legacy navigation message) subframe decoding, IS-GPS-200 20.3.2-20.3.3.

Input is one subframe as ten 30-bit words.  Each word is given right-aligned in an int whose bits
29..6 are the 24 data bits (IS-GPS-200 bits 1..24, MSB first) and bits 5..0 the six parity bits.
This is exactly how u-blox RXM-SFRBX ``dwrd`` presents GPS L1 C/A words; in addition u-blox puts
D29*/D30* (the last two parity bits of the previous word) in bits 31..30 and delivers the data bits
already de-inverted (source bits d1..d24).  :func:`word_parity_ok` checks the parity with that
convention (verified on a real ZED-F9P log: every L1 C/A word passes).

Ephemeris parameters and scale factors: IS-GPS-200 Table 20-I (subframe 1) and 20-III
(subframes 2 and 3).  Angles are converted from semicircles to radians.

:class:`LnavEphemerisAssembler` keeps subframes 1-3 per satellite and returns a
:class:`~companion.messages.GpsEphemeris` once a consistent set (IODC low 8 bits == IODE of
subframe 2 == IODE of subframe 3) is present.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..messages import SECONDS_PER_WEEK, GpsEphemeris

PREAMBLE = 0x8B
PI_GPS = 3.1415926535898          # the value of pi IS-GPS-200 prescribes for semicircle conversion

# URA index -> nominal URA (m), IS-GPS-200 20.3.3.3.1.3 (upper bound of each range).
URA_M = (2.4, 3.4, 4.85, 6.85, 9.65, 13.65, 24.0, 48.0, 96.0, 192.0, 384.0, 768.0, 1536.0,
         3072.0, 6144.0, 6144.0)

# Parity equations (IS-GPS-200 Table 20-XIV): for D25..D30, which previous bit (29/30) and
# which source data bits take part.
_PARITY = (
    (29, (1, 2, 3, 5, 6, 10, 11, 12, 13, 14, 17, 18, 20, 23)),
    (30, (2, 3, 4, 6, 7, 11, 12, 13, 14, 15, 18, 19, 21, 24)),
    (29, (1, 3, 4, 5, 7, 8, 12, 13, 14, 15, 16, 19, 20, 22)),
    (30, (2, 4, 5, 6, 8, 9, 13, 14, 15, 16, 17, 20, 21, 23)),
    (30, (1, 3, 5, 6, 7, 9, 10, 14, 15, 16, 17, 18, 21, 22, 24)),
    (29, (3, 5, 6, 8, 9, 10, 11, 13, 15, 19, 22, 23, 24)),
)
_PARITY_MASKS = tuple((prev, sum(1 << (24 - i) for i in bits)) for prev, bits in _PARITY)


def word_parity_ok(word: int) -> bool:
    """Parity check of one word in the u-blox SFRBX layout (see module docstring)."""
    d = (word >> 6) & 0xFFFFFF
    d29s = (word >> 31) & 1
    d30s = (word >> 30) & 1
    parity = 0
    for prev, mask in _PARITY_MASKS:
        bit = (d29s if prev == 29 else d30s) ^ (bin(d & mask).count("1") & 1)
        parity = (parity << 1) | bit
    return parity == (word & 0x3F)


class _Bits:
    """The 240 data bits of a subframe (24 per word, parity removed)."""

    def __init__(self, words: list[int] | tuple[int, ...]):
        v = 0
        for w in words:
            v = (v << 24) | ((w >> 6) & 0xFFFFFF)
        self.v = v

    def u(self, word: int, bit: int, n: int) -> int:
        """Unsigned field starting at IS-GPS-200 bit ``bit`` (1..24) of word ``word`` (1..10)."""
        start = (word - 1) * 24 + (bit - 1)
        return (self.v >> (240 - start - n)) & ((1 << n) - 1)

    def s(self, word: int, bit: int, n: int) -> int:
        x = self.u(word, bit, n)
        return x - (1 << n) if x & (1 << (n - 1)) else x

    def u_split(self, w1: int, b1: int, n1: int, w2: int, b2: int, n2: int) -> int:
        return (self.u(w1, b1, n1) << n2) | self.u(w2, b2, n2)

    def s_split(self, w1: int, b1: int, n1: int, w2: int, b2: int, n2: int) -> int:
        x = self.u_split(w1, b1, n1, w2, b2, n2)
        n = n1 + n2
        return x - (1 << n) if x & (1 << (n - 1)) else x


@dataclass(frozen=True, slots=True)
class Subframe:
    """Header of a decoded subframe plus its data-bit accessor."""

    subframe_id: int
    tow_next_s: int          # HOW TOW count * 6: GPS time of week at the start of the NEXT subframe
    bits: _Bits

    @property
    def tow_start_s(self) -> int:
        """Time of week at the start of this subframe."""
        return (self.tow_next_s - 6) % int(SECONDS_PER_WEEK)


def parse_subframe(words: list[int] | tuple[int, ...], check_parity: bool = True) -> Subframe | None:
    """Split off the TLM/HOW header; None if the preamble or (optionally) parity is wrong."""
    if len(words) != 10:
        return None
    if check_parity and not all(word_parity_ok(w) for w in words):
        return None
    bits = _Bits(words)
    if bits.u(1, 1, 8) != PREAMBLE:
        return None
    tow_count = bits.u(2, 1, 17)
    sfid = bits.u(2, 20, 3)
    return Subframe(subframe_id=sfid, tow_next_s=tow_count * 6, bits=bits)


def resolve_week(wn_mod: int, ref_week: int, modulus: int = 1024) -> int:
    """Full week number congruent to ``wn_mod`` (mod ``modulus``) nearest to ``ref_week``."""
    k = round((ref_week - wn_mod) / modulus)
    return wn_mod + k * modulus


def fit_interval_h(flag: int, iodc: int) -> float:
    if flag == 0:
        return 4.0
    # IS-GPS-200 Table 20-XII (fit interval flag 1): by IODC range
    if 240 <= iodc <= 247:
        return 8.0
    if 248 <= iodc <= 255 or iodc == 496:
        return 14.0
    if 497 <= iodc <= 503 or 1021 <= iodc <= 1023:
        return 26.0
    return 6.0


def qzss_fit_interval_h(flag: int) -> float:
    """QZSS LNAV fit interval flag: 0 = 2 h, 1 = more than 2 h (IS-QZSS-PNT 5.2.2.2.4), taken as 4 h
    as the RTCM 1044 decoder does."""
    return 4.0 if flag else 2.0


def week_of_toe(week: int, toe_s: float, t_tx_sow_s: float) -> int:
    """The week of toe: toe within half a week of the transmission time (week crossover)."""
    if toe_s - t_tx_sow_s < -SECONDS_PER_WEEK / 2:
        return week + 1
    if toe_s - t_tx_sow_s > SECONDS_PER_WEEK / 2:
        return week - 1
    return week


def toc_near_toe(toc_s: float, toe_s: float) -> float:
    """toc in toe's week (normally equal; one may sit across the week boundary)."""
    if toc_s - toe_s > SECONDS_PER_WEEK / 2:
        return toc_s - SECONDS_PER_WEEK
    if toc_s - toe_s < -SECONDS_PER_WEEK / 2:
        return toc_s + SECONDS_PER_WEEK
    return toc_s


def new_ephemeris(eph: GpsEphemeris, last: dict, counters) -> GpsEphemeris | None:
    """``eph`` the first time its (IODE, toe, week) is seen for its satellite, else None: a
    broadcast repeats the same set every 30 s.  ``last``: satellite -> key, kept by the caller."""
    key = (eph.iode, eph.toe_s, eph.week)
    if last.get(eph.sat) == key:
        return None
    last[eph.sat] = key
    counters["ephemerides"] += 1
    return eph


def decode_ephemeris(sat: str, sf1: Subframe, sf2: Subframe, sf3: Subframe, ref_week: int) -> GpsEphemeris:
    """Ephemeris from subframes 1, 2, 3 (consistency is the caller's job).  ``sat`` 'Jnn' (QZSS)
    selects the QZSS meaning of the fit interval flag.

    ``ref_week`` (a full GPS week near the transmission time) resolves the 10-bit week number;
    toe/toc are then placed within half a week of the subframe-1 transmission time, so the
    returned ``week`` is the week of toe (it can be the transmission week + 1 near a week end).
    """
    b1, b2, b3 = sf1.bits, sf2.bits, sf3.bits
    pi = PI_GPS
    wn = resolve_week(b1.u(3, 1, 10), ref_week)
    ura_index = b1.u(3, 13, 4)
    health = b1.u(3, 17, 6)
    iodc = b1.u_split(3, 23, 2, 8, 1, 8)
    tgd = b1.s(7, 17, 8) * 2.0 ** -31
    toc = b1.u(8, 9, 16) * 16.0
    af2 = b1.s(9, 1, 8) * 2.0 ** -55
    af1 = b1.s(9, 9, 16) * 2.0 ** -43
    af0 = b1.s(10, 1, 22) * 2.0 ** -31

    iode = b2.u(3, 1, 8)
    crs = b2.s(3, 9, 16) * 2.0 ** -5
    delta_n = b2.s(4, 1, 16) * 2.0 ** -43 * pi
    m0 = b2.s_split(4, 17, 8, 5, 1, 24) * 2.0 ** -31 * pi
    cuc = b2.s(6, 1, 16) * 2.0 ** -29
    e = b2.u_split(6, 17, 8, 7, 1, 24) * 2.0 ** -33
    cus = b2.s(8, 1, 16) * 2.0 ** -29
    sqrt_a = b2.u_split(8, 17, 8, 9, 1, 24) * 2.0 ** -19
    toe = b2.u(10, 1, 16) * 16.0
    fit_flag = b2.u(10, 17, 1)

    cic = b3.s(3, 1, 16) * 2.0 ** -29
    omega0 = b3.s_split(3, 17, 8, 4, 1, 24) * 2.0 ** -31 * pi
    cis = b3.s(5, 1, 16) * 2.0 ** -29
    i0 = b3.s_split(5, 17, 8, 6, 1, 24) * 2.0 ** -31 * pi
    crc = b3.s(7, 1, 16) * 2.0 ** -5
    omega = b3.s_split(7, 17, 8, 8, 1, 24) * 2.0 ** -31 * pi
    omega_dot = b3.s(9, 1, 24) * 2.0 ** -43 * pi
    idot = b3.s(10, 9, 14) * 2.0 ** -43 * pi

    week_toe = week_of_toe(wn, toe, sf1.tow_start_s)
    toc_s = toc_near_toe(toc, toe)
    return GpsEphemeris(
        sat=sat, week=int(week_toe), toe_s=toe, toc_s=toc_s, sqrt_a=sqrt_a, e=e, i0_rad=i0,
        omega0_rad=omega0, omega_rad=omega, m0_rad=m0, delta_n_radps=delta_n, idot_radps=idot,
        omega_dot_radps=omega_dot, cuc_rad=cuc, cus_rad=cus, crc_m=crc, crs_m=crs, cic_rad=cic,
        cis_rad=cis, af0_s=af0, af1_sps=af1, af2_sps2=af2, tgd_s=tgd, iode=iode, iodc=iodc,
        health=health, ura_m=URA_M[ura_index],
        fit_interval_h=qzss_fit_interval_h(fit_flag) if sat[0] == "J" else fit_interval_h(fit_flag, iodc))


KLOBUCHAR_PAGE_SV_ID = 56      # subframe 4 page 18: ionospheric and UTC parameters


def decode_klobuchar(sf4: Subframe) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
    """Klobuchar coefficients from subframe 4 page 18 (IS-GPS-200 20.3.3.5.1.7, Table 20-X), or
    None for any other subframe/page.  Returns (alpha[4], beta[4]) in the broadcast units (s,
    s/semicircle^n), as :func:`companion.gnss.atmosphere.klobuchar_delay_m` and the RINEX header
    reader give them.  Word 3: data ID (2 bits), SV (page) ID (6), alpha0, alpha1; word 4: alpha2,
    alpha3, beta0; word 5: beta1, beta2, beta3 (8-bit two's complement each)."""
    if sf4.subframe_id != 4 or sf4.bits.u(3, 3, 6) != KLOBUCHAR_PAGE_SV_ID:
        return None
    b = sf4.bits
    alpha = (b.s(3, 9, 8) * 2.0 ** -30, b.s(3, 17, 8) * 2.0 ** -27, b.s(4, 1, 8) * 2.0 ** -24,
             b.s(4, 9, 8) * 2.0 ** -24)
    beta = (b.s(4, 17, 8) * 2.0 ** 11, b.s(5, 1, 8) * 2.0 ** 14, b.s(5, 9, 8) * 2.0 ** 16,
            b.s(5, 17, 8) * 2.0 ** 16)
    return alpha, beta


class LnavEphemerisAssembler:
    """Collects subframes 1-3 per satellite; yields an ephemeris once per new consistent set.

    ``add`` returns the new :class:`GpsEphemeris` when the set completes with an issue of data
    (IODE, toe) different from the last one returned for that satellite, else None.  Counters
    (``parity``, ``preamble``, ``inconsistent``) record what was rejected.
    """

    def __init__(self, check_parity: bool = True):
        self.check_parity = check_parity
        self._sf: dict[str, dict[int, Subframe]] = {}
        self._last: dict[str, tuple[int, float, int]] = {}
        self.counters: dict[str, int] = {"parity": 0, "preamble": 0, "inconsistent": 0,
                                         "subframes": 0, "ephemerides": 0, "klobuchar": 0}
        self.klobuchar: tuple | None = None     # (alpha[4], beta[4]) from subframe 4 page 18

    def add(self, sat: str, words, ref_week: int) -> GpsEphemeris | None:
        if self.check_parity and not all(word_parity_ok(w) for w in words):
            self.counters["parity"] += 1
            return None
        sf = parse_subframe(words, check_parity=False)
        if sf is None:
            self.counters["preamble"] += 1
            return None
        self.counters["subframes"] += 1
        if sf.subframe_id == 4:
            klob = decode_klobuchar(sf)
            if klob is not None:
                if klob != self.klobuchar:
                    self.counters["klobuchar"] += 1
                self.klobuchar = klob         # the latest broadcast set (same for all satellites)
            return None
        if sf.subframe_id not in (1, 2, 3):
            return None
        store = self._sf.setdefault(sat, {})
        store[sf.subframe_id] = sf
        if len(store) < 3 or not all(k in store for k in (1, 2, 3)):
            return None
        s1, s2, s3 = store[1], store[2], store[3]
        iodc_lsb = s1.bits.u(8, 1, 8)
        iode2 = s2.bits.u(3, 1, 8)
        iode3 = s3.bits.u(10, 1, 8)
        if not (iodc_lsb == iode2 == iode3):
            # a set straddling an ephemeris cut-over: wait for the next subframes
            self.counters["inconsistent"] += 1
            return None
        return new_ephemeris(decode_ephemeris(sat, s1, s2, s3, ref_week), self._last, self.counters)

