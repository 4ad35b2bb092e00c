"""Which rover and base carrier signals the RTK update may double-difference, and under what name.

The RTK update (:mod:`companion.nav.rtk_update`) pairs a rover observation with the base
observation of the **same signal code** (``SatObservation.signal``) and differences between
satellites within that code only.  Real receivers name the same carrier differently:

* a u-blox F9P rover reports GPS L2 as L2C(L), RINEX ``L2L`` (UBX sigId 3; sigId 4 = L2C(M),
  ``L2S``), never P(Y);
* an RTCM MSM base sends whatever it tracks: ``2L`` from a u-blox base, ``2X`` (L2C M+L) and
  ``2W`` (P(Y) semi-codeless) from most geodetic / CORS receivers, ``2P``/``2D`` from older ones;
  legacy 1004 says only "C/A" or "P(Y)" (``L2X`` / ``L2P``/``L2D``/``L2W`` by its DF016 code).

**Like with like first**: the L2C carrier and the L2 P(Y) carrier are in phase quadrature (the
quarter-cycle issue: RINEX 3 and RTCM MSM ask for the alignment to be applied, not every receiver
does, and a quarter cycle in a DD row is 5 cm of phase the integers cannot absorb).  So a
satellite's L2C is paired with the other receiver's L2C and P(Y) with P(Y) whenever both have it.
Within one tracking family the carrier is the same (L2C M and L codes are time-multiplexed on one
carrier; the P(Y) modes are different ways of tracking one code), so the pipeline renames each
family to one **canonical code** on both sides (:data:`RTK_FAMILIES`) before the engine sees the
epochs; a rover L2L then pairs with a base 2X.

**Across families, in a group of its own** (:data:`RTK_CROSS_PAIRS_BY_SYSTEM`): a satellite whose
L2 the rover tracks only as L2C and the base only as P(Y) (an F9P rover against a CORS file or
RINEX 2 base with P2/L2 only) is paired L2C - P(Y) under a code of the pair's own.  The
quadrature is fixed on the satellites (L2C lags P(Y) by a quarter cycle on every IIR-M and IIF),
so an unaligned receiver adds the same quarter cycle to the single difference of every satellite
of the group, and it cancels between them: it is only mixing L2C - L2C and L2C - P(Y) single
differences in one double difference that would leave it (what a group per pair prevents).  The
rest of the two signals' offsets is millimetres (satellite and receiver delays of L2C against
P(Y), Wanninger 2018).  RTKLIB pairs by frequency slot, whatever the codes.

Every system is renamed and RTK-paired **within itself** (keys carry the system: Galileo E1 and
GPS L1 C/A are both ``L1C`` in RINEX 3, and a ``(sat, signal)`` key keeps them apart); the RTK
update double-differences only satellites of one system against a reference of that system, so no
inter-system phase bias (which differs between receiver makes) is ever needed.  Families:

* GPS / QZSS: L1 C/A; L2C (M+L, L, M); L2 P(Y) (GPS only); L5 (Q pilot, I+Q);
* Galileo: E1 (C pilot, B+C); E5a (Q, I+Q); E5b (Q, I+Q) -- the data components (E1B, E5aI, E5bI)
  are a half / quarter cycle off their pilots when a receiver does not align them, so they are not
  mixed in;
* BeiDou: B1I (I, I+Q); B3I (I, I+Q); B2I (I, I+Q; BDS-2 only, see
  :func:`companion.gnss.signals.is_transmitted`); B1C (pilot P, D+P); B2a (P, D+P).
"""
from __future__ import annotations

import dataclasses

from .messages import GnssEpoch

#: tracking families per system: canonical code -> the RINEX 3 codes on the same carrier component,
#: preferred first (when one receiver reports two codes of a family, the first one listed is kept)
RTK_FAMILIES_BY_SYSTEM: dict[str, dict[str, tuple[str, ...]]] = {
    "G": {
        "L1C": ("L1C",),                              # L1 C/A (L1 P(Y) 'L1W'/'L1P' is in quadrature)
        "L2X": ("L2X", "L2L", "L2S", "L2C"),          # L2C (M+L, L, M); 'L2C' = legacy 1004 'C/A on L2'
        "L2W": ("L2W", "L2P", "L2D", "L2Y"),          # L2 P(Y): Z-tracking, codeless, cross-correlated
        "L5Q": ("L5Q", "L5X"),                        # L5 pilot / I+Q (the data component L5I is in quadrature)
    },
    "J": {
        "L1C": ("L1C",),
        "L2X": ("L2X", "L2L", "L2S"),
        "L5Q": ("L5Q", "L5X"),
    },
    "E": {
        "L1C": ("L1C", "L1X"),                        # E1 C pilot / B+C
        "L5Q": ("L5Q", "L5X"),                        # E5a
        "L7Q": ("L7Q", "L7X"),                        # E5b
    },
    "C": {
        "L2I": ("L2I", "L2X"),                        # B1I
        "L6I": ("L6I", "L6X"),                        # B3I
        "L7I": ("L7I", "L7X"),                        # B2I (BDS-2)
        "L1P": ("L1P", "L1X"),                        # B1C pilot / D+P
        "L5P": ("L5P", "L5X"),                        # B2a pilot / D+P
    },
    # GLONASS: C/A and P apart on each band (in quadrature, as GPS's); the FDMA carriers differ per
    # satellite, so the post-processing RTK keeps GLONASS ambiguities float (companion.gnss.rtk)
    "R": {
        "L1C": ("L1C",),
        "L2C": ("L2C",),
        "L1P": ("L1P",),
        "L2P": ("L2P",),
        "L3Q": ("L3Q", "L3X"),                        # L3OC (CDMA) pilot / I+Q
    },
}

#: per system, (rover family, base family) -> the code of that cross pair: a satellite the two
#: receivers track on one carrier under these two families only (neither has the other's)
RTK_CROSS_PAIRS_BY_SYSTEM: dict[str, dict[tuple[str, str], str]] = {
    "G": {("L2X", "L2W"): "L2X~W", ("L2W", "L2X"): "L2W~X"},
}

#: GPS's families (kept under their old name)
RTK_FAMILIES: dict[str, tuple[str, ...]] = RTK_FAMILIES_BY_SYSTEM["G"]

#: systems whose observations the engine may RTK-pair (those of ``[filter] systems`` among them;
#: GLONASS's ambiguities stay float in the engine: companion.nav.rtk_update)
RTK_SYSTEMS = "GRECJ"

#: per system, the engine's RTK signal list: the first one is the code whose pseudorange places the
#: satellite (receiver_sats), the rest in order of preference
RTK_SIGNALS_BY_SYSTEM: dict[str, tuple[str, ...]] = {
    sys: (*f, *RTK_CROSS_PAIRS_BY_SYSTEM.get(sys, {}).values()) for sys, f in RTK_FAMILIES_BY_SYSTEM.items()}

#: the engine's RTK signal list (every system's canonical codes, GPS's first: L1 C/A, L2C, L2 P(Y),
#: L5, then its cross pairs)
RTK_SIGNALS: tuple[str, ...] = tuple(dict.fromkeys(c for f in RTK_SIGNALS_BY_SYSTEM.values() for c in f))

#: each system's first frequency alone (its positioning code: GPS/QZSS/GLONASS L1 C/A, Galileo E1,
#: BeiDou B1I): what a single-frequency receiver gives (``companion gnss --mode rtk --freq l1``)
RTK_FIRST_SIGNALS: tuple[str, ...] = tuple(dict.fromkeys(f[0] for f in RTK_SIGNALS_BY_SYSTEM.values()))

_CROSS_BASE = {code: fam_b for pairs in RTK_CROSS_PAIRS_BY_SYSTEM.values() for (_, fam_b), code in pairs.items()}
_CANONICAL = {(sys, code): canon for sys, fam in RTK_FAMILIES_BY_SYSTEM.items()
              for canon, codes in fam.items() for code in codes}
_RANK = {(sys, code): i for sys, fam in RTK_FAMILIES_BY_SYSTEM.items()
         for codes in fam.values() for i, code in enumerate(codes)}


def signals_for_system(system: str, signals) -> tuple[str, ...]:
    """The canonical codes of ``system`` among ``signals`` (a configured RTK signal list), in the
    system's order (its positioning code first); empty when the system's positioning code is not
    among them."""
    own = RTK_SIGNALS_BY_SYSTEM.get(system, ())
    out = tuple(s for s in own if s in signals)
    return out if out and out[0] == own[0] else ()


def base_signal(signal: str) -> str:
    """The base's own code of an RTK signal: the base family of a cross pair, else the signal."""
    return _CROSS_BASE.get(signal, signal)


def canonical_signal(sat: str, signal: str) -> str | None:
    """The family name a (satellite, signal) is paired under, or None (not RTK-paired)."""
    return _CANONICAL.get((sat[:1], signal))


def rtk_epoch(epoch: GnssEpoch) -> GnssEpoch:
    """``epoch`` with every GPS / GLONASS / Galileo / BeiDou / QZSS observation of a known family renamed to its canonical code (one
    per satellite and family: the preferred code); everything else is passed unchanged.  An epoch
    that needs no renaming is returned as is (the same object)."""
    best: dict[tuple[str, str], int] = {}         # (sat, canonical) -> index of the kept observation
    for i, o in enumerate(epoch.observations):
        canon = canonical_signal(o.sat, o.signal)
        if canon is None:
            continue
        j = best.get((o.sat, canon))
        if j is None or _RANK[(o.sat[:1], o.signal)] < _RANK[(o.sat[:1], epoch.observations[j].signal)]:
            best[(o.sat, canon)] = i
    out, changed = [], False
    keep = set(best.values())
    for i, o in enumerate(epoch.observations):
        canon = canonical_signal(o.sat, o.signal)
        if canon is None:
            out.append(o)
        elif i not in keep:
            changed = True            # a second code of the same family on this satellite: dropped
        elif canon != o.signal:
            out.append(dataclasses.replace(o, signal=canon))
            changed = True
        else:
            out.append(o)
    return dataclasses.replace(epoch, observations=tuple(out)) if changed else epoch


__all__ = ["RTK_CROSS_PAIRS_BY_SYSTEM", "RTK_FAMILIES", "RTK_FAMILIES_BY_SYSTEM", "RTK_FIRST_SIGNALS", "RTK_SIGNALS", "RTK_SIGNALS_BY_SYSTEM", "RTK_SYSTEMS",
           "base_signal", "canonical_signal", "rtk_epoch", "signals_for_system"]
