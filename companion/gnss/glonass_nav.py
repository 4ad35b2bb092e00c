"""GLONASS navigation strings (L1OF / L2OF) -> :class:`~companion.gnss.glonass.GlonassEphemeris`.

A GLONASS frame is 15 strings of 85 bits every 30 s; strings 1-4 carry the satellite's own
ephemeris (GLONASS ICD edition 5.1, section 4.4 and table 4.5), repeated every frame while its
t_b (a 30-min slot) lasts.  Bit numbers below are the ICD's: bit 85 is sent first (the idle
chip, always 0), bits 84-81 are the string number, bits 8-1 the Hamming check (section 4.7).

u-blox RXM-SFRBX gives a string as four 32-bit words: the first three hold bits 85..1 from their
most significant bit on (the third's 11 low bits unused), the fourth the frame and superframe
numbers the receiver inferred (the F9 interface description's RXM-SFRBX section).  The
frequency channel is not in strings 1-4: SFRBX's ``freqId`` (k + 7) gives it.

Strings 1-4 make an ephemeris when each came at most 10 s after the one before (one frame sends
them 2 s apart): older strings of another t_b never mix in.  Every string passes the Hamming check
first.
"""
from __future__ import annotations

import numpy as np

from .glonass import GlonassEphemeris, t_b_gps

STRING_BITS = 85
FRAME_STRINGS_S = 10.0        # strings 1-4 take 8 s; a little slack for the receive times

# The Hamming code (ICD 5.1, 4.7): check bit beta_k (string bit k, k = 1..7) is the parity of the
# data bits (9..85) whose position in the 85-bit code word has bit k-1 set, with the code word
# numbering the check bits at the powers of two.  Worked out below rather than tabulated.
_DATA_BITS = list(range(9, STRING_BITS + 1))


def _hamming_sets() -> list[tuple[int, ...]]:
    position, code = 0, {}
    for bit in _DATA_BITS:                      # code word positions 3, 5, 6, 7, 9, ... (not 2^j)
        position += 1
        while position & (position - 1) == 0:
            position += 1
        code[bit] = position
    return [tuple(b for b in _DATA_BITS if code[b] >> k & 1) for k in range(7)]


_HAMMING_SETS = _hamming_sets()


def string_bits(words) -> list[int]:
    """The 85 bits of an SFRBX GLONASS string, index = ICD bit number (index 0 unused)."""
    w = (int(words[0]) << 64) | (int(words[1]) << 32) | int(words[2])     # bit 85 at position 95
    return [0] + [(w >> (10 + k)) & 1 for k in range(1, STRING_BITS + 1)]


def hamming_ok(bits: list[int]) -> bool:
    """All seven check bits and the overall parity (beta_8 over the whole string) agree."""
    for k, members in enumerate(_HAMMING_SETS):
        if (bits[k + 1] + sum(bits[b] for b in members)) & 1:
            return False
    return sum(bits[1:]) & 1 == 0


def _field(bits: list[int], hi: int, n: int) -> int:
    """Unsigned field of ``n`` bits whose most significant is ICD bit ``hi``."""
    v = 0
    for b in range(hi, hi - n, -1):
        v = (v << 1) | bits[b]
    return v


def _signed(bits: list[int], hi: int, n: int) -> int:
    """Sign-magnitude field (GLONASS's: the first bit is the sign)."""
    mag = _field(bits, hi - 1, n - 1)
    return -mag if bits[hi] else mag


class GlonassStringAssembler:
    """Strings 1-4 per satellite -> an ephemeris; see the module docstring.  ``add`` returns the
    ephemeris the string completed, or None; ``counters`` count strings, Hamming failures and
    ephemerides."""

    def __init__(self):
        self._strings: dict[tuple[str, int], dict[int, tuple[float, list[int]]]] = {}
        self.counters = {"strings": 0, "length": 0, "hamming": 0, "ephemerides": 0, "incomplete_frame": 0}

    def add(self, sat: str, words, frequency_channel: int, t_rx_gps: float, leap_seconds: int,
            signal: int = 0) -> GlonassEphemeris | None:
        """One string of ``sat`` on ``signal`` (L1OF and L2OF carry the same message: each makes
        its own ephemeris, the store keeps one), received at ``t_rx_gps`` (continuous GPS s)."""
        self.counters["strings"] += 1
        if len(words) < 3:
            self.counters["length"] += 1
            return None
        bits = string_bits(words)
        if not hamming_ok(bits):
            self.counters["hamming"] += 1
            return None
        m = _field(bits, 84, 4)
        if not 1 <= m <= 4:
            return None
        held = self._strings.setdefault((sat, signal), {})
        held[m] = (t_rx_gps, bits)
        if m != 4:
            return None
        got = [held.get(k) for k in (1, 2, 3, 4)]
        if any(x is None for x in got) or not all(
                0.0 <= got[k + 1][0] - got[k][0] <= FRAME_STRINGS_S for k in range(3)):
            self.counters["incomplete_frame"] += 1
            return None
        held.clear()
        eph = _ephemeris(sat, [x[1] for x in got], frequency_channel, t_rx_gps, leap_seconds)
        self.counters["ephemerides"] += 1
        return eph


def _ephemeris(sat: str, s: list[list[int]], k: int, t_rx_gps: float, leap_seconds: int) -> GlonassEphemeris:
    """Strings 1-4 (ICD table 4.5); km, km/s, km/s^2 -> m."""
    def axis(b):        # x_n (27 bits, 2^-11 km), x_n' (24, 2^-20 km/s), x_n'' (5, 2^-30 km/s^2)
        return (_signed(b, 35, 27) * 2.0 ** -11, _signed(b, 64, 24) * 2.0 ** -20,
                _signed(b, 40, 5) * 2.0 ** -30)
    (x, vx, ax), (y, vy, ay), (z, vz, az) = axis(s[0]), axis(s[1]), axis(s[2])
    s2, s3, s4 = s[1], s[2], s[3]
    tb = _field(s2, 76, 7)                    # 15-min units of the Moscow day
    unhealthy = s2[80] or s3[65]              # B_n's high bit, l_n
    km = 1e3
    return GlonassEphemeris(
        sat=sat, t_oe_gps=t_b_gps(tb, t_rx_gps, leap_seconds),
        r_e=np.array([x, y, z]) * km, v_e=np.array([vx, vy, vz]) * km, a_e=np.array([ax, ay, az]) * km,
        clock_bias_s=-_signed(s4, 80, 22) * 2.0 ** -30, clock_rate=_signed(s3, 79, 11) * 2.0 ** -40,
        frequency_channel=k, health=int(unhealthy), iode=tb,
        delta_tau_n_s=_signed(s4, 58, 5) * 2.0 ** -30, age_days=_field(s4, 53, 5))


__all__ = ["GlonassStringAssembler", "hamming_ok", "string_bits"]
