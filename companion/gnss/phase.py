"""Carrier-phase bookkeeping for time-differenced carrier (TDCP): what the previous epoch of each
satellite's carrier was, whether the carrier since is continuous with it, and the base station's
carrier history that corrects a rover interval.

* :class:`RoverCarrierBook`: one :class:`PhaseRecord` per satellite from the last epoch, with its
  geometric range from the *corrected* INS state (the engine hands the antenna state over).  A slip
  flag, a half-cycle flag or a lock time that went down since means the carrier is not continuous:
  the record is dropped before a TDCP row is formed.  Every epoch replaces the records, so a slip
  the gate caught spoils one interval only; a half-cycle-ambiguous carrier is never stored.
* :class:`BaseCarrierBook`: a few seconds of the base's carrier with its geometric range and
  satellite clock, so that a rover TDCP over (t_a, t_b) can be corrected by the base's TDCP over
  the same interval.
"""
from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass
from statistics import median

import numpy as np

#: base epochs kept per satellite (8 s at 1 Hz)
BASE_HISTORY_EPOCHS = 8


@dataclass
class PhaseRecord:
    """What a TDCP measurement needs from the previous epoch of one satellite's carrier."""

    t_gps: float
    carrier_cycles: float
    wavelength_m: float
    geometric_range_m: float     # |r_sat - r_ant| at that epoch, from the *updated* INS state
    sat_clock_bias_m: float
    los_e: np.ndarray
    lock_time_s: float
    los_rate_mps: float = 0.0   # u . v_ant at that epoch: what a time-tag error did to the range


def row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products a_i . b_i of (n, 3) arrays (b may be one 3-vector): the numbers of
    ``a[i] @ b[i]`` one row at a time (a stacked matmul is one BLAS dot per row; einsum and
    ``a @ b`` sum in other orders, which moves results by rounding)."""
    return np.matmul(a[:, None, :], b[..., None])[:, 0, 0]


def _line_of_sight(r_sat_e: np.ndarray, r_ant_e: np.ndarray):
    d = r_sat_e - r_ant_e
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    return rho, d / rho[:, None]


def _nearest(hist, t: float):
    """The record of ``hist`` nearest in time to ``t`` (the first of equals, as min() picks), or None."""
    best, best_d = None, math.inf
    for rec in hist:
        d = abs(rec[0] - t)
        if d < best_d:
            best, best_d = rec, d
    return best


class RoverCarrierBook:
    """The rover's carrier at its last epoch, per satellite (``records``: sat -> PhaseRecord)."""

    def __init__(self, counters: Counter | None = None):
        self.records: dict[str, PhaseRecord] = {}
        self.counters = counters if counters is not None else Counter()

    def __len__(self) -> int:
        return len(self.records)

    def clear(self) -> None:
        self.records.clear()

    def last_time(self) -> float:
        """GPS time of the newest record (-inf when empty)."""
        return max((p.t_gps for p in self.records.values()), default=-math.inf)

    def drop_slipped(self, prep) -> None:
        """Before TDCP is formed: a receiver slip flag, a half-cycle flag or a lock time that went
        down means the carrier of that satellite is not continuous with the stored one."""
        for i, sat in enumerate(prep.sats):
            prev = self.records.get(sat)
            if prev is None:
                continue
            lock = float(prep.lock_time_s[i])
            if (bool(prep.loss_of_lock[i]) or bool(prep.half_cycle[i])
                    or (math.isfinite(lock) and math.isfinite(prev.lock_time_s) and lock < prev.lock_time_s)):
                del self.records[sat]
                self.counters["carrier bookkeeping restarted (slip flag / lock time)"] += 1

    def remember(self, prep, r_ant_e: np.ndarray, v_ant_e: np.ndarray) -> None:
        """Replace the records by this epoch's carriers, ranges taken from the antenna state given
        (the corrected one); satellites without a usable carrier now are forgotten."""
        seen = set()
        finite = np.isfinite(prep.carrier_cycles)
        if np.any(finite):
            rows = np.flatnonzero(finite)
            rho, u = _line_of_sight(prep.r_sat_e[rows], r_ant_e)
            v = np.asarray(v_ant_e, dtype=float)
            los_rate = row_dot(u, v).tolist()
            rho_l = rho.tolist()
            carrier, wavelength = prep.carrier_cycles.tolist(), prep.wavelength_m.tolist()
            clock, lock, half = prep.sat_clock_bias_m.tolist(), prep.lock_time_s.tolist(), prep.half_cycle.tolist()
            t, sats = prep.t_gps, prep.sats
            for j, i in enumerate(rows.tolist()):
                if half[i]:
                    continue   # unresolved half-cycle: do not build on this carrier
                sat = sats[i]
                self.records[sat] = PhaseRecord(t, carrier[i], wavelength[i], rho_l[j], clock[i], u[j], lock[i],
                                                los_rate[j])
                seen.add(sat)
        for sat in [s for s in self.records if s not in seen]:
            del self.records[sat]


class BaseCarrierBook:
    """The base's recent carrier per satellite (``history``: sat -> deque of
    (t_gps, carrier cycles, wavelength m, geometric range m, satellite clock m))."""

    def __init__(self):
        self.history: dict[str, deque] = {}

    def remember(self, prep, r_base_e: np.ndarray) -> None:
        """``prep``: the base epoch as the DGPS corrector prepared it (same satellites, same clocks)."""
        finite = np.isfinite(prep.carrier_cycles)
        if not np.any(finite):
            return
        rows = np.flatnonzero(finite)
        rho, _ = _line_of_sight(prep.r_sat_e[rows], r_base_e)
        rho_l = rho.tolist()
        carrier, wavelength = prep.carrier_cycles.tolist(), prep.wavelength_m.tolist()
        clock, lol, half = prep.sat_clock_bias_m.tolist(), prep.loss_of_lock.tolist(), prep.half_cycle.tolist()
        t, sats = prep.t_gps, prep.sats
        for j, i in enumerate(rows.tolist()):
            sat = sats[i]
            hist = self.history.get(sat)
            if hist is None:
                hist = self.history[sat] = deque(maxlen=BASE_HISTORY_EPOCHS)
            if lol[i] or half[i]:
                hist.clear()
                if half[i]:
                    continue
            hist.append((t, carrier[i], wavelength[i], rho_l[j], clock[i]))

    def tdcp_corrections(self, t_a: float, t_b: float, tol_s: float = 0.05) -> dict[str, float]:
        """Per-satellite correction (m) of a rover TDCP over (t_a, t_b) from the base's TDCP over the
        same interval: minus the base's unexplained carrier change, with the base clock change (the
        median over satellites: common to every system, an inter-system bias being constant)
        removed, so only per-satellite common errors are taken out.

        Each end takes the base epoch nearest to it within ``tol_s``: real rovers tag x.987-x.992 s
        (u-blox M8P, clock bias -8 to -13 ms) while the base tags x.000; 50 ms is below half the
        interval of a 10-Hz base, so the pairing stays unambiguous.  The base carrier needs no
        shift to the rover's instants although the range changes by ~10 m in 13 ms: the residual is
        formed against geometric ranges and clocks at the base's own epochs, so what remains is the
        slow per-satellite error rate times the difference of the two ends' offsets (0.1 mm for
        2 cm/s and 5 ms; tests/test_engine_tdcp_pairing.py)."""
        resid = {}
        for sat, hist in self.history.items():
            a, b = _nearest(hist, t_a), _nearest(hist, t_b)
            if (a is None or a is b or abs(a[0] - t_a) > tol_s or abs(b[0] - t_b) > tol_s
                    or a[2] != b[2]):
                continue
            resid[sat] = b[2] * (b[1] - a[1]) + (b[4] - a[4]) - (b[3] - a[3])
        if len(resid) < 2:
            return {}
        common = median(resid.values())
        return {sat: -(e - common) for sat, e in resid.items()}
