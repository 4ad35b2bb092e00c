"""u-blox UBX-RXM-SFRBX -> broadcast ephemerides of GPS, QZSS, Galileo and BeiDou.

One navigation-message assembler per message type, chosen by (gnssId, sigId) of the frame (u-blox
F9 interface description, "Broadcast navigation data"):

============  ==================  ==========================  ==========================
gnssId        sigId               words                       decoder
============  ==================  ==========================  ==========================
0 GPS         0 L1 C/A            10 LNAV words               :mod:`companion.gnss.lnav`
5 QZSS        0 L1 C/A            10 LNAV words               :mod:`companion.gnss.lnav`
2 Galileo     1 E1-B, 5 E5b-I     8 (one I/NAV page pair)     :mod:`companion.gnss.inav`
3 BeiDou      0-3 B1I / B2I       10 D1 or D2 words           :mod:`companion.gnss.beidou_nav`
============  ==================  ==========================  ==========================

Everything else (GPS/QZSS L2C and L5 CNAV, QZSS L1S, GLONASS strings, SBAS, Galileo F/NAV and
E6) is counted per system as ``sfrbx_not_decoded_<letter>``.  QZSS has its own LNAV assembler so
that its Klobuchar page (fitted to the QZSS service area) never replaces GPS's.

The bit unpacking is hand-written: pyubx2 splits RXM-SFRBX into its 32-bit ``dwrd`` words but has
no navigation-message decoder, and no package on the index decodes LNAV / I/NAV / D1 / D2 to
Keplerian elements; the CRC-24Q of I/NAV is pyrtcm's.
"""
from __future__ import annotations

from ..gnss.beidou_nav import BeidouEphemerisAssembler
from ..gnss.inav import InavEphemerisAssembler
from ..gnss.lnav import LnavEphemerisAssembler
from ..messages import GpsEphemeris

GALILEO_INAV_SIGNALS = (1, 5)          # E1-B, E5b-I
BEIDOU_D_SIGNALS = (0, 1, 2, 3)        # B1I D1, B1I D2, B2I D1, B2I D2
BEIDOU_D2_SIGNALS = (1, 3)


class SfrbxEphemerides:
    """Feeds SFRBX words to the assembler of their message; see the module docstring.

    ``add`` returns (ephemeris or None, rejection reason or ''): the reason is set when the words
    were malformed (parity, CRC, preamble), which the caller counts and logs."""

    def __init__(self, check_parity: bool = True):
        self.gps = LnavEphemerisAssembler(check_parity=check_parity)
        self.qzss = LnavEphemerisAssembler(check_parity=check_parity)
        self.galileo = InavEphemerisAssembler()
        self.beidou = BeidouEphemerisAssembler(check_parity=check_parity)

    def add(self, letter: str, sat: str, sig_id: int, words, ref_week: int) -> tuple[GpsEphemeris | None, str]:
        if letter in ("G", "J") and sig_id == 0 and len(words) == 10:
            asm = self.gps if letter == "G" else self.qzss
            before = dict(asm.counters)
            eph = asm.add(sat, words, ref_week)
            return eph, _changed(before, asm.counters, ("parity", "preamble"))
        if letter == "E" and sig_id in GALILEO_INAV_SIGNALS:
            before = dict(self.galileo.counters)
            eph = self.galileo.add(sat, words)
            return eph, _changed(before, self.galileo.counters, ("length", "even_odd", "crc"))
        if letter == "C" and sig_id in BEIDOU_D_SIGNALS:
            before = dict(self.beidou.counters)
            geo = True if sig_id in BEIDOU_D2_SIGNALS else None
            eph = self.beidou.add(sat, words, geo=geo)
            return eph, _changed(before, self.beidou.counters, ("length", "parity", "preamble"))
        return None, "not_decoded"


def _changed(before: dict, after: dict, reasons: tuple[str, ...]) -> str:
    for r in reasons:
        if after[r] != before[r]:
            return r
    return ""

