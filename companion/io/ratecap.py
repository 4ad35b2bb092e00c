"""A byte-rate cap (token bucket) for untrusted input streams.

A source that sends faster than any honest one (a flooding caster, a babbling radio) must not be
able to fill the SD card or eat the CPU the IMU path needs.  :class:`ByteRateCap` allows
``rate_bps`` sustained with bursts up to ``burst_bytes``.  Two ways to use it:

* ``admit(n)`` -> bool: take the whole chunk or none of it (the service drops a chunk over the cap,
  before it is logged or decoded, so replay still sees exactly what the pipeline saw);
* ``delay_s(n)`` -> seconds: always take the chunk, return how long the reader should pause to
  stay at the cap (the NTRIP client sleeps instead of reading: TCP back-pressure on the caster).

Counters (stable keys): ``bytes`` admitted, ``dropped_bytes``, ``dropped_chunks``, ``throttled``
(times a pause was needed).  The clock is injectable for tests.
"""
from __future__ import annotations

import time
from typing import Callable


class ByteRateCap:
    def __init__(self, rate_bps: float, burst_bytes: float | None = None,
                 clock: Callable[[], float] = time.monotonic):
        if not rate_bps > 0:
            raise ValueError("rate_bps must be > 0")
        self.rate_bps = float(rate_bps)
        self.burst_bytes = float(burst_bytes if burst_bytes is not None else rate_bps)
        self._clock = clock
        self._tokens = self.burst_bytes
        self._t = clock()
        self.counters: dict[str, int] = {"bytes": 0, "dropped_bytes": 0, "dropped_chunks": 0, "throttled": 0}

    def _refill(self) -> None:
        now = self._clock()
        self._tokens = min(self.burst_bytes, self._tokens + (now - self._t) * self.rate_bps)
        self._t = now

    def admit(self, n: int) -> bool:
        self._refill()
        if n <= self._tokens:
            self._tokens -= n
            self.counters["bytes"] += n
            return True
        self.counters["dropped_bytes"] += n
        self.counters["dropped_chunks"] += 1
        return False

    def delay_s(self, n: int) -> float:
        self._refill()
        self._tokens -= n
        self.counters["bytes"] += n
        if self._tokens >= 0:
            return 0.0
        self.counters["throttled"] += 1
        return -self._tokens / self.rate_bps


__all__ = ["ByteRateCap"]
