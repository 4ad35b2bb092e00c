"""Which base position to believe: the announced one (RTCM 1005/1006, or the configuration's)
against the base's own pseudoranges.

Every differential row, DGPS corrections and RTK double differences alike, takes the base's
position as true, so a position kilometres off poisons them all: on the real 5.3-km car, a 1005
5 km off at epoch 200 left the INS 62 m off by the end of the drive, its rows mostly gated away,
while it called itself float (tests/test_rtk_engine_real_car.py).  Such a position comes from
another station when a network switches bases, from a mistyped or hostile message, and from a
stale one whose station another has replaced on the mountpoint.

The base's single-point solution from its own code is good to metres (measured on the three real
bases here: 5.4-9.5 m from their surveyed positions at the median, 10.4 m at most, without an
ionosphere model), so an announced position more than :data:`BASE_POSITION_MAX_SPP_DIFF_M`
(``corrections.base_max_spp_diff_m``) from it is not believed.  It waits as a candidate, adopted once the base's epochs agree with it: a new
station's 1005 that arrives before its first epochs.  Base epochs that disagree with the believed
position and with the candidate are not used: a new station's epochs before its 1005.  A base
position metres off is within what the code can tell: the rover moves with it, as in every RTK
system.
"""
from __future__ import annotations

import logging
from collections import Counter

import numpy as np

from ..messages import BaseStationPosition

log = logging.getLogger(__name__)

#: the base's single-point solution from its own code and its announced position may differ by
#: this much (about ten times the SPP's error on real bases, so an ionospheric storm without a
#: model still passes; a station switch, kilometres, does not)
BASE_POSITION_MAX_SPP_DIFF_M = 100.0

USE, SKIP, ADOPT = "use", "skip", "adopt"


class BaseStationCheck:
    """The believed base position's guard.  :meth:`announced` judges a new position,
    :meth:`judge_epoch` a base epoch by its single-point solution (None: none could be computed)."""

    def __init__(self, counters: Counter, max_diff_m: float = BASE_POSITION_MAX_SPP_DIFF_M):
        self.counters = counters
        self.max_diff_m = float(max_diff_m)
        self.spp_r_e: np.ndarray | None = None          # the base's last single-point solution
        self.candidate: BaseStationPosition | None = None
        self.confirmed_r_e: np.ndarray | None = None    # the last position a base epoch's SPP agreed with
        self.skipping = False                             # the last base epoch was not used

    def _agrees(self, r_e, spp_r_e) -> bool:
        return float(np.linalg.norm(np.asarray(r_e, float) - spp_r_e)) <= self.max_diff_m

    def announced(self, msg: BaseStationPosition) -> bool:
        """True: believe ``msg`` now (it agrees with the base's last single-point solution, or
        there is none yet to judge it by, then its epochs judge it).  False: a candidate only."""
        if self.spp_r_e is None or self._agrees(msg.r_e, self.spp_r_e):
            self.candidate = None
            return True
        self.counters["base position not believed: far from the base's own pseudoranges"] += 1
        if self.candidate is None or not np.array_equal(self.candidate.r_e, msg.r_e):
            log.warning("base position (station %d) %.0f m from the base's own pseudoranges: not believed until "
                        "its epochs agree", msg.station_id, float(np.linalg.norm(np.asarray(msg.r_e, float)
                                                                                 - self.spp_r_e)))
        self.candidate = msg
        return False

    def judge_epoch(self, spp_r_e, believed: BaseStationPosition | None) -> str:
        """USE the epoch, SKIP it, or ADOPT the candidate (it agrees with the epoch) and use it.
        An epoch without a single-point solution (too few satellites with ephemerides) is used
        only once an earlier epoch confirmed the believed position: at the start a mistyped
        configured position would otherwise be used until the ephemerides come."""
        if spp_r_e is None:
            if believed is not None and self.confirmed_r_e is not None and np.array_equal(believed.r_e,
                                                                                          self.confirmed_r_e):
                self.counters["base epochs not checked: no single-point solution"] += 1
                return USE
            self.counters["base epochs not used: position not checked yet"] += 1
            return SKIP
        self.spp_r_e = np.asarray(spp_r_e, float)
        if believed is not None and self._agrees(believed.r_e, self.spp_r_e):
            # a candidate stays: a network's next station may announce itself before its epochs
            self.confirmed_r_e = np.asarray(believed.r_e, float)
            return self._verdict(USE)
        if self.candidate is not None and self._agrees(self.candidate.r_e, self.spp_r_e):
            self.confirmed_r_e = np.asarray(self.candidate.r_e, float)
            return self._verdict(ADOPT)
        self.counters["base epochs not used: far from the base position"] += 1
        if not self.skipping and believed is not None:
            log.warning("base epochs %.0f m from the base position: not used until a position they agree with",
                        float(np.linalg.norm(np.asarray(believed.r_e, float) - self.spp_r_e)))
        return self._verdict(SKIP)

    def _verdict(self, verdict: str) -> str:
        if self.skipping and verdict != SKIP:
            log.info("base epochs agree with the base position again")
        self.skipping = verdict == SKIP
        return verdict


__all__ = ["BaseStationCheck", "BASE_POSITION_MAX_SPP_DIFF_M", "USE", "SKIP", "ADOPT"]
