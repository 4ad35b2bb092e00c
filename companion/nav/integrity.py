"""Divergence detection: the filter decides from its own innovations that it no longer knows
where it is.

A filter that has drifted away from the truth (a corrupted IMU sample, a contradicting IMU, a
wrong heading) does not notice from its covariance: P says it is fine, and the gate then rejects
the correct GNSS as outliers, which keeps P small.  What does notice is the innovation sequence.
Over a sliding window of ``window_s`` (data time) of each GNSS source, the filter is *diverged*
when

* most rows are rejected (``max_rejected_fraction``): either the GNSS is lying everywhere at once
  or, far more likely with several satellites, the INS is wrong; or
* the rows it still fuses are inconsistent with their predicted variances: mean NIS above
  ``max_nis_mean`` (1 expected; the gate caps a single row at chi2(0.999, 1) = 10.8, so a mean of
  4 over tens of rows is far outside any chi-square band and far inside the gate).

Both need ``min_updates`` updates with ``min_rows`` rows in the window, so one bad epoch
(multipath, a slip) is not a divergence.  But one epoch whose rows of one GNSS source (at least
``suspect_min_rows``; sources are never pooled, a position error hides from velocity rows) fail
the same tests (most rejected, or a mean NIS of the fused ones above its chi-square bound at
1e-5) makes the state ``suspect`` at once: nothing is injected until ``suspect_clear_epochs``
epochs in a row pass the stricter probation test (back to ``ok``); the window confirms the
divergence, or ``window_s`` without that makes it one too.  Otherwise a corrupted state would be
injected for the seconds that the window needs.

After a re-initialisation the state is ``probation`` until one full window passes with at most
``probation_max_rejected_fraction`` rejected and the NIS inside its bound; only then is it ``ok``
again (the shell injects only when ``ok``).

**Which side is wrong.**  When a *position* source (pseudoranges, position fixes) fails while a
*velocity* source (TDCP, Doppler, velocity fixes) passes the same window test, the INS agrees with
the carrier- or Doppler-derived velocity, so it is the GNSS position that jumped: a spoofer, or a
receiver whose position stepped -- or the INS position did (a corrupted state), which looks the
same.  Re-initialising at once would adopt the lie in the first case.  The state becomes ``hold``:
the engine keeps fusing velocity and stops fusing position rows (still testing them), and since
which side is wrong is unknown, nothing is injected (solution status ``suspect``).  Two
consecutive epochs whose position rows agree with the INS again end the hold (``ok``: a spoofer
that stopped); a velocity source failing too, or ``hold_max_s`` without agreement, makes it
``diverged`` after all and the shell re-initialises from GNSS (the INS was wrong, or the spoofer
outlasted what the INS can vouch for).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

from .chi2 import chi2_ppf

GNSS_SOURCES = ("pseudorange", "tdcp", "doppler", "position", "velocity")
POSITION_SOURCES = ("pseudorange", "position")
VELOCITY_SOURCES = ("tdcp", "doppler", "velocity")


@dataclass(frozen=True)
class IntegrityLimits:
    window_s: float = 5.0
    min_updates: int = 3
    min_rows: int = 10
    max_rejected_fraction: float = 0.5
    max_nis_mean: float = 4.0
    probation_max_rejected_fraction: float = 0.2
    suspect_min_rows: int = 3
    suspect_clear_epochs: int = 2
    hold_max_s: float = 30.0
    sources: tuple = GNSS_SOURCES


class IntegrityState:
    OK = "ok"
    SUSPECT = "suspect"
    DIVERGED = "diverged"
    PROBATION = "probation"
    HOLD = "hold"               # GNSS position disagrees with an INS that the velocity sources confirm


class IntegrityCounter:
    """Stable counter keys."""

    DIVERGED = "integrity.diverged"
    SUSPECT = "integrity.suspect"
    PROBATION_PASSED = "integrity.probation_passed"
    HOLD = "integrity.position_hold"


class IntegrityMonitor:
    """State machine ok <-> suspect -> diverged (-> re-initialised by the shell) -> probation -> ok."""

    def __init__(self, limits: IntegrityLimits = IntegrityLimits(), counters=None):
        self.limits = limits
        self.counters = counters if counters is not None else {}
        for k in (IntegrityCounter.DIVERGED, IntegrityCounter.SUSPECT, IntegrityCounter.PROBATION_PASSED,
                  IntegrityCounter.HOLD):
            self.counters.setdefault(k, 0)
        self.state = IntegrityState.OK
        self.reason = ""
        self.t_start = -math.inf
        self.t_changed = -math.inf
        self._clean_epochs = 0
        self._bad_source = ""

    def restart(self, t_gps: float, probation: bool) -> None:
        """A (re-)initialisation at ``t_gps``; with ``probation`` the state is not ``ok`` until a
        consistent window has passed."""
        self.state = IntegrityState.PROBATION if probation else IntegrityState.OK
        self.reason = "re-initialised: waiting for a consistent window" if probation else ""
        self.t_start = self.t_changed = float(t_gps)

    def evaluate(self, book, t_gps: float) -> bool:
        """After a GNSS update: check the windows, then this epoch.  True when the state changed."""
        if self.state == IntegrityState.DIVERGED:
            return False
        lim = self.limits
        full = []
        holding = self.state == IntegrityState.HOLD
        for src in lim.sources:
            w = book.window(src, t_gps)
            if w.n_updates < lim.min_updates or w.n_rows < lim.min_rows:
                continue
            full.append(src)
            if holding and src in POSITION_SOURCES:
                continue                     # known to disagree: the hold's own test below
            why = self._window_failure(src, w)
            if why is not None:
                return self._fail(book, t_gps, src, why)
        if holding:
            return self._hold_test(book, t_gps)
        if self.state in (IntegrityState.OK, IntegrityState.SUSPECT):
            return self._epoch_test(book, t_gps)
        if self.state == IntegrityState.PROBATION and full and t_gps - self.t_start >= lim.window_s:
            ok = all(book.window(s, t_gps).rejected_fraction <= lim.probation_max_rejected_fraction for s in full)
            if ok:
                self.state, self.reason, self.t_changed = IntegrityState.OK, "", t_gps
                self.counters[IntegrityCounter.PROBATION_PASSED] += 1
                return True
        return False

    def implausible_state(self, t_gps: float, why: str) -> bool:
        """The filter's own estimate is outside what is physically plausible (e.g. an IMU time-tag
        offset far beyond its prior): it is absorbing an error its model does not have, and its
        innovations may look fine meanwhile.  Diverged, like a failed window.  True when the state
        changed."""
        if self.state == IntegrityState.DIVERGED:
            return False
        self.state, self.reason, self.t_changed = IntegrityState.DIVERGED, why, t_gps
        self.counters[IntegrityCounter.DIVERGED] += 1
        return True

    def _window_failure(self, src: str, w) -> str | None:
        lim = self.limits
        if w.rejected_fraction >= lim.max_rejected_fraction:
            return f"{src}: {w.n_rejected} of {w.n_rows} rows rejected in {w.span_s:.1f} s"
        if math.isfinite(w.nis_accepted_mean) and w.nis_accepted_mean > lim.max_nis_mean:
            return f"{src}: mean NIS {w.nis_accepted_mean:.1f} over {w.n_rows} rows in {w.span_s:.1f} s"
        return None

    def _confirming_velocity_source(self, book, t_gps: float) -> str | None:
        """A velocity source with a full window that passes the divergence tests, if any."""
        lim = self.limits
        for src in VELOCITY_SOURCES:
            if src not in lim.sources:
                continue
            w = book.window(src, t_gps)
            if w.n_updates >= lim.min_updates and w.n_rows >= lim.min_rows and self._window_failure(src, w) is None:
                return src
        return None

    def _failing_position_source(self, book, t_gps: float, src: str) -> str | None:
        """The position source that fails: ``src`` itself, or (when a velocity source's one bad
        epoch, such as the step of a spoofer's carrier, made the state suspect) one whose window
        fails now."""
        if src in POSITION_SOURCES:
            return src
        lim = self.limits
        for s in POSITION_SOURCES:
            w = book.window(s, t_gps)
            if s in lim.sources and w.n_updates >= lim.min_updates and w.n_rows >= lim.min_rows \
                    and self._window_failure(s, w) is not None:
                return s
        return None

    def _fail(self, book, t_gps: float, src: str, why: str) -> bool:
        """A source failed: hold (the position disagrees, a velocity source confirms the INS, not on
        probation) or diverged."""
        pos = self._failing_position_source(book, t_gps, src)
        vel = self._confirming_velocity_source(book, t_gps) if pos is not None else None
        if vel is not None and self.state in (IntegrityState.OK, IntegrityState.SUSPECT):
            self.state, self.t_changed = IntegrityState.HOLD, t_gps
            self.reason = f"GNSS position disagrees with the INS, which {vel} confirms: not fused ({why})"
            self._bad_source, self._clean_epochs = pos, 0
            self.counters[IntegrityCounter.HOLD] += 1
            return True
        self.state, self.reason, self.t_changed = IntegrityState.DIVERGED, why, t_gps
        self.counters[IntegrityCounter.DIVERGED] += 1
        return True

    def _hold_test(self, book, t_gps: float) -> bool:
        """In hold: two epochs whose position rows agree end it; too long is a divergence."""
        lim = self.limits
        st = book.sources.get(self._bad_source)
        if st is not None and st.t_gps == t_gps and len(st.labels):
            rows = len(st.labels)
            fused = int(st.accepted.sum())
            nis_mean = st.nis_accepted_sum / fused if fused else math.inf
            clean = (rows - fused) <= lim.probation_max_rejected_fraction * rows and \
                nis_mean <= max(lim.max_nis_mean, _chi2_bound(fused))
            self._clean_epochs = self._clean_epochs + 1 if clean else 0
            if self._clean_epochs >= lim.suspect_clear_epochs:
                self.state, self.reason, self.t_changed = IntegrityState.OK, "", t_gps
                return True
        if t_gps - self.t_changed >= lim.hold_max_s:
            self.state, self.t_changed = IntegrityState.DIVERGED, t_gps
            self.reason = f"GNSS position still disagrees after {lim.hold_max_s:.0f} s of hold ({self.reason})"
            self.counters[IntegrityCounter.DIVERGED] += 1
            return True
        return False

    def _epoch_test(self, book, t_gps: float) -> bool:
        """Each GNSS source's rows of this epoch alone (a position error hides from velocity rows,
        so sources are never pooled): ok <-> suspect, and suspect for too long -> diverged."""
        lim = self.limits
        suspect_now = self.state == IntegrityState.SUSPECT
        bad = None
        bad_src = ""
        all_clean = True
        for src in lim.sources:
            st = book.sources.get(src)
            if st is None or st.t_gps != t_gps or len(st.labels) < lim.suspect_min_rows:
                continue
            rows = len(st.labels)
            fused = int(st.accepted.sum())
            rejected = rows - fused
            nis_mean = st.nis_accepted_sum / fused if fused else math.inf
            # few rows: the chi-square bound at 1e-5 rather than the window's fixed one, so that a
            # consistent filter is not suspected once a minute
            nis_bound = max(lim.max_nis_mean, _chi2_bound(fused))
            if bad is None and (rejected >= lim.max_rejected_fraction * rows or nis_mean > nis_bound):
                bad = f"one epoch: {src} {rejected} of {rows} rows rejected, mean NIS {nis_mean:.1f}"
                bad_src = src
            if rejected > lim.probation_max_rejected_fraction * rows or nis_mean > nis_bound:
                all_clean = False
        if not suspect_now and bad is not None:
            self.state, self.reason, self.t_changed = IntegrityState.SUSPECT, bad, t_gps
            self._clean_epochs = 0
            self._bad_source = bad_src
            self.counters[IntegrityCounter.SUSPECT] += 1
            return True
        if suspect_now and t_gps > self.t_changed:
            self._clean_epochs = self._clean_epochs + 1 if all_clean and bad is None else 0
            if self._clean_epochs >= lim.suspect_clear_epochs:
                self.state, self.reason, self.t_changed = IntegrityState.OK, "", t_gps
                return True
        if suspect_now and t_gps - self.t_changed >= lim.window_s:
            return self._fail(book, t_gps, self._bad_source,
                              f"no consistent GNSS epoch for {lim.window_s:.0f} s ({self.reason})")
        return False


@lru_cache(maxsize=64)
def _chi2_bound(dof: int, p_false: float = 1e-5) -> float:
    """Mean of ``dof`` chi-square(1) values exceeded with probability ``p_false``."""
    return float(chi2_ppf(1.0 - p_false, dof)) / dof if dof > 0 else math.inf
