"""Fusion of the several IMUs an autopilot reports into one ImuSample stream (seed 004's IMU cluster).

Inputs: :class:`~companion.messages.ImuSample` of several units (``imu_id``: RAW_IMU / HIGHRES_IMU
id, SCALED_IMU2 -> 1, SCALED_IMU3 -> 2), in arrival order.  Output: one ImuSample per sample of the
*primary* unit, on its time grid, with ``imu_id = config.output_id``.

* **Time alignment.**  The units are not sampled simultaneously.  Each sample is turned into mean
  rates over its interval (dtheta/dt, dv/dt), tagged with the interval's midpoint; the other units'
  rates are linearly interpolated to the midpoint of each primary interval.  The interval is the
  unit's *own sampling period*, not the time since the previous sample that arrived: autopilots
  report rates (RAW_IMU, SCALED_IMU, HIGHRES_IMU), so after a frame lost on the link the next
  rate still describes only the last period before its time stamp.  Tagging it at the middle of
  the gap would misalign it by half the gap, and a vibrating airframe's rates change enough in
  2.5 ms to flag a healthy unit (seen on a loaded companion, whose socket buffer overflows).  The
  period is learnt per unit from the intervals that are not gaps.  A primary sample waits
  until every healthy unit has a sample at or after its midpoint; a unit that has fallen more than
  ``max_wait_s`` behind is left out of that sample (counted).
* **Weighted average** of the healthy units by their configured noise densities (weights 1/N^2,
  gyro and accelerometer separately): the fused density is 1/sqrt(sum 1/N_i^2), N/sqrt(3) for three
  equal units.
* **Unit biases.**  Real units disagree by their own turn-on biases (a few mrad/s, tens of mg even
  after calibration), far beyond their white noise.  Each unit's bias *relative to the primary*
  is learnt -- a plain mean over its first ``learn_samples`` samples, then an exponential average
  with time constant ``bias_tau_s`` -- and removed before testing and fusing, so the fused stream
  keeps the primary's bias (no step in it when a unit is dropped or re-admitted).  A unit's
  relative bias is only updated while it and the primary are healthy and unflagged: a failed unit
  cannot teach the cluster its fault.  A unit is not tested during its learning period (a unit
  broken from power-on is indistinguishable from one with a large turn-on bias), and a slow drift
  (ramp much slower than ``bias_tau_s``) is followed, not flagged: the navigation filter's bias
  states take those.
* **Fault detection.**  For every unit, the difference between its (bias-corrected) rates and
  the median of the other *healthy* units' rates is normalised by its predicted standard
  deviation (the unit's per-sample noise plus that of the median of the others, plus
  ``relative_scale_sigma`` times the rate magnitude for the units' scale-factor/misalignment
  mismatch) and summed over a sliding window of ``window`` samples: chi-square with 6*window dof
  under no fault.  Above the ``1 - false_alarm_prob`` quantile a unit is flagged.  With three or
  more healthy units a fault in one also pulls the others' references (the median of two is their
  mean), so only the *worst* flagged unit is dropped (counter, log line) and the remaining units'
  windows restart without it.  A frozen ("stuck") output -- all six rates bit-identical over
  ``stuck_samples`` samples -- is a fault of that unit alone.  A dropped unit keeps being tested
  against the healthy ones and is re-admitted after ``readmit_quiet_samples`` consecutive quiet
  samples.
* **Two units**: a disagreement cannot be attributed to either.  The cluster raises ``ambiguous``
  (counter, log line) and keeps the primary (or the other unit if the primary is the stuck one);
  the navigation filter's own innovation tests must arbitrate.  With one unit there is no test.

Pure and deterministic: no clocks, the same input sequence gives the same output.
"""
from __future__ import annotations

import bisect
import logging
import math
from collections import Counter, deque
from dataclasses import dataclass, field

import numpy as np
from .chi2 import chi2_ppf

from ..messages import ImuSample

log = logging.getLogger(__name__)


@dataclass
class UnitNoise:
    gyro_arw_rad_per_sqrt_s: float
    accel_vrw_mps_per_sqrt_s: float


@dataclass
class ClusterConfig:
    noise: dict[int, UnitNoise]             # per imu_id; units not listed use ``default_noise``
    primary_id: int = 0
    default_noise: UnitNoise = field(default_factory=lambda: UnitNoise(1e-3, 1e-2))
    output_id: int = 100
    window: int = 20                        # samples in the chi-square window
    false_alarm_prob: float = 1e-6          # per window test
    stuck_samples: int = 10
    readmit_quiet_samples: int = 500
    max_wait_s: float = 0.05
    history: int = 64                       # samples kept per unit for interpolation
    learn_samples: int = 200                # plain-mean relative-bias learning before a unit is tested
    bias_tau_s: float = 60.0                # then: time constant of the relative-bias average
    relative_scale_sigma: float = 0.002     # scale/misalignment mismatch between units (fraction of the rate)
    learn_biases: bool = True               # False: units are assumed to share one bias (test only)


@dataclass
class _Unit:
    uid: int
    t_mid: deque
    rates: deque
    healthy: bool = True
    win: deque = field(default_factory=deque)
    win_sum: float = 0.0
    quiet: int = 0
    last_stat: float = 0.0
    same_count: int = 0
    last_raw: tuple | None = None
    _stuck: bool = False
    _faulty: bool = False
    rel_bias: np.ndarray = field(default_factory=lambda: np.zeros(6))   # rates minus the primary's
    n_learnt: int = 0
    period_s: float = 0.0                  # the unit's sampling period, learnt from non-gap intervals


class ImuCluster:
    """Feed samples with :meth:`push`; it returns the fused samples that became ready."""

    def __init__(self, config: ClusterConfig):
        self.cfg = config
        self.units: dict[int, _Unit] = {}
        self.pending: deque = deque()          # (primary sample, its rate's time tag) waiting for the others
        self.counters: Counter = Counter()
        self.ambiguous = False
        self._thr = float(chi2_ppf(1.0 - config.false_alarm_prob, 6 * config.window))
        self.events: list[tuple] = []          # (t_gps, imu_id, 'dropped'|'readmitted'|'ambiguous', detail)

    # ------------------------------------------------------------------ input
    def _unit(self, uid: int) -> _Unit:
        u = self.units.get(uid)
        if u is None:
            n = self.cfg.history
            u = self.units[uid] = _Unit(uid, deque(maxlen=n), deque(maxlen=n))
        return u

    def _sigma(self, uid: int) -> np.ndarray:
        """Per-sample standard deviation of one rate of unit ``uid``: white noise averaged over one
        sampling period (after a lost frame the rate still covers one period, not the gap)."""
        nz = self.cfg.noise.get(uid, self.cfg.default_noise)
        s = 1.0 / math.sqrt(self.units[uid].period_s)
        return np.array([nz.gyro_arw_rad_per_sqrt_s * s] * 3 + [nz.accel_vrw_mps_per_sqrt_s * s] * 3)

    def push(self, s: ImuSample) -> list[ImuSample]:
        if not (s.dt_s > 0):
            self.counters["invalid dt (dropped)"] += 1
            return []
        u = self._unit(s.imu_id)
        tm = s.t_gps - 0.5 * self._period(u, s.dt_s)
        if u.t_mid and tm <= u.t_mid[-1]:
            self.counters[f"imu {s.imu_id}: sample not after previous (dropped)"] += 1
            return []
        raw = np.concatenate([s.dtheta_b, s.dv_b]) / s.dt_s
        key = tuple(raw.tolist())
        u.same_count = u.same_count + 1 if key == u.last_raw else 0
        u.last_raw = key
        u.t_mid.append(tm)
        u.rates.append(raw)
        if s.imu_id == self.cfg.primary_id:
            self.pending.append((s, tm))
        return self._drain()

    # ------------------------------------------------------------------ alignment
    @staticmethod
    def _period(u: _Unit, dt: float) -> float:
        """The unit's sampling period (see module doc): an interval longer than 1.5 periods is a gap
        (frames lost) and does not teach it; the rate of a sample after a gap covers one period."""
        if u.period_s <= 0.0 or dt < 0.67 * u.period_s:
            u.period_s = dt                     # first sample, or the unit now samples faster
        elif dt <= 1.5 * u.period_s:
            u.period_s += 0.05 * (dt - u.period_s)
        return min(dt, u.period_s)

    def _rate_at(self, u: _Unit, tm: float):
        ts = u.t_mid
        if not ts or tm > ts[-1] or tm < ts[0]:
            return None
        k = bisect.bisect_left(ts, tm)
        if ts[k] == tm or k == 0:
            return u.rates[k]
        a = (tm - ts[k - 1]) / (ts[k] - ts[k - 1])
        return u.rates[k - 1] * (1.0 - a) + u.rates[k] * a

    def _drain(self) -> list[ImuSample]:
        out = []
        while self.pending:
            p, tm = self.pending[0]
            newest = self.units[self.cfg.primary_id].t_mid[-1]
            rates = {}
            wait = False
            for uid, u in self.units.items():
                r = self._rate_at(u, tm)
                if r is not None:
                    rates[uid] = r
                elif u.t_mid and u.t_mid[-1] < tm and newest - tm <= self.cfg.max_wait_s:
                    wait = True
                elif u.t_mid and u.t_mid[-1] < tm:
                    self.counters[f"imu {uid}: late (left out)"] += 1
            if wait:
                break
            self.pending.popleft()
            out.append(self._fuse(p, rates))
        return out

    # ------------------------------------------------------------------ test and fuse
    def _learn_biases(self, p: ImuSample, raw: dict) -> None:
        """Update each healthy, unflagged unit's bias relative to the primary (see module doc)."""
        pid = self.cfg.primary_id
        prim = self.units.get(pid)
        if not self.cfg.learn_biases:
            for u in self.units.values():
                u.n_learnt = self.cfg.learn_samples
            return
        if pid not in raw or prim is None or not prim.healthy or prim._faulty:
            return
        for uid, r in raw.items():
            u = self.units[uid]
            if uid == pid or not u.healthy or u._faulty:
                continue
            u.n_learnt += 1
            alpha = max(1.0 / u.n_learnt, p.dt_s / self.cfg.bias_tau_s)
            u.rel_bias = u.rel_bias + alpha * ((r - raw[pid]) - u.rel_bias)

    def _test(self, p: ImuSample, rates: dict) -> None:
        """Window chi-square of every unit against the median of the other *healthy*, learnt units;
        with three or more healthy units the worst flagged one is dropped (one per sample, and the
        others' windows, which it contaminated, restart); with two, see the module doc."""
        cfg = self.cfg
        ids = sorted(rates)
        if len(ids) < 2:
            return
        ready = [o for o in ids if self.units[o].healthy and (o == cfg.primary_id
                                                              or self.units[o].n_learnt >= cfg.learn_samples)]
        for uid in ids:
            u = self.units[uid]
            u._stuck = u.same_count >= cfg.stuck_samples - 1
            u._faulty = u._stuck
            learning = uid != cfg.primary_id and u.n_learnt < cfg.learn_samples and u.healthy
            others = [o for o in ready if o != uid]
            if learning or not others:
                u.quiet = 0 if u._stuck else u.quiet + 1
                continue
            med = np.median(np.array([rates[o] for o in others]), axis=0)
            so = np.mean([self._sigma(o) ** 2 for o in others], axis=0)
            var_med = so * (math.pi / 2.0 / len(others) if len(others) >= 3 else 1.0 / len(others))
            var = self._sigma(uid) ** 2 + var_med + (cfg.relative_scale_sigma * med) ** 2
            q = float(np.sum((rates[uid] - med) ** 2 / var))
            u.win.append(q)
            u.win_sum += q
            if len(u.win) > cfg.window:
                u.win_sum -= u.win.popleft()
            u.last_stat = u.win_sum / (6 * len(u.win))
            u._faulty = u._stuck or (len(u.win) == cfg.window and u.win_sum > self._thr)
            u.quiet = 0 if u._faulty else u.quiet + 1

        healthy = [uid for uid in ids if self.units[uid].healthy]
        flagged = [uid for uid in healthy if self.units[uid]._faulty]
        bad = [uid for uid in flagged if self.units[uid]._stuck]
        if len(healthy) == 2 and flagged and not bad:
            if not self.ambiguous:
                self.ambiguous = True
                self.counters["ambiguous disagreement (2 units)"] += 1
                self.events.append((p.t_gps, None, "ambiguous", "2 units disagree"))
                log.warning("IMU cluster: 2 units disagree at t=%.3f; cannot attribute, keeping the primary",
                            p.t_gps)
            bad = [uid for uid in healthy if uid != cfg.primary_id]
        elif len(healthy) >= 3 and flagged and not bad:
            bad = [max(flagged, key=lambda uid: self.units[uid].win_sum)]
        for uid in bad:
            u = self.units[uid]
            u.healthy = False
            self.counters[f"imu {uid} dropped"] += 1
            why = "stuck output" if u._stuck else f"chi-square {u.win_sum:.1f} > {self._thr:.1f}"
            self.events.append((p.t_gps, uid, "dropped", why))
            log.warning("IMU cluster: unit %d dropped at t=%.3f (%s)", uid, p.t_gps, why)
        if bad:
            for uid in ids:                 # their windows held the dropped unit's contamination
                u = self.units[uid]
                if u.healthy:
                    u.win.clear()
                    u.win_sum = 0.0
        for uid in ids:
            u = self.units[uid]
            if not u.healthy and uid not in bad and u.quiet >= cfg.readmit_quiet_samples:
                u.healthy = True
                u.win.clear()
                u.win_sum = 0.0
                self.counters[f"imu {uid} readmitted"] += 1
                self.events.append((p.t_gps, uid, "readmitted", f"{u.quiet} quiet samples"))
                log.info("IMU cluster: unit %d re-admitted at t=%.3f", uid, p.t_gps)
        if self.ambiguous and len(ids) == 2 and all(
                self.units[uid].quiet >= cfg.readmit_quiet_samples for uid in ids):
            self.ambiguous = False      # latched until both have been quiet for the re-admission period

    def _fuse(self, p: ImuSample, raw: dict) -> ImuSample:
        rates = {uid: r - self.units[uid].rel_bias for uid, r in raw.items()}    # primary's bias for all
        self._test(p, rates)
        self._learn_biases(p, raw)
        use = [uid for uid in sorted(rates) if self.units[uid].healthy]
        if not use:
            use = [self.cfg.primary_id] if self.cfg.primary_id in rates else sorted(rates)[:1]
            self.counters["no healthy unit: primary passed through"] += 1
        w = np.array([1.0 / self._sigma(uid) ** 2 for uid in use])
        r = np.sum(w * np.array([rates[uid] for uid in use]), axis=0) / np.sum(w, axis=0)
        self.counters[f"fused from {len(use)} units"] += 1
        return ImuSample(p.t_gps, p.dt_s, r[:3] * p.dt_s, r[3:] * p.dt_s, self.cfg.output_id)

    def status(self) -> dict:
        return {uid: {"healthy": u.healthy, "window_stat": u.last_stat} for uid, u in self.units.items()}


def fuse(samples, config: ClusterConfig):
    """Batch helper: (fused samples, cluster) for a sequence of samples in arrival order."""
    c = ImuCluster(config)
    out = []
    for s in samples:
        out.extend(c.push(s))
    return out, c
