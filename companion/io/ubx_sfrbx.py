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
6 GLONASS     0 L1OF, 2 L2OF      4 (one string + frame no.)  :mod:`companion.gnss.glonass_nav`
============  ==================  ==========================  ==========================

Everything else (GPS/QZSS L2C and L5 CNAV, QZSS L1S, SBAS, Galileo F/NAV and E6) is counted per
system as ``sfrbx_not_decoded_<letter>``.  GLONASS needs the receive time (its t_b is a time of
the Moscow day) and the frequency channel (SFRBX's ``freqId``); without a time yet a string is
counted ``sfrbx_glonass_no_time``.  QZSS has its own LNAV assembler so
that its Klobuchar page (fitted to the QZSS service area) never replaces GPS's.

The bit unpacking is hand-written: pyubx2 splits RXM-SFRBX into its 32-bit ``dwrd`` words but has
no navigation-message decoder, and no package on the index decodes LNAV / I/NAV / D1 / D2 to
Keplerian elements or GLONASS strings to their state vector; the CRC-24Q of I/NAV is pyrtcm's.
"""
from __future__ import annotations

from ..gnss.beidou_nav import BeidouEphemerisAssembler
from ..gnss.glonass import GlonassEphemeris, gps_minus_utc_s
from ..gnss.glonass_nav import GlonassStringAssembler
from ..gnss.inav import InavEphemerisAssembler
from ..gnss.lnav import LnavEphemerisAssembler
from ..messages import GpsEphemeris

GALILEO_INAV_SIGNALS = (1, 5)          # E1-B, E5b-I
BEIDOU_D_SIGNALS = (0, 1, 2, 3)        # B1I D1, B1I D2, B2I D1, B2I D2
BEIDOU_D2_SIGNALS = (1, 3)
GLONASS_FDMA_SIGNALS = (0, 2)          # L1OF, L2OF
GLONASS_FREQ_ID_OFFSET = 7             # SFRBX freqId = channel k + 7


class SfrbxEphemerides:
    """Feeds SFRBX words to the assembler of their message; see the module docstring.

    ``add`` returns (ephemeris or None, rejection reason or ''): the reason is set when the words
    were malformed (parity, CRC, preamble), which the caller counts and logs."""

    def __init__(self, check_parity: bool = True):
        self.gps = LnavEphemerisAssembler(check_parity=check_parity)
        self.qzss = LnavEphemerisAssembler(check_parity=check_parity)
        self.galileo = InavEphemerisAssembler()
        self.beidou = BeidouEphemerisAssembler(check_parity=check_parity)
        self.glonass = GlonassStringAssembler()

    def add(self, letter: str, sat: str, sig_id: int, words, ref_week: int, *, freq_id: int | None = None,
            t_rx_gps: float | None = None, leap_seconds: int | None = None,
            ) -> tuple[GpsEphemeris | GlonassEphemeris | None, str]:
        """``freq_id``, ``t_rx_gps`` (and ``leap_seconds``, else the table's) for GLONASS only."""
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
        if letter == "R" and sig_id in GLONASS_FDMA_SIGNALS:
            if t_rx_gps is None or freq_id is None:
                return None, "glonass_no_time"
            leap = gps_minus_utc_s(t_rx_gps) if leap_seconds is None else leap_seconds
            before = dict(self.glonass.counters)
            eph = self.glonass.add(sat, words, freq_id - GLONASS_FREQ_ID_OFFSET, t_rx_gps, leap, signal=sig_id)
            return eph, _changed(before, self.glonass.counters, ("length", "hamming"))
        return None, "not_decoded"


def _changed(before: dict, after: dict, reasons: tuple[str, ...]) -> str:
    for r in reasons:
        if after[r] != before[r]:
            return r
    return ""

