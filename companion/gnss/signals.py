"""Signals of GPS, GLONASS, Galileo, BeiDou and QZSS: carrier frequencies, which code each system uses for
single-frequency and dual-frequency positioning, and the broadcast group delay a code needs.

Signals are named as in :class:`companion.messages.SatObservation`: 'L' + RINEX 3 band + attribute
('L1C', 'L2W', 'L7Q', 'L2I').  The lists are in order of preference; the first one a satellite
has with a pseudorange is used.

Broadcast clocks refer to: GPS/QZSS LNAV the L1 P(Y)/L2 P(Y) iono-free combination (an L1 C/A user
subtracts TGD, IS-GPS-200 20.3.3.3.3.2); Galileo I/NAV E1/E5b, F/NAV E1/E5a (an E1 user subtracts
BGD(E1,E5b) resp. BGD(E1,E5a), Galileo OS SIS ICD 5.1.5); BeiDou D1/D2 the B3I code (a B1I user
subtracts TGD1, a B2I user TGD2, BeiDou B1I ICD 5.2.4.10); GLONASS the L1 signals (tau_n,
ICD GLONASS 5.1 table 4.5; RTKLIB applies no group delay to L1 or to the L1/L2 iono-free pair).
GLONASS's FDMA carriers depend on the satellite's frequency channel
(:func:`companion.gnss.glonass.carrier_hz`), but L1 and L2 are 9/7 of each other on every
channel, so an iono-free pair needs no channel (:func:`pair_frequencies_hz`).
"""
from __future__ import annotations

import math

from ..messages import GPS_L1_HZ, GPS_L2_HZ, SPEED_OF_LIGHT_MPS, GpsEphemeris
from .glonass import carrier_hz as glonass_carrier_hz

#: carrier frequency, Hz, by system and RINEX 3 band number
FREQUENCY_HZ: dict[str, dict[str, float]] = {
    "G": {"1": GPS_L1_HZ, "2": GPS_L2_HZ, "5": 1176.45e6},
    "J": {"1": GPS_L1_HZ, "2": GPS_L2_HZ, "5": 1176.45e6, "6": 1278.75e6},
    "E": {"1": GPS_L1_HZ, "5": 1176.45e6, "7": 1207.14e6, "8": 1191.795e6, "6": 1278.75e6},
    "C": {"2": 1561.098e6, "1": GPS_L1_HZ, "5": 1176.45e6, "7": 1207.14e6, "8": 1191.795e6,
          "6": 1268.52e6},
    "S": {"1": GPS_L1_HZ, "5": 1176.45e6},
    "I": {"5": 1176.45e6, "9": 2492.028e6},
}

#: systems whose Keplerian broadcast ephemerides and signals are modelled, in the order used to
#: pick the reference clock of a multi-system solution
SUPPORTED_SYSTEMS = "GECJ"

#: GLONASS: its ephemerides are integrated (:mod:`companion.gnss.glonass`), not Keplerian.  Its
#: pseudoranges carry receiver inter-channel biases that differ with the receiver's make (up to
#: metres between makes), so it joins a solution only when asked (``--sys`` with R, ``[filter]
#: systems``), never by default
GLONASS = "R"
#: the systems :func:`companion.gnss.prepare.prepare_epoch` models, in reference-clock order
PREPARED_SYSTEMS = SUPPORTED_SYSTEMS + GLONASS
#: standard deviation factor of a GLONASS code against the same model for the CDMA systems: its
#: inter-channel biases (RTKLIB's EFACT_GLO)
GLONASS_CODE_SIGMA_FACTOR = 1.5

#: systems whose pseudoranges share another system's receiver clock.  QZSS transmits the same L1 C/A
#: and L2C signals as GPS, on a time steered to GPS time (a few ns), so the receiver sees no
#: inter-system bias worth a column (RTKLIB's pntpos does the same): measured -0.4 m on L1 C/A and
#: -0.1 m iono-free on the NovAtel OEM729 base of tests/test_spp_multignss.py.
#: A DGPS base must group its clocks the same way (companion.gnss.dgps)
CLOCK_GROUPS = {"J": "G"}


def clock_group(sat: str) -> str:
    """The receiver clock a satellite's pseudorange refers to: its system's, except QZSS, which
    shares GPS's (:data:`CLOCK_GROUPS`)."""
    return CLOCK_GROUPS.get(sat[0], sat[0])


#: single-frequency code of each system: GPS/QZSS L1 C/A, Galileo E1 (C pilot, B+C, B data),
#: BeiDou B1I
PRIMARY_SIGNALS: dict[str, tuple[str, ...]] = {
    "G": ("L1C",),
    "E": ("L1C", "L1X", "L1B"),
    "C": ("L2I", "L2X"),
    "J": ("L1C",),
    "R": ("L1C", "L1P"),
}
#: first code of the dual-frequency (iono-free) pair; GPS accepts P(Y) on L1 as before
IF_FIRST_SIGNALS: dict[str, tuple[str, ...]] = {
    "G": ("L1C", "L1W", "L1P"),
    "E": PRIMARY_SIGNALS["E"],
    "C": PRIMARY_SIGNALS["C"],
    "J": PRIMARY_SIGNALS["J"],
    "R": PRIMARY_SIGNALS["R"],
}
#: second code of the pair.  Galileo prefers E5b: the I/NAV clock (the one read by default) refers
#: to E1/E5b, so that combination needs no group delay; E5a follows.  BeiDou B3I first (the clock's
#: own code), then B2I.  GPS L2 P(Y) first (the LNAV clock's own pair), then L2C, then L5.
IF_SECOND_SIGNALS: dict[str, tuple[str, ...]] = {
    "G": ("L2W", "L2P", "L2X", "L2C", "L2L", "L2S", "L5Q", "L5X", "L5I"),
    "E": ("L7Q", "L7X", "L7I", "L5Q", "L5X", "L5I"),
    "C": ("L6I", "L6X", "L7I", "L7X"),
    "J": ("L2L", "L2S", "L2X", "L5Q", "L5X", "L5I"),
    "R": ("L2C", "L2P"),                  # FDMA L2 (its L3 CDMA carrier is not 9/7 of L1's)
}


#: first BeiDou PRN of BDS-3 (C19 onwards; BDS-2 is C01-C18)
BDS3_FIRST_PRN = 19


def is_transmitted(sat: str, signal: str) -> bool:
    """False for a signal the satellite does not broadcast, which a receiver can still report from a
    false lock: BDS-3 satellites carry B1I and B3I for BDS-2 users but not B2I (band 7 I/Q/X; their
    band-7 signal is B2b), BeiDou ICD B1I 3.0 / B3I 1.0.  On the real ZED-F9P log of
    tests/test_ubx_sfrbx_multignss.py one C36 'B2I' pseudorange at 10 dB-Hz, lock time 0, was 360 m
    off its B1I and put the iono-free residual 525 m off."""
    if sat[0] == "C" and signal in ("L7I", "L7Q", "L7X"):
        try:
            return int(sat[1:]) < BDS3_FIRST_PRN
        except ValueError:
            return True
    return True


def frequency_hz(sat: str, signal: str) -> float:
    """Carrier frequency of ``signal`` ('L1C') of ``sat`` ('E11'), NaN when unknown (GLONASS FDMA)."""
    return FREQUENCY_HZ.get(sat[0], {}).get(signal[1:2], float("nan"))


def pair_frequencies_hz(sat: str, signal1: str, signal2: str) -> tuple[float, float]:
    """The carrier frequencies of two signals of ``sat`` in their true ratio, which is all an
    iono-free or divergence-free combination needs: exact for the CDMA systems; GLONASS FDMA L1/L2
    are 9/7 of each other on every frequency channel, so channel 0's are returned."""
    if sat[0] == GLONASS:
        return glonass_carrier_hz(signal1, 0), glonass_carrier_hz(signal2, 0)
    return frequency_hz(sat, signal1), frequency_hz(sat, signal2)


def iono_free_noise_factor(f1_hz: float, f2_hz: float) -> float:
    """Noise amplification of the iono-free combination of two equally noisy codes."""
    g1, g2 = f1_hz * f1_hz, f2_hz * f2_hz
    return math.hypot(g1, g2) / (g1 - g2)


def group_delay_m(eph: GpsEphemeris, codes: tuple[str, ...], tgd_factor: float) -> float:
    """Broadcast group delay (m) that the pseudorange formed from ``codes`` (one code, or the two
    of an iono-free pair) carries relative to the broadcast clock; subtract it.

    GPS/QZSS/Galileo: c x TGD x ``tgd_factor`` ((f_L1/f)^2 for one code, 0 for an iono-free pair:
    exact for L1, GPS L2, Galileo E1 and E1/E5b with an I/NAV clock; other codes, e.g. L5 with an
    LNAV clock, keep a 0.1-0.3 m bias common to the system's satellites, which its inter-system
    bias absorbs).  BeiDou: delay d = TGD1 on B1I, TGD2 on B2I, 0 on B3I (the clock's own code) and
    on B1C/B2a (their ISCs are not in D1/D2 records); an iono-free pair carries
    (f1^2 d1 - f2^2 d2) / (f1^2 - f2^2).
    """
    if eph.sat[0] == GLONASS:
        return 0.0
    if eph.sat[0] != "C":
        return SPEED_OF_LIGHT_MPS * eph.tgd_s * tgd_factor

    def d(code: str) -> float:
        band = code[1:2]
        return eph.tgd_s if band == "2" else eph.tgd2_s if band == "7" else 0.0

    if len(codes) == 1:
        return SPEED_OF_LIGHT_MPS * d(codes[0])
    g1, g2 = frequency_hz(eph.sat, codes[0]) ** 2, frequency_hz(eph.sat, codes[1]) ** 2
    return SPEED_OF_LIGHT_MPS * (g1 * d(codes[0]) - g2 * d(codes[1])) / (g1 - g2)
