"""Which rover and base carrier signals the RTK update may double-difference, and under what name.

The RTK update (:mod:`companion.nav.rtk_update`) pairs a rover observation with the base
observation of the **same signal code** (``SatObservation.signal``) and differences between
satellites within that code only.  Real receivers name the same carrier differently:

* a u-blox F9P rover reports GPS L2 as L2C(L), RINEX ``L2L`` (UBX sigId 3; sigId 4 = L2C(M),
  ``L2S``), never P(Y);
* an RTCM MSM base sends whatever it tracks: ``2L`` from a u-blox base, ``2X`` (L2C M+L) and
  ``2W`` (P(Y) semi-codeless) from most geodetic / CORS receivers, ``2P``/``2D`` from older ones;
  legacy 1004 says only "C/A" or "P(Y)" (``L2X`` / ``L2P``/``L2D``/``L2W`` by its DF016 code).

**Like with like**: the L2C carrier and the L2 P(Y) carrier are in phase quadrature (the
quarter-cycle issue: RINEX 3 and RTCM MSM ask for the alignment to be applied, not every receiver
does, and a quarter cycle in a DD row is 5 cm of phase the integers cannot absorb).  So L2C is
only ever paired with L2C and P(Y) with P(Y).  Within one tracking family the carrier is the same
(L2C M and L codes are time-multiplexed on one carrier; the P(Y) modes are different ways of
tracking one code), so the pipeline renames each family to one **canonical code** on both sides
(:data:`RTK_FAMILIES`) before the engine sees the epochs; a rover L2L then pairs with a base 2X,
and a base sending only 2W has no L2 partner for an L2C rover (L1 carries the fix alone).

Only GPS is renamed and RTK-paired (the other systems' pseudoranges are fused, not RTK-paired);
Galileo E1 is also called ``L1C`` and differencing it against GPS would need the inter-system
phase bias, which differs between receiver makes.
"""
from __future__ import annotations

import dataclasses

from .messages import GnssEpoch

#: GPS tracking families: canonical code -> the RINEX 3 codes on the same carrier component,
#: preferred first (when one receiver reports two codes of a family, the first one listed is kept)
RTK_FAMILIES: dict[str, tuple[str, ...]] = {
    "L1C": ("L1C",),                              # L1 C/A (L1 P(Y) 'L1W'/'L1P' is in quadrature)
    "L2X": ("L2X", "L2L", "L2S", "L2C"),          # L2C (M+L, L, M); 'L2C' = legacy 1004 'C/A on L2'
    "L2W": ("L2W", "L2P", "L2D", "L2Y"),          # L2 P(Y): Z-tracking, codeless, cross-correlated
}

#: the engine's RTK signal list: L1 C/A first (receiver_sats needs its pseudorange), then L2C, L2 P(Y)
RTK_SIGNALS: tuple[str, ...] = ("L1C", "L2X", "L2W")

_CANONICAL = {code: canon for canon, codes in RTK_FAMILIES.items() for code in codes}
_RANK = {code: i for codes in RTK_FAMILIES.values() for i, code in enumerate(codes)}
RTK_SYSTEMS = "G"


def canonical_signal(sat: str, signal: str) -> str | None:
    """The family name a (satellite, signal) is paired under, or None (not RTK-paired)."""
    if sat[:1] not in RTK_SYSTEMS:
        return None
    return _CANONICAL.get(signal)


def rtk_epoch(epoch: GnssEpoch) -> GnssEpoch:
    """``epoch`` with every GPS observation of a known family renamed to its canonical code (one
    per satellite and family: the preferred code); everything else is passed unchanged.  An epoch
    that needs no renaming is returned as is (the same object)."""
    best: dict[tuple[str, str], int] = {}         # (sat, canonical) -> index of the kept observation
    for i, o in enumerate(epoch.observations):
        canon = canonical_signal(o.sat, o.signal)
        if canon is None:
            continue
        j = best.get((o.sat, canon))
        if j is None or _RANK[o.signal] < _RANK[epoch.observations[j].signal]:
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


__all__ = ["RTK_FAMILIES", "RTK_SIGNALS", "RTK_SYSTEMS", "canonical_signal", "rtk_epoch"]
