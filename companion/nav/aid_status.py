"""Per aid source status, as PX4 EKF2 publishes ``estimator_aid_src_*``: the last update's
innovations, their variances and test ratios, whether anything was fused and when it last was,
plus sliding windows (data time) of normalised innovation squared and of rejections.

A source is a measurement kind (``pseudorange``, ``tdcp``, ``doppler``, ``position``,
``velocity``, ``attitude``, ``baseline``, ``nhc``, ``zupt``, ``zaru``, ...).  Every gated batch
is recorded with :meth:`AidSourceBook.record`; :mod:`.integrity` reads the windows.

NIS of a row: ``z^2 / S`` (1 dof; ``test_ratio * gate``, so for the leave-one-out kinds it is the
row's conditional NIS given the other rows).  The window keeps the *accepted* rows' NIS (what
the filter fused: chi-square 1 on average if the filter is consistent) and the rejected count
(a rejected row's NIS says it was an outlier, not how wrong the filter is).
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np


@dataclass
class WindowStats:
    """Aggregate of one source over its window."""

    n_updates: int = 0
    n_rows: int = 0
    n_rejected: int = 0
    nis_accepted_mean: float = math.nan
    span_s: float = 0.0              # from the first to the last update in the window

    @property
    def rejected_fraction(self) -> float:
        return self.n_rejected / self.n_rows if self.n_rows else math.nan


@dataclass
class AidSourceStatus:
    """The last update of one aid source (PX4: estimator_aid_src_*) and its running totals."""

    source: str
    t_gps: float = math.nan                 # last update attempt
    labels: list = field(default_factory=list)
    innovation: np.ndarray = field(default_factory=lambda: np.zeros(0))
    innovation_var: np.ndarray = field(default_factory=lambda: np.zeros(0))
    test_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))
    accepted: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    fused: bool = False                     # at least one row of the last update fused
    nis_accepted_sum: float = 0.0           # of the last update's fused rows
    t_last_fused: float = math.nan
    updates: int = 0
    rows_fused: int = 0
    rows_rejected: int = 0
    # window entries: (t_gps, n_rows, n_rejected, nis_sum_accepted, n_accepted)
    _window: deque = field(default_factory=deque, repr=False)

    def as_dict(self, window: WindowStats) -> dict:
        """Plain values for the health report / MQTT / the field log."""
        return {"t_gps": _r(self.t_gps, 3), "fused": self.fused, "t_last_fused": _r(self.t_last_fused, 3),
                "labels": list(self.labels), "innovation": _round_list(self.innovation),
                "innovation_var": _round_list(self.innovation_var), "test_ratio": _round_list(self.test_ratio),
                "updates": self.updates, "rows_fused": self.rows_fused, "rows_rejected": self.rows_rejected,
                "window": {"updates": window.n_updates, "rows": window.n_rows, "rejected": window.n_rejected,
                           "rejected_fraction": _r(window.rejected_fraction),
                           "nis_accepted_mean": _r(window.nis_accepted_mean), "span_s": _r(window.span_s)}}


class AidSourceBook:
    """Status and windows of every aid source the engine fuses."""

    def __init__(self, window_s: float = 5.0):
        self.window_s = float(window_s)
        self.sources: dict[str, AidSourceStatus] = {}

    def clear_windows(self) -> None:
        """After a re-initialisation the old innovations say nothing about the new state."""
        for st in self.sources.values():
            st._window.clear()

    def record(self, rep, t_gps: float, gate_chi2: float) -> None:
        """One gated batch (:class:`~companion.nav.filter.UpdateReport`) at GPS time ``t_gps``."""
        st = self.sources.get(rep.kind)
        if st is None:
            st = self.sources[rep.kind] = AidSourceStatus(rep.kind)
        acc = rep.accepted
        n = len(acc)
        n_acc = int(np.count_nonzero(acc))
        st.t_gps = t_gps
        st.labels = rep.labels
        st.innovation, st.innovation_var, st.test_ratio = rep.innovation, rep.innovation_var, rep.test_ratio
        st.accepted = acc
        st.fused = n_acc > 0
        if st.fused:
            st.t_last_fused = t_gps
        st.updates += 1
        st.rows_fused += n_acc
        st.rows_rejected += n - n_acc
        nis_sum = float(np.sum(rep.test_ratio[acc])) * gate_chi2 if n_acc else 0.0
        st.nis_accepted_sum = nis_sum
        w = st._window
        w.append((t_gps, n, n - n_acc, nis_sum, n_acc))
        while w and w[0][0] < t_gps - self.window_s:
            w.popleft()

    def window(self, source: str, t_now: float | None = None) -> WindowStats:
        """The source's updates within ``window_s`` before ``t_now`` (default: its last update)."""
        st = self.sources.get(source)
        if st is None or not st._window:
            return WindowStats()
        w = st._window
        if t_now is not None:
            w = [e for e in w if e[0] >= t_now - self.window_s]
            if not w:
                return WindowStats()
        rows = sum(e[1] for e in w)
        rej = sum(e[2] for e in w)
        n_acc = sum(e[4] for e in w)
        nis = sum(e[3] for e in w) / n_acc if n_acc else math.nan
        return WindowStats(len(w), rows, rej, nis, w[-1][0] - w[0][0])

    def snapshot(self) -> dict:
        return {k: st.as_dict(self.window(k)) for k, st in sorted(self.sources.items())}


def _r(x: float, nd: int = 4):
    return None if not math.isfinite(x) else round(float(x), nd)


def _round_list(a) -> list:
    return [_r(float(x)) for x in np.asarray(a, float).tolist()]
