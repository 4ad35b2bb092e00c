"""When the MAVLink reader may sleep: fewer wake-ups for the same estimates, on time.

A wake-up costs far more than its Python: the first datagram read after one took 150-270 us in
the live service, the fourth of the same read ~70 us (the caches and predictors were someone else's
meanwhile).  A 200-Hz IMU stream woke the service ~270 times a second, one datagram each.

Only the IMU sample that opens an output slot is urgent: the estimate is stamped with it and sent
right after it (the latency the autopilot sees).  The samples between are integrated whenever
they are read.  So after each read the reader sleeps until shortly before that sample is due, and
what arrived meanwhile is read in one go.  Nothing is lost or reordered (the socket buffers it),
every record keeps its order in the field log, and replay is unaffected.  The due time comes from
the stream itself: the lower envelope of (receive time - GPS time x clock ratio) over the last two
seconds, i.e. the samples that were read on arrival, not those read late from a batch; the clock
ratio (wall seconds per GPS second: 1 live, 1/speedup in a simulation) from two such samples
about a second apart.  The margin before the due time covers the timer's lateness (the event loop
waits in whole milliseconds) and the stream's jitter.

An autopilot's TIMESYNC request read after a sleep is answered late; PX4 uses only exchanges
with round trips under 10 ms, so it keeps those read on arrival (our own requests are never slept
across: the link reads on arrival until the reply is in).

Measure it: ``python -m sitl fly --duration 120`` against the same with ``--set
mavlink.rx_pacing=false``.
"""
from __future__ import annotations

import math
from collections import deque


class OutputPacedReads:
    """The reader's pause after a read: until ``margin_s`` before the IMU sample that opens the
    next output slot is due, at most ``max_pause_s``; 0 (read on arrival) while the stream's
    timing is unknown (fewer than ``min_samples`` recent samples, a gap, a clock jump) or no slot
    is running.  ``observe`` every IMU sample the pipeline took (its receive time, its GPS time);
    ``pause_s(now, next_slot_t_gps)`` at the end of each read."""

    def __init__(self, *, margin_s: float = 0.004, max_pause_s: float = 0.05, window_s: float = 2.0,
                 min_samples: int = 20):
        self.margin_s = float(margin_s)
        self.max_pause_s = float(max_pause_s)
        self.window_s = float(window_s)
        self.min_samples = int(min_samples)
        self._recent: deque = deque()        # (t_rx_s, t_gps_s) of the last window_s
        self._ratio: float | None = None     # wall seconds per GPS second
        self._ratio_t_gps = -math.inf        # when it was last estimated
        self._lead: deque = deque()          # (t_gps_s, t_rx_s - ratio * t_gps_s), increasing: its
        #                                      first is the window's minimum (a sliding minimum)

    def reset(self) -> None:
        self._recent.clear()
        self._lead.clear()
        self._ratio, self._ratio_t_gps = None, -math.inf

    def observe(self, t_rx_s: float, t_gps_s: float) -> None:
        r = self._recent
        if r and not (0.0 < t_gps_s - r[-1][1] < 1.0 and t_rx_s >= r[-1][0]):
            self.reset()                    # a gap, a jump back, a reboot: learn the timing again
        r.append((t_rx_s, t_gps_s))
        while t_gps_s - r[0][1] > self.window_s:
            r.popleft()
        if t_gps_s - self._ratio_t_gps > 1.0:
            self._estimate_ratio()
        elif self._ratio is not None:
            self._push_lead(t_gps_s, t_rx_s - self._ratio * t_gps_s)
        lead = self._lead
        while lead and t_gps_s - lead[0][0] > self.window_s:
            lead.popleft()

    def _push_lead(self, t_gps_s: float, v: float) -> None:
        lead = self._lead
        while lead and lead[-1][1] >= v:
            lead.pop()
        lead.append((t_gps_s, v))

    def _estimate_ratio(self) -> None:
        """Once a second: the clock ratio between two samples read on arrival (the earliest of the
        window's first and last quarters: a sample read late from a batch would tilt it), and the
        sliding minimum rebuilt with it."""
        r = self._recent
        self._lead.clear()
        g0, g1 = r[0][1], r[-1][1]
        if g1 - g0 < 0.5 * self.window_s:
            self._ratio = None               # too little stream yet: again at the next sample
            return
        self._ratio_t_gps = g1               # tried: again in a second, whatever the outcome
        quarter = 0.25 * (g1 - g0)
        first = [x for x in r if x[1] - g0 <= quarter]
        last = [x for x in r if g1 - x[1] <= quarter]
        ratio = (r[-1][0] - r[0][0]) / (g1 - g0)
        for _ in range(2):                   # the earliest depends on the ratio: once more with it
            a = min(first, key=lambda x: x[0] - ratio * x[1])
            b = min(last, key=lambda x: x[0] - ratio * x[1])
            ratio = (b[0] - a[0]) / (b[1] - a[1])
        if not 0.05 < ratio < 20.0:
            self._ratio = None
            return
        self._ratio = ratio
        for rx, g in r:
            self._push_lead(g, rx - ratio * g)

    def due_s(self, t_gps_s: float) -> float | None:
        """The receive time of a sample stamped ``t_gps_s`` when read on arrival, or None."""
        if self._ratio is None or len(self._recent) < self.min_samples or not self._lead:
            return None
        return self._lead[0][1] + self._ratio * t_gps_s

    def pause_s(self, now_s: float, next_slot_t_gps: float | None) -> float:
        if next_slot_t_gps is None:
            return 0.0
        due = self.due_s(next_slot_t_gps)
        if due is None:
            return 0.0
        return max(0.0, min(due - self.margin_s - now_s, self.max_pause_s))
