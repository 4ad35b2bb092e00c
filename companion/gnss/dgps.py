"""Code DGPS: RTCM-style pseudorange corrections (PRC/RRC) computed from a base station's observations.

For each satellite i seen by the base (same signal as the rover will use)::

    raw_i = |r_sat,i - r_base| (Sagnac-rotated) - (P_base,i + c dt_sat,i)
    base_clock_s = robust weighted mean of raw_i over the satellites of clock group s (each system,
                 QZSS with GPS: :func:`companion.gnss.signals.clock_group`, as the rover's SPP) (weights 1/sigma_i^2
                 from elevation; iteratively drop values more than max(3 x 1.4826 MAD, 3 m) from the
                 weighted mean; this value is -c x base receiver clock of system s, inter-system bias
                 included, plus the atmosphere common to its satellites)
    PRC_i = raw_i - base_clock_s(i)

Each system's base-clock estimate is kept *continuous*: from one epoch to the next it moves by the
median change of raw_i over its satellites seen at both epochs, pulled towards the robust mean by
``CLOCK_PULL`` per epoch.  A plain per-epoch mean jumps whenever the satellite subset changes (tens
of metres with Selective Availability), and every such jump lands in the rover's clock as a step.

so the rover gets P_rover + c dt_sat + PRC ~= |r_sat - r_rover| + c dt_rover + residual.
TGD, ionosphere and troposphere are all inside the PRC (the rover applies none of them).
The range-rate correction RRC is the least-squares slope of the PRC history of the satellite over
the last ``rrc_window_s`` (same IODE, no loss of lock); 0 until two epochs exist.
``correction(sat, t, iode)`` returns PRC + RRC (t - t_base); corrections older than ``max_age_s``
are refused and counted.
"""
from __future__ import annotations

import math
from collections import Counter, deque
from statistics import median

import numpy as np

from ..messages import BaseStationPosition, GnssEpoch
from .ephemeris_store import EphemerisStore
from .prepare import prepare_epoch
from .signals import clock_group

BASE_ELEVATION_MASK_RAD = math.radians(5.0)   # corrections are produced down to this elevation
CLOCK_MIN_ELEVATION_RAD = math.radians(10.0)  # satellites used for the base clock estimate
CLOCK_OUTLIER_FLOOR_M = 3.0
CLOCK_PULL = 0.02          # per-epoch pull of the continuous base-clock estimate to the robust mean
CLOCK_MAX_GAP_S = 5.0      # beyond this gap between base epochs the estimate restarts from the mean


class DgpsCorrector:
    """Holds the latest base-station corrections.  See module docstring."""

    def __init__(self, max_age_s: float = 30.0, signal: str = "L1C", rrc_window_s: float = 30.0,
                 systems: str = "G"):
        self.max_age_s = max_age_s
        self.signal = signal
        self.systems = systems
        self.rrc_window_s = rrc_window_s
        self.t_base_gps: float | None = None
        self.base_clock_m: float = float("nan")      # of the first system (GPS when present)
        self.base_clocks_m: dict[str, float] = {}   # clock group ('G' for GPS and QZSS) -> its clock term
        self._prc: dict[str, tuple[float, float, float, int]] = {}   # sat -> (t, prc, rrc, iode)
        self._hist: dict[str, deque] = {}
        self._phase: dict[str, tuple[float, float, float]] = {}
        self._raw_prev: dict[str, float] = {}
        self.last_prepared = None
        self.counters: Counter = Counter()

    # ----------------------------------------------------------------------- base side
    def update_base(self, base_epoch: GnssEpoch, base: BaseStationPosition, store: EphemerisStore) -> int:
        """Compute corrections from one base epoch; returns the number of satellites corrected."""
        r_base = np.asarray(base.r_e, dtype=float)
        prep = prepare_epoch(base_epoch, store, r_base, elevation_mask_rad=BASE_ELEVATION_MASK_RAD,
                             signal=self.signal, apply_models=False, systems=self.systems)
        t = base_epoch.t_gps
        self.last_prepared = prep      # reused by the engine's base-carrier bookkeeping
        for sat, why in prep.rejected.items():
            self.counters["base: " + why] += 1
        sats = prep.sats
        carrier, wavelength = prep.carrier_cycles.tolist(), prep.wavelength_m.tolist()
        for i, sat in enumerate(sats):
            if carrier[i] == carrier[i]:
                self._phase[sat] = (t, carrier[i], wavelength[i])
            else:
                self._phase.pop(sat, None)
        ok = np.isfinite(prep.pseudorange_m)
        if not np.any(ok):
            self.counters["base epoch without pseudoranges"] += 1
            return 0
        rho = np.linalg.norm(prep.r_sat_e - r_base, axis=1)
        raw = rho - prep.pseudorange_m
        w = 1.0 / prep.sigma_pseudorange_m ** 2
        groups = [clock_group(sat) for sat in sats]
        ok_l, raw_l = ok.tolist(), raw.tolist()
        raw_now = {sat: raw_l[i] for i, sat in enumerate(sats) if ok_l[i]}
        continuing = self.t_base_gps is not None and 0.0 < t - self.t_base_gps <= CLOCK_MAX_GAP_S
        clocks: dict[str, float] = {}
        one_group = len(set(groups)) == 1
        sys_of = None if one_group else np.array(groups)
        for sys_ in dict.fromkeys(g for g, k in zip(groups, ok_l) if k):   # each system's clock (ISBs)
            mine = ok if one_group else ok & (sys_of == sys_)
            clocks[sys_] = self._system_clock(raw, w, mine, prep, raw_now, continuing, sys_)
        self._raw_prev = raw_now
        self.base_clocks_m = clocks
        self.base_clock_m = next(iter(clocks.values()))
        self.t_base_gps = t
        n = 0
        new_prc = {}
        iodes, lol = prep.iode.tolist(), prep.loss_of_lock.tolist()
        window = self.rrc_window_s + 1e-6
        centred: dict[tuple, tuple] = {}      # (length, first time) -> (centred times, their sum of squares)
        for i, sat in enumerate(sats):
            if not ok_l[i]:
                continue
            prc = raw_l[i] - clocks[groups[i]]
            iode = iodes[i]
            h = self._hist.get(sat)
            if h is None or (h and (h[-1][2] != iode or lol[i])):
                h = deque()
                self._hist[sat] = h
            h.append((t, prc, iode))
            while h and t - h[0][0] > window:
                h.popleft()
            rrc = 0.0
            n_h = len(h)
            if n_h >= 2:
                # least-squares slope of PRC against time (plain floats: ~30 points, every epoch).  A
                # history is the run of base epochs since its satellite's last restart, so two of the
                # same length and start have the same times: their centred times are computed once
                key = (n_h, h[0][0])
                ct = centred.get(key)
                if ct is None:
                    tm = sum([x[0] - t for x in h]) / n_h
                    cts = [x[0] - t - tm for x in h]
                    ct = centred[key] = (cts, sum([c ** 2 for c in cts]))
                cts, den = ct
                if den > 0:
                    pm = sum([x[1] for x in h]) / n_h
                    rrc = sum([c * (x[1] - pm) for c, x in zip(cts, h)]) / den
            new_prc[sat] = (t, prc, rrc, iode)
            n += 1
        for sat in list(self._hist):
            if sat not in new_prc:
                del self._hist[sat]
        self._prc = new_prc
        self.counters["base epochs"] += 1
        return n

    def _system_clock(self, raw, w, mine, prep, raw_now, continuing: bool, sys_: str) -> float:
        """Continuous robust estimate of one system's base clock term from the satellites ``mine``."""
        use = mine & (prep.elevation_rad >= CLOCK_MIN_ELEVATION_RAD)
        if not np.any(use):
            use = mine.copy()
        n_use = int(np.count_nonzero(use))
        for _ in range(5):
            wu = w[use]
            clk = float(np.sum(wu * raw[use]) / np.sum(wu))
            dev = np.abs(raw - clk)
            mad = 1.4826 * median(dev[use].tolist())      # statistics.median: np.median's value, cheaper
            new_use = use & (dev <= max(3.0 * mad, CLOCK_OUTLIER_FLOOR_M))
            n_new = int(np.count_nonzero(new_use))
            if n_new == n_use or n_new < 2:
                break
            use, n_use = new_use, n_new
        prev = self._raw_prev
        common = [sat for sat in raw_now if sat in prev and clock_group(sat) == sys_]
        last = self.base_clocks_m.get(sys_, float("nan"))
        if len(common) >= 2 and continuing and math.isfinite(last):
            step = median([raw_now[sat] - prev[sat] for sat in common])
            continued = last + step
            clk = continued + CLOCK_PULL * (clk - continued)
        return clk

    # ----------------------------------------------------------------------- rover side
    def iode(self, sat: str) -> int | None:
        """IODE the correction for ``sat`` was computed with, or None if there is none."""
        c = self._prc.get(sat)
        return None if c is None else c[3]

    def correction(self, sat: str, t_gps: float, iode: int) -> tuple[float, float, str]:
        """(PRC m extrapolated with RRC, age s, '') or (NaN, NaN|age, reason) with reason in
        'no DGPS correction', 'IODE mismatch', 'DGPS correction too old'."""
        c = self._prc.get(sat)
        if c is None:
            self.counters["no DGPS correction"] += 1
            return float("nan"), float("nan"), "no DGPS correction"
        t_b, prc, rrc, iode_c = c
        age = t_gps - t_b
        if iode_c != iode:
            self.counters["IODE mismatch"] += 1
            return float("nan"), age, "IODE mismatch"
        if abs(age) > self.max_age_s:
            self.counters["DGPS correction too old"] += 1
            return float("nan"), age, "DGPS correction too old"
        return prc + rrc * age, age, ""

    def base_phase(self, sat: str) -> tuple[float, float, float] | None:
        """(t_gps, carrier cycles, wavelength m) of the latest base carrier phase of ``sat``, or None."""
        return self._phase.get(sat)

    @property
    def sats(self) -> list[str]:
        return sorted(self._prc)
