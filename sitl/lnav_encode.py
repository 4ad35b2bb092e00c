"""GPS LNAV subframes and u-blox RXM-SFRBX frames for the simulated receiver (the inverse of
:mod:`companion.gnss.lnav`, IS-GPS-200 20.3.2-20.3.3).

* :func:`ephemeris_subframe` builds subframe 1, 2 or 3 of a :class:`GpsEphemeris` (Tables 20-I and
  20-III, every field at its broadcast scale); :func:`klobuchar_subframe` subframe 4 page 18 (the
  ionospheric parameters, Table 20-X; the UTC fields of that page are left zero).
* Words come in the RXM-SFRBX ``dwrd`` layout the decoder reads: the 24 source data bits in bits
  29..6, the six parity bits (Table 20-XIV, computed with the previous word's D29/D30) in 5..0 and
  that previous D29/D30 in bits 31..30.  Bits 23-24 of words 2 and 10 are the "t" bits the
  satellite chooses so that D29 = D30 = 0, so every subframe starts from D29* = D30* = 0.
* :func:`quantised` is an ephemeris rounded to what LNAV can carry (encode, then decode with the
  companion's own decoder): the simulator uses those values, so the ephemeris the companion
  decodes from SFRBX is exactly the one the observations were made with.
* :func:`subframe_due` is the broadcast schedule: subframe ``((S / 6) mod 5) + 1`` is sent over
  ``[S, S + 6)`` of GPS time of week and a receiver outputs it when it is complete, at ``S + 6``.
  Of subframes 4 and 5 only page 18 of subframe 4 is simulated (sent in every subframe-4 slot,
  subframe 5 not at all): it is the page the companion decodes.
"""
from __future__ import annotations

import math

from companion.gnss.lnav import (_PARITY_MASKS, KLOBUCHAR_PAGE_SV_ID, PI_GPS, PREAMBLE, URA_M, LnavEphemerisAssembler,
                                 word_parity_ok)
from companion.messages import SECONDS_PER_WEEK, GpsEphemeris

SUBFRAME_S = 6.0


class _Fields:
    """The 240 data bits of a subframe, set field by field (word 1..10, IS-GPS-200 bit 1..24)."""

    def __init__(self):
        self.data = [0] * 10

    def u(self, word: int, bit: int, n: int, value: int) -> "_Fields":
        value = int(value)
        if not 0 <= value < (1 << n):
            raise ValueError(f"{value} does not fit in {n} unsigned bits (word {word} bit {bit})")
        self.data[word - 1] |= value << (24 - (bit - 1) - n)
        return self

    def s(self, word: int, bit: int, n: int, value: int) -> "_Fields":
        value = int(value)
        if not -(1 << (n - 1)) <= value < (1 << (n - 1)):
            raise ValueError(f"{value} does not fit in {n} signed bits (word {word} bit {bit})")
        return self.u(word, bit, n, value & ((1 << n) - 1))

    def split(self, w1: int, b1: int, n1: int, w2: int, b2: int, n2: int, value: int, signed: bool) -> "_Fields":
        """A field whose n1 most significant bits are in w1 and the n2 others in w2."""
        n = n1 + n2
        value = int(value)
        lo, hi = (-(1 << (n - 1)), 1 << (n - 1)) if signed else (0, 1 << n)
        if not lo <= value < hi:
            raise ValueError(f"{value} does not fit in {n} bits")
        value &= (1 << n) - 1
        return self.u(w1, b1, n1, value >> n2).u(w2, b2, n2, value & ((1 << n2) - 1))


def _parity(d: int, d29s: int, d30s: int) -> int:
    p = 0
    for prev, mask in _PARITY_MASKS:
        p = (p << 1) | ((d29s if prev == 29 else d30s) ^ (bin(d & mask).count("1") & 1))
    return p


def _words(f: _Fields) -> list[int]:
    """Ten SFRBX words with parity; the t bits (23-24) of words 2 and 10 make their D29/D30 zero."""
    out = []
    d29s = d30s = 0
    for i, d in enumerate(f.data):
        if i in (1, 9):
            d = next(d | t for t in range(4) if _parity(d | t, d29s, d30s) & 0b11 == 0)
        p = _parity(d, d29s, d30s)
        w = (d29s << 31) | (d30s << 30) | (d << 6) | p
        assert word_parity_ok(w)
        out.append(w)
        d29s, d30s = (p >> 1) & 1, p & 1
    return out


def _header(sfid: int, tow_next_s: float) -> _Fields:
    f = _Fields()
    f.u(1, 1, 8, PREAMBLE)
    tow_count = int(round(tow_next_s / SUBFRAME_S)) % int(SECONDS_PER_WEEK / SUBFRAME_S)
    return f.u(2, 1, 17, tow_count).u(2, 20, 3, sfid)


def _q(value: float, lsb: float) -> int:
    return int(round(value / lsb))


def _sc(rad: float) -> float:
    """Radians -> semicircles in [-1, 1)."""
    return (rad / PI_GPS + 1.0) % 2.0 - 1.0


def transmission_week(e: GpsEphemeris, tow_next_s: float) -> int:
    """The week a subframe of ``e`` ending at ``tow_next_s`` is sent in: subframe 1's WN
    (IS-GPS-200 20.3.3.3.1.1), which is ``e``'s week (the week of toe) except across a week
    boundary, where toe lies within half a week of the transmission time on the other side."""
    t_tx = (tow_next_s - SUBFRAME_S) % SECONDS_PER_WEEK
    if e.toe_s - t_tx > SECONDS_PER_WEEK / 2:
        return e.week + 1          # toe late in the week before, sent early in this one
    if e.toe_s - t_tx < -SECONDS_PER_WEEK / 2:
        return e.week - 1          # toe early in the next week, sent late in this one
    return e.week


def ephemeris_subframe(e: GpsEphemeris, sfid: int, tow_next_s: float) -> list[int]:
    """Subframe ``sfid`` (1, 2, 3) of ``e``, transmitted so that it ends at ``tow_next_s``."""
    f = _header(sfid, tow_next_s)
    if sfid == 1:
        ura = next((i for i, v in enumerate(URA_M) if e.ura_m <= v), 15)
        f.u(3, 1, 10, transmission_week(e, tow_next_s) % 1024).u(3, 11, 2, 1).u(3, 13, 4, ura).u(3, 17, 6, e.health & 0x3F)
        f.u(3, 23, 2, (e.iodc >> 8) & 0x3).s(7, 17, 8, _q(e.tgd_s, 2.0 ** -31))
        f.u(8, 1, 8, e.iodc & 0xFF).u(8, 9, 16, _q(e.toc_s % SECONDS_PER_WEEK, 16.0))
        f.s(9, 1, 8, _q(e.af2_sps2, 2.0 ** -55)).s(9, 9, 16, _q(e.af1_sps, 2.0 ** -43))
        f.s(10, 1, 22, _q(e.af0_s, 2.0 ** -31))
    elif sfid == 2:
        f.u(3, 1, 8, e.iode & 0xFF).s(3, 9, 16, _q(e.crs_m, 2.0 ** -5))
        f.s(4, 1, 16, _q(e.delta_n_radps / PI_GPS, 2.0 ** -43))
        f.split(4, 17, 8, 5, 1, 24, _q(_sc(e.m0_rad), 2.0 ** -31), signed=True)
        f.s(6, 1, 16, _q(e.cuc_rad, 2.0 ** -29)).split(6, 17, 8, 7, 1, 24, _q(e.e, 2.0 ** -33), signed=False)
        f.s(8, 1, 16, _q(e.cus_rad, 2.0 ** -29)).split(8, 17, 8, 9, 1, 24, _q(e.sqrt_a, 2.0 ** -19), signed=False)
        f.u(10, 1, 16, _q(e.toe_s, 16.0)).u(10, 17, 1, 0 if e.fit_interval_h <= 4.0 else 1)
    elif sfid == 3:
        f.s(3, 1, 16, _q(e.cic_rad, 2.0 ** -29)).split(3, 17, 8, 4, 1, 24, _q(_sc(e.omega0_rad), 2.0 ** -31), True)
        f.s(5, 1, 16, _q(e.cis_rad, 2.0 ** -29)).split(5, 17, 8, 6, 1, 24, _q(_sc(e.i0_rad), 2.0 ** -31), True)
        f.s(7, 1, 16, _q(e.crc_m, 2.0 ** -5)).split(7, 17, 8, 8, 1, 24, _q(_sc(e.omega_rad), 2.0 ** -31), True)
        f.s(9, 1, 24, _q(e.omega_dot_radps / PI_GPS, 2.0 ** -43))
        f.u(10, 1, 8, e.iode & 0xFF).s(10, 9, 14, _q(e.idot_radps / PI_GPS, 2.0 ** -43))
    else:
        raise ValueError(f"no ephemeris in subframe {sfid}")
    return _words(f)


KLOBUCHAR_SCALES = ((2.0 ** -30, 2.0 ** -27, 2.0 ** -24, 2.0 ** -24), (2.0 ** 11, 2.0 ** 14, 2.0 ** 16, 2.0 ** 16))


def klobuchar_subframe(alpha, beta, tow_next_s: float) -> list[int]:
    """Subframe 4 page 18 with the Klobuchar coefficients (broadcast units, as the RINEX header)."""
    a = [_q(v, k) for v, k in zip(alpha, KLOBUCHAR_SCALES[0])]
    b = [_q(v, k) for v, k in zip(beta, KLOBUCHAR_SCALES[1])]
    f = _header(4, tow_next_s)
    f.u(3, 1, 2, 1).u(3, 3, 6, KLOBUCHAR_PAGE_SV_ID).s(3, 9, 8, a[0]).s(3, 17, 8, a[1])
    f.s(4, 1, 8, a[2]).s(4, 9, 8, a[3]).s(4, 17, 8, b[0])
    f.s(5, 1, 8, b[1]).s(5, 9, 8, b[2]).s(5, 17, 8, b[3])
    return _words(f)


def subframe_due(t_rx_gps: float, tol_s: float = 1e-6) -> tuple[int, float] | None:
    """(subframe id, time of week at its end) of the subframe a receiver completes at receiver
    time ``t_rx_gps``, or None when no subframe ends then."""
    tow = t_rx_gps % SECONDS_PER_WEEK
    n = round(tow / SUBFRAME_S)
    if abs(tow - n * SUBFRAME_S) > tol_s:
        return None
    start = (n - 1) % int(SECONDS_PER_WEEK / SUBFRAME_S)
    return start % 5 + 1, float(n * SUBFRAME_S % SECONDS_PER_WEEK)


def sfrbx_frame(prn: int, words: list[int], channel: int = 0) -> bytes:
    """UBX RXM-SFRBX (version 2) of one GPS L1 C/A subframe, built with pyubx2."""
    from pyubx2 import GET, UBXMessage
    kw = {f"dwrd_{i:02d}": w for i, w in enumerate(words, 1)}
    return UBXMessage("RXM", "RXM-SFRBX", GET, gnssId=0, svId=prn, sigId=0, freqId=0, numWords=len(words),
                      chn=channel, version=2, **kw).serialize()


def quantised(e: GpsEphemeris) -> GpsEphemeris:
    """``e`` as LNAV carries it (every field at its broadcast resolution), through the companion's
    own subframe decoder."""
    asm = LnavEphemerisAssembler()
    tow_next = (e.toe_s % SECONDS_PER_WEEK) // SUBFRAME_S * SUBFRAME_S
    out = None
    for sfid in (1, 2, 3):
        out = asm.add(e.sat, ephemeris_subframe(e, sfid, tow_next + sfid * SUBFRAME_S), e.week)
    if out is None:
        raise ValueError(f"{e.sat}: subframes 1-3 did not decode")
    if not math.isclose(out.t_oe_gps, e.t_oe_gps, abs_tol=8.0):
        raise ValueError(f"{e.sat}: toe {e.toe_s} is not a multiple of 16 s")
    return out


__all__ = ["ephemeris_subframe", "klobuchar_subframe", "subframe_due", "sfrbx_frame", "quantised", "transmission_week"]
