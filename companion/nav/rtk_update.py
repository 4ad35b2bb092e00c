"""Carrier-phase RTK inside the tightly coupled filter: double-differenced (DD) carrier phase and
code against a base epoch, float single-difference ambiguities as error-state blocks, integers by
LAMBDA with partial fixing, fix-and-hold and wrong-fix detection.

The measurement model is :mod:`companion.gnss.rtk`'s (shared pieces in
:mod:`companion.gnss.double_difference`), with the engine's INS in place of a position-only state:

* **States**: one between-receiver single-difference ambiguity ``N = N_rover - N_base`` (cycles)
  per (satellite, signal), an identity block ``"amb G05 L1C"`` of the engine's error state
  (:meth:`NavEngine.add_state_block`), added on acquisition with the code-minus-phase value
  (receiver clocks cancel in it), reset on a slip or a loss of lock, dropped when the satellite has
  not been seen for ``max_gap_s`` -- unless the rover's lock time then covers the whole gap (a
  data-link outage while the receiver kept tracking: the ambiguity is unchanged and a held fix
  resumes at the first epoch after it).  Their common part is unobservable and never matters: only
  between-satellite differences enter the rows.
* **Differential ionosphere** (``iono_states``): one single-difference slant delay per satellite
  (m at L1's frequency), a block ``"iono G05"`` added with the satellite's first ambiguity (zero,
  zenith sigma ``iono_sigma_zenith_m`` + ``iono_sigma_ppm`` x baseline through the single-layer
  mapping) and dropped with its last; ``-(f_L1/f)^2`` of it on a phase row, ``+`` on a code row.
  Without it a few millimetres of rover-only ionosphere bias the float ambiguities of a
  dual-frequency rover, whose covariance keeps shrinking, and the ratio test fails for a minute.
* **Systems**: the satellites of ``systems`` (the engine's ``[filter] systems``: GPS, GLONASS,
  Galileo, BeiDou, QZSS), each on its own signals (:data:`companion.rtk_signals.RTK_SIGNALS_BY_SYSTEM`
  among ``signals``) and differenced **within its system only**: a reference per (system,
  signal), so no inter-system phase or code bias enters (receiver-make dependent, and between
  different frequencies not even defined).  QZSS has its own reference too (RTKLIB differences
  it against GPS's, which saves one satellite but assumes a zero GPS-QZSS receiver bias).
  Block names carry the satellite, hence the system: ``"amb E11 L7Q"``.  A GPS L2 the rover tracks
  only as L2C and the base only as P(Y) forms its own group (``"amb G05 L2X~W"``,
  :func:`~companion.gnss.double_difference.cross_pair`).
* **Rows** per (system, signal) against its highest satellite ``j`` (``d`` = rover - base):
  ``lambda (dphi_i - dphi_j) = DD rho + lambda (N_i - N_j)`` and ``dP_i - dP_j = DD rho``
  (GLONASS, each satellite on its own carrier: ``lambda_i dphi_i - lambda_j dphi_j`` and
  ``lambda_i N_i - lambda_j N_j``),
  rho modelled at the **INS-predicted antenna position** (the linearisation point) for the rover
  and at the surveyed position for the base.  Jacobians: ``-(u_i - u_j)`` on the antenna position
  (chain rule to the IMU position, attitude through the lever arm, ``dt_imu`` through the antenna
  velocity, as :func:`.measurements.pseudorange_batch`), ``+-lambda`` on the two ambiguities.  The DD
  covariance (the reference's share in every row) is whitened by its Cholesky factor, so the
  filter's update with uncorrelated rows is the correlated update exactly.
* **Epoch pairing**: each receiver is modelled at its own epoch
  (:func:`~companion.gnss.double_difference.receiver_sats`); the base epoch nearest the rover's
  within ``max_base_age_s`` is used **without interpolation or extrapolation**.  Receiver clocks
  cancel in the DD whatever the two tags are; what a time offset leaves is the change of the
  per-satellite errors (satellite clock, orbit, atmosphere: mm/s) over it, 0.01 mm for a real
  rover's x.987 s against a base's x.000 s and ~1 mm for a 1-s-old base epoch.
* **Slips before they reach the ambiguities**: the receiver's flags (loss of lock, half cycle, lock
  time going down, at rover or base) and the INS-predicted phase: per satellite, the change since
  the last epoch of ``lambda dphi - d rho(INS) - lambda N`` with the median over the satellites
  removed (the receiver clocks' change), against its noise and the INS's velocity uncertainty
  (seed 004's innovation test, on single differences).  A slipped ambiguity is re-initialised
  before the rows are built.
* **Integers**: after the float update, LAMBDA (:func:`~companion.gnss.lambda_ils.lambda_ils`) on
  the DD ambiguities (but GLONASS's: ``float_only_systems``) with the ratio test; partial fixing
  drops the least certain DD ambiguity and tries again down to ``min_fix_ambiguities``.  A candidate is validated against the phase
  residuals it leaves (``fixed_residual_sigma``) and against the INS prediction (the position it
  implies, chi-square with 3 dof against the predicted covariance); accepted, it is **held**: fed
  to the filter as a measurement of the DD ambiguities (``hold_sigma_cycles``), so the whole state
  (position, velocity, attitude, biases) moves to the fixed solution and the next epochs start
  from it.
* **Antennas** (``rover_antenna``, ``base_antenna``: :mod:`.rtk_antennas`): each receiver's
  carriers moved from their phase centres to its ARP before the rows
  (:func:`~companion.gnss.double_difference.at_reference_point`), as the post-processing does.
* **Wrong fixes**, per system: a system whose held phase rows then fail the gate (more than one
  row, or most of its rows) has all its ambiguities re-initialised and its rows left out of the
  epoch, and the position covariance is widened by ``wrong_fix_position_sigma_m``; when every
  held system fails, the whole epoch is dropped.  Counted.
"""
from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from ..gnss.atmosphere import saastamoinen_zenith_m
from ..gnss.differential_iono import iono_factor, random_walk_psd
from ..gnss.differential_iono import prior_sigma_m as iono_prior_sigma_m
from ..gnss.double_difference import (at_reference_point, cross_pair, place_at, receiver_sats, sd_variance_m2,
                                       transmit_states)
from ..rtk_signals import base_signal, signals_for_system
from ..gnss.lambda_kernel import lambda_ils      # compiled when numba is there, same results
from ..messages import SPEED_OF_LIGHT_MPS, GnssEpoch
from .chi2 import chi2_ppf
from .earth import C_n_e, ecef_to_geodetic, skew
from .filter import MeasurementBatch, UpdateReport, cholesky_lower, solve_lower

FIX_NONE, FIX_FLOAT, FIX_FIXED = "none", "float", "fixed"


@dataclass(frozen=True)
class RtkUpdateConfig:
    signals: tuple[str, ...] = ("L1C", "L2W")
    systems: str = "G"                        # each differenced within itself (signals_for_system)
    # systems whose DD ambiguities stay float (RTKLIB's gloarmode off): GLONASS FDMA, whose
    # receivers' inter-channel phase biases do not cancel between makes (the base's make is not
    # known live: '' when the user says it is the rover's, [filter] rtk_glonass_integers); its
    # rows still constrain the position through the float ambiguities
    float_only_systems: str = "R"
    elevation_mask_deg: float = 10.0
    sigma_phase_a_m: float = 0.003            # SD variance 2 (a^2 + b^2 / sin^2 el) per receiver pair
    sigma_phase_b_m: float = 0.003
    code_phase_ratio: float = 100.0
    max_base_age_s: float = 1.5
    ambiguity_init_sigma_cycles: float = 30.0
    ambiguity_psd_cycles2ps: float = 1e-8
    max_gap_s: float = 5.0
    slip_min_m: float = 0.05                  # INS-predicted phase change beyond which a slip is declared
    slip_sigmas: float = 5.0
    slip_max_interval_s: float = 1.5
    ratio_threshold: float = 3.0
    min_success_rate: float = 0.999           # bootstrapped success rate of the (partial) set
    min_fix_ambiguities: int = 4
    fixed_residual_sigma: float = 4.0
    ins_fix_probability: float = 0.999        # chi-square test of the fixed position against the INS
    hold_sigma_cycles: float = 0.01
    # a fix must pin the position: its 3-D sigma after the hold at most this (a fixed solution is
    # 1-2 cm; integers that leave the position at decimetres are not tied to the geometry -- after
    # a re-initialisation 31-64 of them passed the ratio test at 3.1-6.0 with 0.8 m left, 0.1-1.3 m off)
    max_fixed_sigma_3d_m: float = 0.10
    wrong_fix_position_sigma_m: float = 0.3
    gate_probability: float = 0.999
    # the differential ionosphere as states (RTKLIB's IONOOPT_EST): one SD slant delay per
    # satellite at L1's frequency, -(lambda/lambda_L1)^2 of it on the phase, + on the code.  Its
    # zenith sigma at acquisition: iono_sigma_zenith_m + iono_sigma_ppm x baseline (RTKLIB's
    # default is 3 ppm: on a real car 5.3 km from its base it kept the float loose for 82 s, 1 ppm
    # fixed from the first epoch; tests/test_rtk_engine_real_car.py), mapped to the slant by the
    # single-layer model; a random walk whose PSD is that of a first-order Markov process of that
    # sigma and iono_correlation_time_s
    iono_states: bool = True
    iono_sigma_zenith_m: float = 0.001
    iono_sigma_ppm: float = 1.0
    iono_correlation_time_s: float = 900.0


@dataclass
class _Amb:
    name: str                 # state block name
    wavelength_m: float
    t_added: float
    base_slips: int           # base slip count at initialisation
    last_seen: float


@dataclass
class RtkEpochRows:
    """The DD rows of one epoch (before whitening) and what resolution needs."""

    t_gps: float
    z: np.ndarray             # innovations (m), phase rows then code rows
    H: np.ndarray
    R: np.ndarray
    kinds: list[str]          # 'phase' / 'code'
    labels: list[str]
    refs: dict                # (system, signal) -> reference satellite
    amb_pairs: list           # per phase row: (key_i, key_ref)
    sd_resid: dict            # key -> (SD residual at the INS point (m), rover LOS, ambiguity (cycles))
    P_prior_pos: np.ndarray | None = None
    keep: np.ndarray | None = None
    amb_cols: np.ndarray | None = None   # per phase row: state indices of (ambiguity i, reference's)


@dataclass
class RtkStatus:
    fix_state: str = FIX_NONE
    ratio: float = math.nan
    n_fixed: int = 0
    n_ambiguities: int = 0
    t_gps: float = math.nan
    success_rate: float = math.nan


class RtkUpdate:
    """RTK bookkeeping of one engine: base epochs, ambiguity blocks, slip tests, fix state."""

    def __init__(self, cfg: RtkUpdateConfig, counters):
        self.cfg = cfg
        self.counters = counters
        self.gate_chi2 = float(chi2_ppf(cfg.gate_probability, 1))
        self.ins_chi2_3 = float(chi2_ppf(cfg.ins_fix_probability, 3))
        self._base: deque = deque(maxlen=8)          # (t_gps, epoch, sats or None)
        self._base_slips: dict = {}                  # (sat, signal) -> count of base slips seen
        self._base_lock: dict = {}
        self._rover_lock: dict = {}
        self.amb: dict[tuple[str, str], _Amb] = {}
        self.iono: dict[str, str] = {}               # sat -> its differential ionosphere's block
        self._resid: dict = {}                       # key -> (t_gps, post-update SD residual m)
        self.held: set = set()                       # keys in the last held fix
        self._reset_after: set = set()               # keys to re-initialise at the end of the epoch
        self.status = RtkStatus()
        # per system, its signals among the configured ones (positioning code first)
        self.sig: dict[str, tuple[str, ...]] = {}
        for sys in dict.fromkeys(cfg.systems):
            own = signals_for_system(sys, cfg.signals)
            if own:
                self.sig[sys] = own
        self._groups = [(sys, s) for sys, sigs in self.sig.items() for s in sigs]
        # the receivers' antenna calibrations (companion.nav.rtk_antennas; None: phase centres at the ARP)
        self.rover_antenna = None
        self.base_antenna = None

    def set_base_antenna(self, calibration) -> None:
        """The base's antenna calibration changed: the base epochs kept are placed again with it."""
        self.base_antenna = calibration
        for b in self._base:
            b[2] = None

    # ------------------------------------------------------------------ bookkeeping
    def reset(self) -> None:
        """After an engine (re-)initialisation: the layout was rebuilt without the blocks."""
        self.amb.clear()
        self.iono.clear()
        self._resid.clear()
        self.held.clear()
        self._rover_lock.clear()
        self.status = RtkStatus()

    def base_changed(self, eng) -> None:
        """Another base station: its carriers' integers are others, its lock times its own."""
        self._drop_all(eng)
        self._base.clear()
        self._base_slips.clear()
        self._base_lock.clear()

    def add_base(self, epoch: GnssEpoch) -> None:
        """A base epoch (its station position must be known to the engine); base slips counted."""
        for o in epoch.observations:
            key = (o.sat, o.signal)
            lock = float(o.lock_time_s)
            prev = self._base_lock.get(key)
            if o.loss_of_lock or o.half_cycle_ambiguous or (
                    prev is not None and math.isfinite(lock) and math.isfinite(prev) and lock < prev):
                self._base_slips[key] = self._base_slips.get(key, 0) + 1
            self._base_lock[key] = lock
        self._base.append([epoch.t_gps, epoch, None])

    def _base_for(self, t_gps: float):
        best = min(self._base, key=lambda b: abs(b[0] - t_gps), default=None)
        if best is None or abs(best[0] - t_gps) > self.cfg.max_base_age_s:
            return None
        return best

    def _base_slips_of(self, key) -> int:
        """The base slips seen on the base's own signal of an ambiguity (a cross pair's base family)."""
        return self._base_slips.get((key[0], base_signal(key[1])), 0)

    def _add_amb(self, eng, key, value_cycles: float, wavelength_m: float, t: float) -> None:
        name = f"amb {key[0]} {key[1]}"
        eng.add_state_block(name, 1, self.cfg.ambiguity_init_sigma_cycles, self.cfg.ambiguity_psd_cycles2ps,
                            value=value_cycles)
        self.amb[key] = _Amb(name, wavelength_m, t, self._base_slips_of(key), t)
        self.counters["rtk ambiguities added"] += 1

    def _drop_amb(self, eng, key) -> None:
        a = self.amb.pop(key, None)
        if a is not None:
            eng.remove_state_block(a.name)
        self._resid.pop(key, None)
        self.held.discard(key)

    def _drop_all(self, eng) -> None:
        for key in list(self.amb):
            self._drop_amb(eng, key)
        self._prune_iono(eng)

    # the differential ionosphere: a block per satellite while any of its ambiguities lives
    def _ensure_iono(self, eng, sat: str, elevation_rad: float) -> None:
        cfg = self.cfg
        if not cfg.iono_states or sat in self.iono:
            return
        base_m = float(np.linalg.norm(eng.r_e - eng.base.r_e)) if eng.base is not None else 0.0
        sigma = iono_prior_sigma_m(elevation_rad, base_m, cfg.iono_sigma_zenith_m, cfg.iono_sigma_ppm)
        name = f"iono {sat}"
        eng.add_state_block(name, 1, sigma, random_walk_psd(sigma, cfg.iono_correlation_time_s))
        self.iono[sat] = name

    def _prune_iono(self, eng) -> None:
        live = {k[0] for k in self.amb}
        for sat in [q for q in self.iono if q not in live]:
            eng.remove_state_block(self.iono.pop(sat))

    def _iono_values(self, eng) -> dict:
        """sat -> its differential ionosphere now (m on L1), the satellites with a block."""
        bs = eng.block_states
        return {sat: float(bs[name][0]) for sat, name in self.iono.items()}

    # ------------------------------------------------------------------ one epoch: float rows
    def rows(self, eng, ins, epoch: GnssEpoch, r_ant_e: np.ndarray, l_e: np.ndarray,
             v_ant_e: np.ndarray, code_variance_factor: float = 1.0) -> RtkEpochRows | None:
        """Ambiguity bookkeeping, slip tests and the DD rows of a rover epoch at the INS point
        (None: no base epoch near enough, or fewer than two common satellites).
        ``code_variance_factor``: the engine's inflation for time-correlated code errors (its
        ``pseudorange_correlation_time_s``), so that averaging epochs of correlated multipath does
        not make the float ambiguities look better than they are (the success rate relies on it).

        The rover measured at its tag minus its clock bias, not at the tag: the antenna is taken
        back along its velocity by the bias (from the code, median over the satellites), since in
        RTK epochs nothing else estimates it (a u-blox rover tags x.99 s, 10 ms off: 8 wrong fixes
        in 120 s at 20 m/s without this, none with it, tests/test_rtk_outputs.py)."""
        # one receiver clock for every system: the bias from the reference system's code alone
        # (the others carry an inter-system bias of up to tens of metres).  The satellites at
        # their transmit times once (they depend on the pseudoranges only), placed at the
        # antenna for the bias, then again at the antenna taken back by it
        states = transmit_states(epoch, eng.ephemerides, self.sig)
        sr = place_at(states, r_ant_e)
        sys0 = next(iter(self.sig), None)
        if sys0 is not None:
            sr0 = [q for sat, q in sr.items() if sat[:1] == sys0]
            if len(sr0) >= 2:
                p0 = self.sig[sys0][0]
                sr0 = [q for q in sr0 if p0 in q.code_m]
                bias_m = float(np.median(np.array([q.code_m[p0] for q in sr0]) - _model_ranges_m(r_ant_e, sr0)[0])) \
                    if sr0 else math.nan
                if math.isfinite(bias_m):
                    r_ant_e = r_ant_e - v_ant_e * (bias_m / SPEED_OF_LIGHT_MPS)
                    sr = None
        obs = self.observe(eng, epoch, r_ant_e, states=states, sr=sr)
        if obs is None:
            return None
        t, common, sr, sb, model_r, model_b = obs
        self._manage(eng, t, common, sr, sb)
        self._slip_test(eng, t, common, sr, sb, model_r, model_b)
        return self.build(eng, obs, l_e, v_ant_e, code_variance_factor)

    def observe(self, eng, epoch: GnssEpoch, r_ant_e: np.ndarray, states=None, sr=None):
        """The rover epoch and its base epoch modelled (rover at the antenna position ``r_ant_e``):
        (t, common satellites above the mask, rover sats, base sats, rover and base models);
        changes nothing but the base epoch's cached geometry.  ``states``: the rover epoch's
        :func:`transmit_states` if known; ``sr``: the rover's satellites placed at ``r_ant_e``
        if known."""
        cfg = self.cfg
        b = self._base_for(epoch.t_gps)
        if b is None:
            self.counters["rtk epochs without a base epoch"] += 1
            return None
        if b[2] is None:
            # the base's satellites from the rover's orbits where their transmit times agree
            b[2] = place_at(transmit_states(b[1], eng.ephemerides, self.sig, near=states), eng.base.r_e)
            # each receiver's carriers moved from their phase centres to its ARP, where the model is
            b[2] = at_reference_point(b[2], self.base_antenna, eng.base.r_e)
        sb = b[2]
        if sr is None:
            sr = (place_at(states, r_ant_e) if states is not None
                  else receiver_sats(epoch, eng.ephemerides, r_ant_e, self.sig))
        sr = at_reference_point(sr, self.rover_antenna, r_ant_e)
        sr, sb = cross_pair(sr, sb)          # rover L2C only against base P(Y) only: a group of its own
        cand = []
        for sat in sorted(set(sr) & set(sb)):
            if sr[sat].eph is not sb[sat].eph:
                self.counters["rtk satellite skipped: base and rover ephemerides differ"] += 1
                continue
            cand.append(sat)
        model_r, model_b, common = {}, {}, []
        if not cand:
            return epoch.t_gps, common, sr, sb, model_r, model_b
        rho_r, U_r, el_r = _model_ranges_m(r_ant_e, [sr[q] for q in cand])
        above = np.flatnonzero(el_r >= math.radians(cfg.elevation_mask_deg))
        cand = [cand[i] for i in above]
        if not cand:
            return epoch.t_gps, common, sr, sb, model_r, model_b
        rho_b, U_b, _ = _model_ranges_m(eng.base.r_e, [sb[q] for q in cand])
        for k, (i, sat) in enumerate(zip(above, cand)):
            sr[sat].elevation_rad = float(el_r[i])
            model_r[sat] = (float(rho_r[i]), U_r[i])
            model_b[sat] = (float(rho_b[k]), U_b[k])
            common.append(sat)
        return epoch.t_gps, common, sr, sb, model_r, model_b

    def _manage(self, eng, t, common, sr, sb) -> None:
        """Add, reset and drop ambiguity blocks from the receivers' flags and the satellites seen."""
        cfg = self.cfg
        for sat in common:
            for s in self.sig.get(sat[:1], ()):
                key = (sat, s)
                r, q = sr[sat], sb[sat]
                ok = s in r.phase_cyc and s in q.phase_cyc and s in r.code_m and s in q.code_m \
                    and not r.half_cycle.get(s, False) and not q.half_cycle.get(s, False)
                lock = r.lock_time_s.get(s, math.nan)
                prev_lock = self._rover_lock.get(key)
                self._rover_lock[key] = lock
                a = self.amb.get(key)
                if a is not None:
                    slipped = r.slip.get(s, False) or (prev_lock is not None and math.isfinite(lock)
                                                       and math.isfinite(prev_lock) and lock < prev_lock)
                    base_slipped = self._base_slips_of(key) != a.base_slips
                    gap = t - a.last_seen
                    # a gap in the rover's data (a link outage: nothing arrived) is bridged only when
                    # the receiver's lock time says it tracked the carrier all through it (its lock
                    # began before the last epoch we saw): the ambiguity has not changed
                    lost = gap > cfg.max_gap_s and not (math.isfinite(lock) and lock >= gap)
                    if slipped or base_slipped or not ok or lost:
                        self._drop_amb(eng, key)
                        self.counters["rtk ambiguities reset: slip flag / lock time / gap"] += 1
                        a = None
                if ok:
                    self._ensure_iono(eng, sat, r.elevation_rad)
                if ok and a is None:
                    lam = r.wavelength_m[s]
                    n0 = (r.phase_cyc[s] - q.phase_cyc[s]) - (r.code_m[s] - q.code_m[s]) / lam
                    self._add_amb(eng, key, n0, lam, t)
                if ok:
                    if t - self.amb[key].last_seen > cfg.max_gap_s:
                        self.counters["rtk ambiguities kept through a data gap (lock time)"] += 1
                    self.amb[key].last_seen = t
        for key in [k for k, a in self.amb.items() if t - a.last_seen > cfg.max_gap_s]:
            self._drop_amb(eng, key)
            self.counters["rtk ambiguities dropped: satellite lost"] += 1
        self._prune_iono(eng)

    def _sd_residual(self, eng, key, sr, sb, model_r, model_b, ion: dict) -> float:
        """The SD phase residual (m) at the INS point; ``ion``: :meth:`_iono_values`."""
        sat, s = key
        a = self.amb[key]
        lam = a.wavelength_m
        sd_phi = lam * (sr[sat].phase_cyc[s] - sb[sat].phase_cyc[s])
        return (sd_phi - (model_r[sat][0] - model_b[sat][0]) - lam * float(eng.block_states[a.name][0])
                + iono_factor(lam) * ion.get(sat, 0.0))

    def _slip_test(self, eng, t, common, sr, sb, model_r, model_b) -> None:
        """INS-predicted phase: per ambiguity, the change of its SD residual since the last epoch,
        minus the median change of the signal (the receiver clocks); a jump re-initialises it."""
        cfg = self.cfg
        L = eng.layout
        P = eng.kf.P
        sig_v2 = float(np.trace(P[L.vel, L.vel])) / 3.0
        ion = self._iono_values(eng)
        for sys, s in self._groups:
            keys, d, var = [], [], []
            for sat in common:
                if sat[:1] != sys:
                    continue
                key = (sat, s)
                prev = self._resid.get(key)
                if key not in self.amb or prev is None or not 0.0 < t - prev[0] <= cfg.slip_max_interval_s:
                    continue
                e = self._sd_residual(eng, key, sr, sb, model_r, model_b, ion)
                keys.append(key)
                d.append(e - prev[1])
                v = sd_variance_m2(sr[sat].elevation_rad, "phase", cfg.sigma_phase_a_m, cfg.sigma_phase_b_m, 1.0)
                var.append(2.0 * v + sig_v2 * (t - prev[0]) ** 2)
            if len(keys) < 4:
                continue
            med = _median(d)
            for key, di, vi in zip(keys, d, var):
                if abs(di - med) > max(cfg.slip_min_m, cfg.slip_sigmas * math.sqrt(vi)):
                    a = self.amb[key]
                    self._drop_amb(eng, key)
                    sat = key[0]
                    lam = a.wavelength_m
                    n0 = (sr[sat].phase_cyc[s] - sb[sat].phase_cyc[s]) - (sr[sat].code_m[s] - sb[sat].code_m[s]) / lam
                    self._add_amb(eng, key, n0, lam, t)
                    self.counters["rtk slips detected: INS-predicted phase"] += 1

    def build(self, eng, obs, l_e: np.ndarray, v_ant_e: np.ndarray,
              code_variance_factor: float = 1.0) -> RtkEpochRows | None:
        """DD phase and code rows (innovations at the INS point, Jacobians over the engine's
        layout, DD covariance) of the modelled epoch ``obs`` (:meth:`observe`): phase rows then
        code rows, each (system, signal) a run of rows against its reference, so that the DD
        covariance is block diagonal, a block ``v_ref + diag(v_i)`` per run."""
        t, common, sr, sb, model_r, model_b = obs
        cfg = self.cfg
        L = eng.layout
        n = L.n
        bs = eng.block_states
        amb = self.amb
        sa, sb_, ratio = cfg.sigma_phase_a_m, cfg.sigma_phase_b_m, cfg.code_phase_ratio
        var_ph = {q: sd_variance_m2(sr[q].elevation_rad, "phase", sa, sb_, ratio) for q in common}
        refs, pairs, cols, iono_cols = {}, [], [], []
        z_ph, z_co, lab_ph, lab_co, lam_ph, lam_ref_ph, du = [], [], [], [], [], [], []
        iono = self.iono
        ion = self._iono_values(eng)
        col = {b.name: b.start for b in L.extra_blocks()}     # the one-state blocks' columns
        runs = []               # per (system, signal): (own SD variances, reference's), phase
        for sys, s in self._groups:
            sats = [q for q in common if q[:1] == sys and (q, s) in amb]
            if len(sats) < 2:
                continue
            ref = max(sats, key=lambda q: sr[q].elevation_rad)
            refs[(sys, s)] = ref
            kref = (ref, s)
            ar = amb[kref]
            rr, br = sr[ref], sb[ref]
            sd_phi_ref = rr.phase_cyc[s] - br.phase_cyc[s]
            sd_code_ref = rr.code_m[s] - br.code_m[s]
            rho_ref = model_r[ref][0] - model_b[ref][0]
            u_ref = model_r[ref][1]
            n_ref = float(bs[ar.name][0])
            col_ref = col[ar.name]
            i_ref = ion.get(ref, 0.0)
            lam_ref = ar.wavelength_m
            own = []
            for sat in sats:
                if sat == ref:
                    continue
                key = (sat, s)
                a = amb[key]
                lam = a.wavelength_m
                q, qb = sr[sat], sb[sat]
                dd_rho = (model_r[sat][0] - model_b[sat][0]) - rho_ref
                # GLONASS FDMA: the reference's carrier differs (k = 1 for the CDMA systems, exactly)
                k_ref = lam_ref / lam
                # the ionosphere advances the phase and delays the code
                dd_iono = iono_factor(lam) * (ion.get(sat, 0.0) - i_ref * k_ref * k_ref) if iono else 0.0
                z_ph.append(lam * ((q.phase_cyc[s] - qb.phase_cyc[s]) - sd_phi_ref * k_ref) - dd_rho
                            - lam * (float(bs[a.name][0]) - n_ref * k_ref) + dd_iono)
                z_co.append(((q.code_m[s] - qb.code_m[s]) - sd_code_ref) - dd_rho - dd_iono)
                if iono:
                    iono_cols.append((col[iono[sat]], col[iono[ref]]))
                du.append(model_r[sat][1] - u_ref)
                lam_ph.append(lam)
                lam_ref_ph.append(lam_ref)
                cols.append((col[a.name], col_ref))
                pairs.append((key, kref))
                lab_ph.append(f"{sat}-{ref} {s} phase")
                lab_co.append(f"{sat}-{ref} {s} code")
                own.append(var_ph[sat])
            runs.append((own, var_ph[ref]))
        if not z_ph:
            self.counters["rtk epochs without DD rows"] += 1
            return None
        k = len(z_ph)
        DU = np.array(du)
        H = np.zeros((2 * k, n))
        H[:k, L.pos] = -DU
        H[:k, L.att] = DU @ skew(l_e)
        H[:k, L.toff] = DU @ v_ant_e
        H[k:, :] = H[:k, :]
        c = np.array(cols)
        lam = np.array(lam_ph)
        rk = np.arange(k)
        lam_ref = np.array(lam_ref_ph)
        H[rk, c[:, 0]] = lam
        H[rk, c[:, 1]] = -lam_ref
        if iono_cols:
            ci = np.array(iono_cols)
            mu, mu_ref = iono_factor(lam), iono_factor(lam_ref)
            H[rk, ci[:, 0]] = -mu
            H[rk, ci[:, 1]] = mu_ref
            H[k + rk, ci[:, 0]] = mu
            H[k + rk, ci[:, 1]] = -mu_ref
        # the DD covariance: phase runs, then the same runs for the code (x ratio^2 x factor)
        R = np.zeros((2 * k, 2 * k))
        code_f = ratio ** 2
        i = 0
        for own, v_ref in runs:
            m = len(own)
            for kind, off, f in (("phase", 0, None), ("code", k, code_variance_factor)):
                blk = R[off + i:off + i + m, off + i:off + i + m]
                if f is None:
                    blk[...] = v_ref
                    blk[np.diag_indices(m)] += own
                else:
                    blk[...] = f * (v_ref * code_f)
                    blk[np.diag_indices(m)] = [f * (v_ref * code_f) + f * (v * code_f) for v in own]
            i += m
        sd_resid = {}
        for key, a in amb.items():
            if key[0] in model_r:
                sd_resid[key] = (self._sd_residual(eng, key, sr, sb, model_r, model_b, ion), model_r[key[0]][1],
                                 float(bs[a.name][0]), ion.get(key[0], 0.0))
        return RtkEpochRows(t, np.array(z_ph + z_co), H, R, ["phase"] * k + ["code"] * k,
                            lab_ph + lab_co, refs, pairs, sd_resid, amb_cols=c)

    # ------------------------------------------------------------------ gating and batches
    def gate(self, eng, rows: RtkEpochRows) -> tuple[list[MeasurementBatch], list[UpdateReport]]:
        """Per-row chi-square test against the predicted variance (correlations ignored for the
        test only).  A failing phase row of a held ambiguity set means a wrong fix (dropped at
        once); any other failing phase row re-initialises that satellite's ambiguity.  Returns the
        whitened phase and code batches with their reports.  The products on the columns the
        rows touch only (the INS core, the ambiguities of the signals present)."""
        P = eng.kf.P
        cols = np.flatnonzero(np.any(rows.H != 0.0, axis=0))
        Hc = rows.H[:, cols]
        Pc = P[np.ix_(cols, cols)]
        S = np.einsum("ij,ij->i", Hc @ Pc, Hc) + np.diag(rows.R)
        ratio = rows.z ** 2 / (S * self.gate_chi2)
        ok = np.isfinite(ratio) & (ratio <= 1.0)
        phase = np.array([k == "phase" for k in rows.kinds])
        bad_phase = np.flatnonzero(phase & ~ok)
        keep = ok.copy()
        if len(bad_phase):
            # per system: more than one held row failing, or most of the system's rows
            sys_of = [rows.amb_pairs[i][0][0][:1] if phase[i] else "" for i in range(len(phase))]
            held_sys = {k[0][:1] for k in self.held}
            wrong = set()
            for sys in held_sys:
                mine = [i for i in range(len(phase)) if phase[i] and sys_of[i] == sys]
                bad = [i for i in bad_phase if sys_of[i] == sys]
                held_bad = [i for i in bad if rows.amb_pairs[i][0] in self.held]
                if mine and (len(held_bad) > 1 or len(bad) > 0.5 * len(mine)):
                    wrong.add(sys)
            if wrong:
                self.counters["rtk wrong fixes dropped: phase residuals"] += 1
                if wrong >= held_sys:
                    self._wrong_fix(eng)
                    return [], []
                self._wrong_fix_systems(eng, wrong)
                drop = np.array([s in wrong for s in sys_of]) | np.array(
                    [rows.labels[i][:1] in wrong for i in range(len(phase))])
                keep &= ~drop          # that system's rows (phase and code) out of this epoch
            for i in bad_phase:       # the row's own satellite: its ambiguity starts again after this epoch
                if sys_of[i] in wrong:
                    continue
                self.counters["rtk phase rows rejected: innovation gate"] += 1
                self._reset_after.add(rows.amb_pairs[i][0])
        rows.keep = keep
        batches, reports = [], []
        n = rows.H.shape[1]
        P = eng.kf.P                  # a wrong fix of some systems widened it
        Pc = P[np.ix_(cols, cols)]
        for kind in ("phase", "code"):
            sel = np.flatnonzero(keep & (phase if kind == "phase" else ~phase))
            if not len(sel):
                continue
            C = cholesky_lower(rows.R[np.ix_(sel, sel)])
            B = np.empty((len(sel), len(cols) + 1), order="F")
            B[:, :-1] = Hc[sel]
            B[:, -1] = rows.z[sel]
            X = solve_lower(C, B)
            zw = X[:, -1].copy()
            Hwc = X[:, :-1]
            Hw = np.zeros((len(sel), n))
            Hw[:, cols] = Hwc
            labels = [rows.labels[i] for i in sel]
            b = MeasurementBatch(f"rtk_{kind}", labels, zw, Hw, np.ones(len(sel)))
            Sw = np.einsum("ij,ij->i", Hwc @ Pc, Hwc) + 1.0
            reports.append(UpdateReport(b.kind, labels, zw, Sw, ratio[sel], np.ones(len(sel), bool), {}))
            batches.append(b)
            self.counters[f"rtk_{kind} used"] += len(sel)
        self.counters["rtk code rows rejected: innovation gate"] += int(np.count_nonzero(~phase & ~ok))
        return batches, reports

    def _wrong_fix_systems(self, eng, systems) -> None:
        """A wrong fix of some systems only: their ambiguities start again after this epoch (the
        layout must not change under the epoch's rows), the position covariance widened."""
        for key in self.amb:
            if key[0][:1] in systems:
                self._reset_after.add(key)
        self.held = {k for k in self.held if k[0][:1] not in systems}
        L = eng.layout
        eng.kf.P[L.pos, L.pos] += np.eye(3) * self.cfg.wrong_fix_position_sigma_m ** 2

    def _wrong_fix(self, eng) -> None:
        self._drop_all(eng)
        L = eng.layout
        eng.kf.P[L.pos, L.pos] += np.eye(3) * self.cfg.wrong_fix_position_sigma_m ** 2
        self.status = RtkStatus(FIX_NONE, math.nan, 0, 0, self.status.t_gps)

    # ------------------------------------------------------------------ integers
    def resolve(self, eng, rows: RtkEpochRows, dx_float: np.ndarray) -> RtkStatus:
        """LAMBDA on the DD ambiguities after the float update; a validated fix is held (applied to
        the filter).  Returns the epoch's fix status."""
        cfg = self.cfg
        L = eng.layout
        keep = rows.keep if rows.keep is not None else np.ones(len(rows.z), bool)
        ph = [i for i, k in enumerate(rows.kinds) if k == "phase" and keep[i]
              and rows.amb_pairs[i][0][0][:1] not in cfg.float_only_systems]
        pairs = [rows.amb_pairs[i] for i in ph]
        n_dd = len(pairs)
        if n_dd < cfg.min_fix_ambiguities:
            return self._set_status(rows.t_gps, FIX_FLOAT, math.nan, 0, n_dd)
        if rows.amb_cols is not None:
            ac = rows.amb_cols[ph]
        else:
            ac = np.array([(L.index(self.amb[k].name), L.index(self.amb[r].name)) for k, r in pairs]).reshape(-1, 2)
        # T (n_dd x n) maps the states to the DD ambiguities; Tc on the columns it touches
        idx = np.unique(ac)
        pos = np.searchsorted(idx, ac)
        rk = np.arange(n_dd)
        Tc = np.zeros((n_dd, len(idx)))
        Tc[rk, pos[:, 0]] = 1.0
        Tc[rk, pos[:, 1]] = -1.0
        bs = eng.block_states
        a = np.array([float(bs[self.amb[k].name][0] - bs[self.amb[r].name][0]) for k, r in pairs])
        P = eng.kf.P
        P_idx = P[:, idx]
        Qa_full = Tc @ P_idx[idx] @ Tc.T
        active = list(np.argsort(-np.diag(Qa_full)))        # the least certain first out
        while len(active) >= cfg.min_fix_ambiguities:
            sel = np.array(sorted(active))
            out = self._try(eng, rows, dx_float, P_idx, Tc[sel], a[sel], Qa_full[np.ix_(sel, sel)])
            if out is not None:
                res, afix = out
                if len(sel) < n_dd:
                    self.counters["rtk epochs fixed partially"] += 1
                self.counters["rtk fixed epochs"] += 1
                if not self.held:
                    self.counters["rtk fixes (from float)"] += 1
                T = np.zeros((len(sel), L.n))
                T[:, idx] = Tc[sel]
                self._hold(eng, T, a[sel], afix)
                self.held = {pairs[i][0] for i in sel} | {pairs[i][1] for i in sel}
                st = self._set_status(rows.t_gps, FIX_FIXED, res.ratio, len(sel), n_dd)
                st.success_rate = res.success_rate
                return st
            active.pop(0)
        self.counters["rtk float epochs"] += 1
        if self.held:
            self.counters["rtk fixes lost (float again)"] += 1
        self.held = set()
        return self._set_status(rows.t_gps, FIX_FLOAT, math.nan, 0, n_dd)

    def _set_status(self, t, state, ratio, n_fixed, n_dd) -> RtkStatus:
        self.status = RtkStatus(state, ratio, n_fixed, n_dd, t)
        return self.status

    def _try(self, eng, rows, dx_float, P_idx, Tc, a, Qa):
        """One LAMBDA candidate set: ``Tc`` its rows of T on the ambiguity columns ``P_idx`` (P's
        columns there), ``Qa`` = Tc P Tc^T.  The fix validated, or None."""
        cfg = self.cfg
        try:
            res = lambda_ils(a, Qa, m=2)
        except (np.linalg.LinAlgError, RuntimeError):
            self.counters["rtk lambda failures"] += 1
            return None
        if not res.ratio >= cfg.ratio_threshold:
            return None
        if not res.success_rate >= cfg.min_success_rate:
            self.counters["rtk fixes rejected: success rate"] += 1
            return None
        afix = res.fixed[:, 0]
        PTt = P_idx @ Tc.T
        S = Qa + np.eye(len(a)) * cfg.hold_sigma_cycles ** 2
        dx_hold = PTt @ np.linalg.solve(S, afix - a)
        # the fixed phase residuals against their own noise (the pre-update rows, linear model)
        keep = rows.keep if rows.keep is not None else np.ones(len(rows.z), bool)
        ph = np.flatnonzero(keep & np.array([k == "phase" for k in rows.kinds]))
        if len(ph):
            v = rows.z[ph] - rows.H[ph] @ (dx_float + dx_hold)
            zr = np.abs(v) / np.sqrt(np.diag(rows.R)[ph])
            if float(zr.max()) > cfg.fixed_residual_sigma:
                self.counters["rtk fixes rejected: phase residuals"] += 1
                return None
        L = eng.layout
        G = PTt[L.pos]                                       # cov(position, DD ambiguities)
        P_pos_fixed = eng.kf.P[L.pos, L.pos] - G @ np.linalg.solve(S, G.T)
        # ... at the epoch: an epoch applied late (a backlog after a gap) leaves the INS drift since
        # then in the current position, up to the velocity sigma times the delay
        late_s = max(0.0, eng.t_gps - rows.t_gps)
        limit_m = cfg.max_fixed_sigma_3d_m + late_s * math.sqrt(max(float(np.trace(eng.kf.P[L.vel, L.vel])), 0.0))
        if not float(np.trace(P_pos_fixed)) <= limit_m ** 2:
            self.counters["rtk fixes rejected: position not pinned"] += 1
            return None
        # against the INS prediction: the position the fix implies, relative to the predicted one
        if rows.P_prior_pos is not None:
            d = dx_float[L.pos] + dx_hold[L.pos]
            if float(d @ np.linalg.solve(rows.P_prior_pos, d)) > self.ins_chi2_3:
                self.counters["rtk fixes rejected: INS prediction"] += 1
                return None
        return res, afix

    def _hold(self, eng, T, a, afix) -> None:
        """Fix-and-hold: the fixed DD ambiguities as a measurement of the whole filter."""
        b = MeasurementBatch("rtk_hold", [f"dd{i}" for i in range(len(a))], afix - a, T,
                             np.full(len(a), self.cfg.hold_sigma_cycles ** 2))
        rep = UpdateReport(b.kind, b.labels, b.z, np.ones(len(a)), np.zeros(len(a)), np.ones(len(a), bool), {})
        dx = eng.kf.update([b], [rep])
        eng._feedback(dx)
        self.last_hold_dx = dx

    # ------------------------------------------------------------------ after the epoch
    def finish(self, eng, rows: RtkEpochRows | None, dx_total: np.ndarray) -> None:
        """End of the epoch: re-initialise the ambiguities whose rows failed, and store each
        ambiguity's post-update SD residual for the next epoch's slip test."""
        for key in self._reset_after:
            self._drop_amb(eng, key)
        self._reset_after.clear()
        self._prune_iono(eng)
        if rows is None:
            return
        L = eng.layout
        dr = dx_total[L.pos]
        ion = self._iono_values(eng)
        for key, (e_pre, u, n_pre, i_pre) in rows.sd_resid.items():
            a = self.amb.get(key)
            if a is None:
                continue
            n_post = float(eng.block_states[a.name][0])
            i_post = ion.get(key[0], 0.0)
            self._resid[key] = (rows.t_gps, e_pre + float(u @ dr) - a.wavelength_m * (n_post - n_pre)
                                + iono_factor(a.wavelength_m) * (i_post - i_pre))


def _median(x: list) -> float:
    """np.median of a short list of floats, without its overhead (the same value: the middle
    element, or the two middle ones' sum halved)."""
    v = sorted(x)
    if not all(map(math.isfinite, v)):
        return float(np.median(x))
    m = len(v) // 2
    return v[m] if len(v) % 2 else (v[m - 1] + v[m]) / 2.0


def _up(llh) -> np.ndarray:
    return -C_n_e(llh[0], llh[1])[:, 2]


def _model_ranges_m(r_rx_e: np.ndarray, sats: list):
    """:func:`~companion.gnss.double_difference.model_range_m` of several satellites at once
    (rho + troposphere - satellite clock, unit lines of sight), and their elevations (rad): the
    receiver's zenith delay once, the mapping per satellite (as ``tropo_delay_m``)."""
    llh = ecef_to_geodetic(r_rx_e)
    up = _up(llh)
    d = np.array([q.r_sat_e for q in sats]) - r_rx_e
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    U = d / rho[:, None]
    sin_el = U @ up
    el = np.arcsin(np.clip(sin_el, -1.0, 1.0))
    tropo = np.zeros(len(sats))
    if -1000.0 <= llh[2] <= 20000.0:
        zhd, zwd = saastamoinen_zenith_m(llh[0], llh[2])
        s = np.sin(np.maximum(el, _ONE_DEG_RAD))      # elevation floored at 1 deg, as model_range_m
        tropo = (zhd + zwd) * (1.001 / np.sqrt(0.002001 + s * s))
    clock = np.array([q.clock_m for q in sats])
    return rho + tropo - clock, U, el


_ONE_DEG_RAD = math.radians(1.0)
