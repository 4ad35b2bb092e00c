"""Grouping of one base station's RTCM observation messages (MSM, 1002/1004/1010/1012) into epochs.

A base sends all messages of one epoch back to back, each with the multiple-message bit (DF393,
DF005) set except the last.  Real links lose frames; this module decides, for every message, which
epoch it belongs to and when an epoch is complete, so that:

* **a lost frame does not relabel anything.**  GLONASS (UTC + 3 h + leap seconds) and BeiDou (BDT
  = GPS - 14 s) times are converted with known constants; a whole-second disagreement with the
  other systems of the same open set is accepted as a sender's leap-second (or BDT/GPST) offset
  only after ``confirm_sets`` consecutive sets show the same offset.  A one-off disagreement is what
  a lost frame looks like (the open set's last frames were lost and the message belongs to a later
  epoch): it is never relabelled.  Before the system has once agreed with the others it is dropped
  (``epoch_time_mismatch``); afterwards it is taken at its own time.
* **an incomplete epoch is flushed on time**, not only when the next epoch's first message comes
  (1 s late at 1 Hz): also when a frame that is not an observation arrives while the set is open
  (1005, 1033, ephemerides, 1230 follow the set), once the stream has shown ``contiguous_sets``
  complete sets without such a frame inside (a stream that interleaves them disables this for good),
  and when the caller tells the receive time (``t_rx_s``) and ``timeout_s`` passed since the set's
  last frame.  Each cause has its counter (``epoch_incomplete_*``); frames of an epoch already
  flushed are dropped and counted (``epoch_late_frames``), never emitted as a second epoch of the
  same time.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable

from ..messages import GnssEpoch, SatObservation

log = logging.getLogger(__name__)

#: systems whose epoch time needs a whole-second constant (leap seconds, BDT - GPST)
OFFSET_SYSTEMS = frozenset("RC")
#: consecutive sets that must show the same whole-second offset before it is adopted
CONFIRM_SETS = 3
#: complete sets without an interleaved non-observation frame before such a frame closes a set
CONTIGUOUS_SETS = 3
#: receive-time gap that closes an open set.  A set's frames leave the sender back to back (a
#: 6-system MSM7 set of ~5 kB is 0.4 s at 115200 Bd, its frames contiguous); packetising radios add
#: tens of ms per packet.  0.3 s is several packets yet well inside the 1-s epoch interval, so the
#: rover epoch that follows (x.99 s, decoded ~1 s after the base epoch) meets a complete base epoch.
TIMEOUT_S = 0.3
_MAX_OFFSET_S = 30
#: a frame this much older than the open set is a late one (dropped); older still, a time jump
_MAX_LATE_S = 2.0


@dataclass
class _Pending:
    t_gps: float
    observations: list = field(default_factory=list)
    more_follow: bool = True
    systems: set = field(default_factory=set)
    t_rx_last: float | None = None
    other_frame_seen: bool = False


class EpochAssembler:
    """See the module docstring.  ``count(key)`` counts; the decoder passes its counter."""

    def __init__(self, count: Callable[[str], int], source: str = "base", confirm_sets: int = CONFIRM_SETS,
                 contiguous_sets: int = CONTIGUOUS_SETS, timeout_s: float = TIMEOUT_S):
        self._count = count
        self.source = source
        self.confirm_sets = confirm_sets
        self.contiguous_sets = contiguous_sets
        self.timeout_s = timeout_s
        self.pending: _Pending | None = None
        self.offset_s: dict[str, float] = {}          # adopted whole-second offsets per system
        self._agreed: set[str] = set()                # systems seen agreeing with the others
        self._candidate: dict[str, tuple[float, int]] = {}
        self._n_contiguous = 0
        self._interleaved = False
        self._last_emitted_t: float | None = None

    # -- helpers -------------------------------------------------------------------------------
    def _emit(self, p: _Pending, cause: str | None) -> GnssEpoch:
        if cause is not None:
            self._count("epoch_incomplete")
            self._count(f"epoch_incomplete_{cause}")
        self._count("epochs")
        self._last_emitted_t = p.t_gps
        return GnssEpoch(t_gps=p.t_gps, observations=tuple(p.observations), source=self.source)

    def _close(self, cause: str) -> list[GnssEpoch]:
        p, self.pending = self.pending, None
        if p is None:
            return []
        return [self._emit(p, cause if p.more_follow else None)]

    def _evidence(self, system: str, offset: float) -> bool:
        """One more set showing ``system`` off by ``offset`` (the offset that would make it agree);
        True when ``confirm_sets`` consecutive sets agree on it."""
        cand, n = self._candidate.get(system, (None, 0))
        n = n + 1 if cand == offset else 1
        self._candidate[system] = (offset, n)
        return n >= self.confirm_sets

    def _adopt(self, system: str, offset: float) -> None:
        self.offset_s[system] = offset
        self._candidate.pop(system, None)
        self._agreed.add(system)
        self._count("system_time_offset_adopted")
        log.warning("RTCM %s epoch times are %+.0f s off the other systems' in %d consecutive sets: "
                    "offset adopted (leap seconds of the sender or of gnss.leap_seconds?)",
                    system, -offset, self.confirm_sets)

    # -- entry points --------------------------------------------------------------------------
    def add(self, t_gps: float, system: str, obs: list[SatObservation], more_follow: bool,
            t_rx_s: float | None = None) -> tuple[list[GnssEpoch], float | None]:
        """One observation message -> (closed epochs, the time it was filed under or None if dropped)."""
        out: list[GnssEpoch] = []
        t = t_gps + self.offset_s.get(system, 0.0)
        p = self.pending
        if p is not None and abs(t - p.t_gps) > 1e-6:
            verdict = self._whole_second(p, t, system)
            if verdict == "merge":
                t = p.t_gps
            elif verdict == "drop_message":
                self._count("epoch_time_mismatch")
                if not more_follow:                    # its set ended with it, whichever set it was
                    out += self._close("mismatch")
                return out, None
            elif verdict == "drop_pending":
                self._count("epoch_time_mismatch")
                self.pending = p = None
        if p is not None and t < p.t_gps - 1e-6 and p.t_gps - t <= _MAX_LATE_S:
            self._count("epoch_late_frames")            # older than the open set: out of order
            return out, None
        if p is not None and abs(t - p.t_gps) > 1e-6:
            if t < p.t_gps:
                self._count("epoch_time_backwards")     # the sender's time jumped back: start anew
            out += self._close("later_epoch")
            p = None
        if p is None:
            if self._last_emitted_t is not None and abs(t - self._last_emitted_t) < 1e-6:
                # the rest of an epoch already closed (lost-frame guess wrong, or a late frame)
                self._count("epoch_late_frames")
                if self._n_contiguous >= self.contiguous_sets and not self._interleaved:
                    self._interleaved = True           # perhaps closed by an interleaved frame
                return out, None
            p = self.pending = _Pending(t)
        p.observations.extend(obs)
        p.systems.add(system)
        if len(p.systems) > 1 and p.systems - OFFSET_SYSTEMS:
            for s in p.systems & OFFSET_SYSTEMS:       # they agree with the other systems of their set
                self._agreed.add(s)
                self._candidate.pop(s, None)
        p.more_follow = more_follow
        if t_rx_s is not None:
            p.t_rx_last = t_rx_s
        if not more_follow:
            if p.other_frame_seen:
                self._interleaved = True
                self._count("epoch_interleaved_frames")
            else:
                self._n_contiguous += 1
            out += self._close("")
        return out, t

    def _whole_second(self, p: _Pending, t: float, system: str) -> str | None:
        """What to do with a message whose time differs from the open set's by whole seconds."""
        if not p.more_follow:
            return None
        d = t - p.t_gps
        k = round(d)
        if abs(d - k) > 1e-6 or not 1 <= abs(k) <= _MAX_OFFSET_S:
            return None
        anchors = p.systems - OFFSET_SYSTEMS
        if system in OFFSET_SYSTEMS and system not in p.systems and anchors:
            suspect, offset, drop = system, self.offset_s.get(system, 0.0) - d, "drop_message"
        elif system not in OFFSET_SYSTEMS and len(p.systems) == 1 and not anchors:
            suspect = next(iter(p.systems))
            offset, drop = self.offset_s.get(suspect, 0.0) + d, "drop_pending"
        else:
            return None                                # two systems without offsets: a lost frame
        if self._evidence(suspect, offset):
            self._adopt(suspect, offset)
            if drop == "drop_pending":
                p.t_gps = t                            # the open set's time is the suspect's
                return None
            return "merge"
        if suspect in self._agreed:
            self._count("epoch_time_lost_frame")       # it agreed before: a lost frame, no relabel
            return None
        return drop

    def other_frame(self, t_rx_s: float | None = None) -> list[GnssEpoch]:
        """A CRC-valid frame that is not an observation message arrived."""
        p = self.pending
        if p is None or not p.more_follow:
            return []
        if self._n_contiguous >= self.contiguous_sets and not self._interleaved:
            return self._close("other_frame")
        p.other_frame_seen = True
        return []

    def poll(self, t_rx_s: float) -> list[GnssEpoch]:
        """Close an open set whose last frame arrived more than ``timeout_s`` before ``t_rx_s``."""
        p = self.pending
        if p is None or p.t_rx_last is None or t_rx_s - p.t_rx_last <= self.timeout_s:
            return []
        return self._close("timeout")

    def flush(self) -> list[GnssEpoch]:
        """End of the stream: whatever is open."""
        return self._close("end")


__all__ = ["EpochAssembler", "CONFIRM_SETS", "CONTIGUOUS_SETS", "OFFSET_SYSTEMS", "TIMEOUT_S"]
