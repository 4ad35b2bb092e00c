"""Carrier-phase RTK against a base station: double-differenced code and phase on every frequency,
float ambiguities in a Kalman filter, integers by LAMBDA with partial fixing and fix-and-hold.

The shape is RTKLIB's relative positioning (``rtkpos.c``), written from its documented model:

* **State**: rover antenna position ``r_e`` (3, m) and one *between-receiver single-difference*
  ambiguity per (satellite, signal) in cycles, ``N = N_rover - N_base``, added when the satellite
  is acquired or after a slip, dropped when it is lost.  Single differences as states make the
  reference satellite a choice of the measurement, not of the state (RTKLIB's ``IB(s,f)``).
* **Systems**: GPS, Galileo, BeiDou and QZSS (``systems``), and GLONASS with float ambiguities
  only (:data:`FLOAT_ONLY_SYSTEMS`), each on its own signals
  (:data:`companion.rtk_signals.RTK_SIGNALS_BY_SYSTEM` among ``signals``; the epochs renamed to
  their tracking families first, :func:`companion.rtk_signals.rtk_epoch`) and differenced within
  the system only (a reference per system and signal: no inter-system bias, as RTKLIB's ``ddres``
  per system, except that QZSS has its own reference here).  A GPS L2 that the rover tracks only
  as L2C and the base only as P(Y) is paired across the families in a group of its own
  (:func:`~.double_difference.cross_pair`).
* **Measurements** per system and frequency, against the highest-elevation satellite ``j``:
  ``DD phase  = lambda_i dphi_i - lambda_j dphi_j = DD rho + lambda_i N_i - lambda_j N_j + e``
  (one wavelength for every satellite but GLONASS's),
  ``DD code   = dP_i - dP_j = DD rho + e`` with ``d = rover - base`` and ``rho`` the geometric
  range (satellite at its own transmit time from each receiver's pseudorange, Sagnac rotation,
  satellite clock) plus the Saastamoinen troposphere at each receiver's height; receiver clocks
  cancel in the between-satellite difference, satellite clocks, orbits and (on short baselines)
  the atmosphere in the between-receiver one.  Per-receiver variance ``a^2 + b^2 / sin^2(el)``
  (RTKLIB's default 3 mm + 3 mm), code ``code_phase_ratio`` x phase; the DD covariance carries
  the reference satellite's share in every row.
* **Ionosphere** (``iono_states``, off by default as in RTKLIB and demo5): one SD slant delay
  per satellite on L1's frequency (:mod:`.differential_iono`, the engine's model), in every DD
  row of its satellite: ``-(lambda / lambda_L1)^2`` of it on the phase, ``+`` on the code; the
  fixed solution conditions it on the integers as it does the position.
* **Antennas** (``rover_antenna``, ``base_antenna``: :mod:`.antenna_calibration`): each
  receiver's phase and code, per frequency, moved from the phase centre to its ARP by the
  calibration's offset along the line of sight and its variation
  (:func:`~.double_difference.at_reference_point`; RTKLIB's ``antmodel``); without one a
  receiver's phase centres are at its ARP.
* **Kinematic**: every epoch the position prior is the previous solution with ``position_sigma_m``
  (30 m: no dynamics are assumed); **static**: the position is a constant.  Iterated update
  (``iterations``), so the 30-m prior does not bias the linearisation.
* **Base epochs**: each rover epoch is solved against the nearest base epoch within
  ``max_base_age_s`` (a slower base, e.g. a 30-s CORS file, serves every rover epoch); each
  receiver is modelled at its own epoch, and the satellite clocks' drift over the age
  (``sat_clock_stability``) is added to the variances, as RTKLIB does.  A base epoch used again
  brings no new slip.
* **Slips**: the receiver's loss-of-lock flag, or a jump of the geometry-free phase
  ``lambda_1 phi_1 - lambda_2 phi_2`` (the satellite's first two signals) of either receiver by more than ``slip_gf_m`` between
  epochs, resets that satellite's ambiguities; a gap longer than ``max_gap_s`` too.
* **Integer resolution**: the float DD ambiguities ``a = T x`` with covariance ``T P T^T`` go to
  LAMBDA; accepted when the ratio test passes (``ratio_threshold``), the fix pins the position
  (3-D sigma at most ``max_fixed_sigma_3d_m``) and the fixed phase residuals stay within
  ``fixed_residual_sigma`` of their noise (a wrong fix shows there).  Otherwise partial fixing: one
  satellite's ambiguities after another are left float and the rest tried again (first those
  younger than ``young_ambiguity_s``, then the others, each group lowest first), down to
  ``min_fix_ambiguities`` and to ``min_fix_fraction`` of the epoch's DD ambiguities.  The fixed
  position is ``r - Q_ra Q_a^-1 (a - a_fix)``.
* **Fix-and-hold**: after ``hold_after_fixes`` consecutive fixed epochs the fixed DD ambiguities
  are fed back to the float filter as measurements (``hold_sigma_cycles``), so the next epochs
  start from them.
* **Why these limits** (tests/test_rtk_car_15km.py, a real car 15 km from its base): without the
  pinning, the fraction and the hold delay, 69 of 139 epochs that two independent systems both
  fixed were 0.1-11 m apart; with them 0 of 50.

Solution quality as RTKLIB's Q: 1 fixed, 2 float.
"""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from ..messages import SPEED_OF_LIGHT_MPS, GnssEpoch
from ..nav.earth import ecef_to_geodetic
from ..rtk_signals import RTK_SIGNALS, signals_for_system
from .antenna_calibration import AntennaCalibration
from .differential_iono import iono_factor, prior_sigma_m as iono_prior_sigma_m, random_walk_psd
from .double_difference import (ReceiverSat, at_reference_point, cross_pair, dd_covariance, elevation_rad,
                                model_range_m, receiver_sats, sd_variance_m2)
from .ephemeris_store import EphemerisStore
from .lambda_kernel import lambda_ils      # compiled when numba is there, the same results

Q_FIX, Q_FLOAT = 1, 2

#: systems whose ambiguities stay float unless ``glonass_ar`` is 'on' (RTKLIB's gloarmode off):
#: GLONASS's FDMA carriers differ per satellite, so a DD ambiguity lambda_i N_i - lambda_j N_j is not
#: an integer of one wavelength, and each receiver make has its own inter-channel phase biases; a
#: float single-difference ambiguity per satellite absorbs both, and the satellites still add
#: geometry to the float solution.  With the biases equal (one receiver model at both ends) the
#: integer is N_i - N_j, and the DD phase lambda_i (N_i - N_j) + (lambda_i - lambda_j) N_j
FLOAT_ONLY_SYSTEMS = "R"
GLONASS_AR_OPTIONS = ("auto", "on", "off")


@dataclass
class RtkConfig:
    signals: tuple[str, ...] = RTK_SIGNALS         # canonical family codes (L2W = RINEX 2 L2/P2), per system
    systems: str = "GECJ"                          # each differenced within itself
    elevation_mask_deg: float = 10.0               # the product's mask (filter.elevation_mask_deg)
    phase_sigma_a_m: float = 0.003
    phase_sigma_b_m: float = 0.003
    code_phase_ratio: float = 100.0
    dynamics: str = "kinematic"                    # or 'static'
    position_sigma_m: float = 30.0                 # kinematic position prior each epoch
    iterations: int = 3
    ambiguity_init_sigma_cycles: float = 60.0
    ambiguity_psd_cycles2ps: float = 1e-8
    slip_gf_m: float = 0.05
    max_gap_s: float = 150.0
    # a rover epoch is solved against the nearest base epoch this close in time (RTKLIB's maxtdiff):
    # a 1-Hz rover against a 30-s CORS file.  Each receiver is modelled at its own epoch, so what the
    # age leaves in the double differences is the change of the atmosphere and of the broadcast
    # orbit and clock errors over it (millimetres over seconds)
    max_base_age_s: float = 30.0
    # the satellite clocks' stability (RTKLIB's sclkstab, 5e-12 s/s): the part of a clock the
    # broadcast polynomial misses drifts over the base's age, so each SD gets (c x this x age)^2 more
    # variance (1.5 cm at 10 s)
    sat_clock_stability: float = 5e-12
    max_phase_innovation_m: float = 5.0            # a DD phase row further than this off is rejected
    ratio_threshold: float = 3.0
    # bootstrapped success rate of the (partial) set (a lower bound of LAMBDA's): 0 = not tested.
    # The engine asks 0.999; here GEONET's first epoch, fixed right at ratio 25, has 0.976, and on
    # a car 15 km from its base the test took out 1 of 4 fixes that disagree between systems
    min_success_rate: float = 0.0
    # a fix must pin the position (3-D sigma at most this): integers that leave it at decimetres are
    # not tied to the geometry (as the engine's RtkUpdateConfig.max_fixed_sigma_3d_m)
    max_fixed_sigma_3d_m: float = 0.10
    min_fix_ambiguities: int = 4
    # partial fixing keeps at least this share of the epoch's DD ambiguities: a small subset passes
    # the ratio test easily and can be wrong together (a car 15 km from its base: 6 of 35 fixed at
    # ratio 18, 0.1-4 m off its GPS-only solution)
    min_fix_fraction: float = 0.5
    # partial fixing leaves float first the satellites with an ambiguity younger than this (a new
    # satellite, or one reset by a slip: its float is still the code's metres), lowest first, then
    # the rest by elevation.  The car 15 km from its base, its Galileo slipping every few seconds in
    # town: G+E+C 41 -> 84 fixed epochs in 6 min (108 -> 228 in 20), the same share of its
    # independent systems' fixes apart (README)
    young_ambiguity_s: float = 10.0
    fixed_residual_sigma: float = 4.0
    fix_and_hold: bool = True
    # hold only after this many consecutive fixed epochs (RTKLIB's minfix, 10): a single wrong fix
    # held would pull the float filter onto its integers, and the next epochs would confirm it
    hold_after_fixes: int = 10
    hold_sigma_cycles: float = 0.03
    # GLONASS integers too (RTKLIB's gloarmode on): 'on' only for two receivers of one model, whose
    # inter-channel phase biases cancel between them; 'off' keeps GLONASS float; 'auto' is decided
    # by companion.gnss.rtk_post from the two receivers' types (the filter alone takes it for 'off')
    glonass_ar: str = "auto"
    # the differential ionosphere as states (RTKLIB's ionoopt est; the engine's model,
    # companion.gnss.differential_iono): one between-receiver SD slant delay per satellite, in
    # metres on L1's frequency, while any of its ambiguities lives; prior at acquisition
    # (iono_sigma_zenith_m + iono_sigma_ppm x baseline) through the single-layer slant factor, a
    # random walk of that sigma over iono_correlation_time_s.  Off: the DD ionosphere is taken as
    # zero (RTKLIB's and demo5's default), which a few kilometres of baseline already make
    # centimetres of position (README)
    iono_states: bool = False
    iono_sigma_zenith_m: float = 0.001
    iono_sigma_ppm: float = 1.0
    iono_correlation_time_s: float = 900.0


@dataclass
class RtkSolution:
    t_gps: float
    r_e: np.ndarray                 # rover antenna position (m)
    cov_e: np.ndarray               # 3x3 (m^2)
    quality: int                    # 1 fixed, 2 float
    n_sats: int
    ratio: float
    n_fixed: int = 0                # DD ambiguities fixed
    n_ambiguities: int = 0          # DD ambiguities formed
    success_rate: float = float("nan")
    counters: dict = field(default_factory=dict)
    n_sats_by_system: dict = field(default_factory=dict)   # system letter -> satellites above the mask
    age_s: float = 0.0              # rover epoch minus the base epoch it was solved against


_Sat = ReceiverSat
_receiver_sats = receiver_sats
_elevation = elevation_rad
_model_m = model_range_m


#: _try_fix's answer when the set is below the partial-fixing floor
_TOO_FEW = object()


def _half_cycle(q: ReceiverSat, signal: str) -> bool:
    return bool(q.half_cycle and q.half_cycle.get(signal, False))


class RtkFilter:
    """Feed epoch pairs with :meth:`process` (a rover epoch, the base epoch nearest to it)."""

    def __init__(self, base_r_e, store: EphemerisStore, config: RtkConfig = RtkConfig(), backward: bool = False,
                 rover_antenna: AntennaCalibration | None = None, base_antenna: AntennaCalibration | None = None):
        self.cfg = config
        # the receivers' phase centres relative to their ARPs (none: each carrier's centre at the ARP)
        self.rover_antenna, self.base_antenna = rover_antenna, base_antenna
        # epochs fed newest first (the backward pass of a combined solution): a receiver's
        # loss-of-lock flag at epoch k means a slip between k - 1 and k, so it resets the
        # ambiguities at the next epoch fed (k - 1), not at k; a base flag at the next base epoch
        self.backward = backward
        self._rover_flags_ahead: set[str] = set()
        self._base_flags_ahead: set[str] = set()
        self.base_r_e = np.asarray(base_r_e, dtype=float)
        self._base_llh = ecef_to_geodetic(self.base_r_e)
        self._base_models: tuple = (None, {})     # (the epoch's base satellites, sat -> model)
        self.store = store
        self.x = np.zeros(3)
        self.P = np.eye(3) * config.position_sigma_m ** 2
        self.amb: dict[tuple[str, str], int] = {}          # (sat, signal) -> state index
        self.iono: dict[str, int] = {}                    # sat -> its SD ionosphere's state index
        self._iono_psd: dict[str, float] = {}             # sat -> its random walk's PSD (m^2/s)
        self.last_seen: dict[tuple[str, str], float] = {}
        self.amb_since: dict[tuple[str, str], float] = {}      # when each ambiguity was (re)started
        self.last_gf: dict[tuple, float] = {}    # (sat, 'rover'|'base', second signal) -> GF phase (m)
        self.t_last: float | None = None
        self.consecutive_fixes = 0
        self._base_t: float | None = None       # the base epoch of the last solution (reused: no new slips)
        self._age_s = 0.0
        self.initialized = False
        self.counters: dict[str, int] = {}
        self.sig: dict[str, tuple[str, ...]] = {}       # system -> its signals, positioning code first
        for sys in dict.fromkeys(config.systems):
            own = signals_for_system(sys, config.signals)
            if own:
                self.sig[sys] = own
        self._groups = [(sys, q) for sys, sigs in self.sig.items() for q in sigs]
        if config.glonass_ar not in GLONASS_AR_OPTIONS:
            raise ValueError(f"glonass_ar must be one of {', '.join(GLONASS_AR_OPTIONS)}, not {config.glonass_ar!r}")
        self._float_only = "" if config.glonass_ar == "on" else FLOAT_ONLY_SYSTEMS

    def _count(self, key: str, n: int = 1) -> None:
        self.counters[key] = self.counters.get(key, 0) + n

    # ------------------------------------------------------------------ state bookkeeping
    def _add_state(self, value: float, sigma: float) -> int:
        """A new state (its index), uncorrelated with the others."""
        n = len(self.x)
        self.x = np.append(self.x, value)
        P = np.zeros((n + 1, n + 1))
        P[:n, :n] = self.P
        P[n, n] = sigma ** 2
        self.P = P
        return n

    def _add_amb(self, key, value: float, t: float) -> None:
        """A new ambiguity state (sat, signal), started at ``t``."""
        self.amb[key] = self._add_state(value, self.cfg.ambiguity_init_sigma_cycles)
        self.amb_since[key] = t

    def _drop_amb(self, keys) -> None:
        self._drop_states(sorted(self.amb.pop(k) for k in keys if k in self.amb))

    def _drop_states(self, idx: list[int]) -> None:
        if not idx:
            return
        keep = np.setdiff1d(np.arange(len(self.x)), idx)
        self.x = self.x[keep]
        self.P = self.P[np.ix_(keep, keep)]
        remap = {int(old): new for new, old in enumerate(keep)}
        self.amb = {k: remap[i] for k, i in self.amb.items()}
        self.iono = {k: remap[i] for k, i in self.iono.items()}

    def _manage_iono(self, common, sr) -> None:
        """An ionosphere state for each satellite with an ambiguity, none for one without."""
        live = {k[0] for k in self.amb}
        gone = [q for q in self.iono if q not in live]
        for q in gone:
            self._iono_psd.pop(q, None)
        self._drop_states(sorted(self.iono.pop(q) for q in gone))
        baseline_m = float(np.linalg.norm(self.x[:3] - self.base_r_e))
        for q in common:
            if q in live and q not in self.iono:
                sigma = iono_prior_sigma_m(sr[q].elevation_rad, baseline_m, self.cfg.iono_sigma_zenith_m,
                                           self.cfg.iono_sigma_ppm)
                self.iono[q] = self._add_state(0.0, sigma)
                self._iono_psd[q] = random_walk_psd(sigma, self.cfg.iono_correlation_time_s)

    # ------------------------------------------------------------------ one epoch
    def process(self, rover: GnssEpoch, base: GnssEpoch, r_prior_e=None) -> RtkSolution | None:
        cfg = self.cfg
        sig = self.sig
        r_guess = self.x[:3].copy() if self.initialized else np.asarray(r_prior_e, dtype=float)
        # each receiver's carriers moved from their phase centres to its ARP, where the model is
        sb = at_reference_point(_receiver_sats(base, self.store, self.base_r_e, sig), self.base_antenna,
                                self.base_r_e, self._base_llh)
        sr = at_reference_point(_receiver_sats(rover, self.store, r_guess, sig), self.rover_antenna, r_guess)
        sr, sb = cross_pair(sr, sb)
        mask = math.radians(cfg.elevation_mask_deg)
        common = []
        for sat in sorted(set(sb) & set(sr)):
            el = _elevation(self.base_r_e, sb[sat].r_sat_e)
            if el >= mask:
                sr[sat].elevation_rad = sb[sat].elevation_rad = el
                common.append(sat)
            else:
                self._count("below mask")
        if len(common) < 2:
            self._count("epochs with fewer than 2 common satellites")
            return None
        t = rover.t_gps
        dt = 0.0 if self.t_last is None else abs(t - self.t_last)
        new_base = base.t_gps != self._base_t
        self._base_t, self._age_s = base.t_gps, t - base.t_gps
        self._predict(r_guess, dt)
        self._manage_ambiguities(t, common, sr, sb, new_base)
        used = self._update(common, sr, sb)
        self.t_last = t
        self.initialized = True
        if used < 2:
            self._count("epochs without a usable DD set")
            return None
        return self._resolve(t, common, sr, sb)

    def _predict(self, r_guess: np.ndarray, dt: float) -> None:
        cfg = self.cfg
        if cfg.dynamics == "kinematic" or not self.initialized:
            self.x[:3] = r_guess
            self.P[:3, :] = 0.0
            self.P[:, :3] = 0.0
            self.P[:3, :3] = np.eye(3) * cfg.position_sigma_m ** 2
        if dt > 0:
            for i in self.amb.values():
                self.P[i, i] += cfg.ambiguity_psd_cycles2ps * dt
            for q, i in self.iono.items():
                self.P[i, i] += self._iono_psd[q] * dt

    def _flagged(self, sats: dict) -> set[str]:
        """Satellites whose receiver flags a loss of lock on any of their signals at this epoch."""
        return {sat for sat, q in sats.items() if sat[:1] in self.sig
                and any(q.slip.get(s, False) for s in self.sig[sat[:1]])}

    def _manage_ambiguities(self, t: float, common, sr, sb, new_base: bool = True) -> None:
        cfg = self.cfg
        slipped = set()
        # a base epoch used again (a slower base) brings no new slip: its flags were seen
        receivers = (("rover", sr), ("base", sb)) if new_base else (("rover", sr),)
        rover_flags = self._flagged(sr)
        base_flags = self._flagged(sb) if new_base else set()
        if self.backward:
            rover_flags, self._rover_flags_ahead = self._rover_flags_ahead, rover_flags
            if new_base:
                base_flags, self._base_flags_ahead = self._base_flags_ahead, base_flags
        for sat in common:
            sigs = self.sig[sat[:1]]
            for who, sats in receivers:
                ph, lam = sats[sat].phase_cyc, sats[sat].wavelength_m
                have = [q for q in sigs if q in ph]
                if len(have) > 1 and have[0] == sigs[0]:
                    s1, s2 = have[0], have[1]
                    gf = lam[s1] * ph[s1] - lam[s2] * ph[s2]
                    prev = self.last_gf.get((sat, who, s2))
                    if prev is not None and abs(gf - prev) > cfg.slip_gf_m:
                        slipped.add(sat)
                        self._count("slips: geometry-free")
                    self.last_gf[(sat, who, s2)] = gf
            if sat in rover_flags or sat in base_flags:
                slipped.add(sat)
                self._count("slips: loss of lock flag")
        for sat in common:
            for s in self.sig[sat[:1]]:
                key = (sat, s)
                # a phase whose half cycle the receiver has not resolved (RINEX 3 LLI bit 1) is left
                # out until it has: the receiver then adds half a cycle, so a new ambiguity starts
                half = _half_cycle(sr[sat], s) or _half_cycle(sb[sat], s)
                if half:
                    self._count("phases with an unresolved half cycle")
                ok = s in sr[sat].phase_cyc and s in sb[sat].phase_cyc and s in sr[sat].code_m \
                    and s in sb[sat].code_m and not half
                stale = key in self.last_seen and abs(t - self.last_seen[key]) > cfg.max_gap_s
                if key in self.amb and (sat in slipped or stale or not ok):
                    self._drop_amb([key])
                    self._count("ambiguities reset")
                if ok and key not in self.amb:
                    lam = sr[sat].wavelength_m[s]
                    n0 = (sr[sat].phase_cyc[s] - sb[sat].phase_cyc[s]) - (sr[sat].code_m[s] - sb[sat].code_m[s]) / lam
                    self._add_amb(key, n0, t)
                    self._count("ambiguities added")
                if ok:
                    self.last_seen[key] = t
        lost = [k for k, ts in self.last_seen.items() if abs(t - ts) > self.cfg.max_gap_s and k in self.amb]
        self._drop_amb(lost)
        if cfg.iono_states:
            self._manage_iono(common, sr)

    # ------------------------------------------------------------------ double differences
    def _dd_rows(self, x: np.ndarray, common, sr, sb, *, fixed: dict | None = None):
        """(innovation z - h(x), H, R, keys) of every DD phase and code row at state ``x``."""
        r = x[:3]
        llh_r = ecef_to_geodetic(r)
        model_r = {sat: _model_m(r, sr[sat], llh_r) for sat in common}
        # the base's side is the same at every iteration of an epoch: computed once
        if self._base_models[0] is not sb:
            self._base_models = (sb, {})
        model_b = self._base_models[1]
        for sat in common:
            if sat not in model_b:
                model_b[sat] = _model_m(self.base_r_e, sb[sat], self._base_llh)
        rows_v, rows_H, var_sd, groups, keys = [], [], [], [], []
        n = len(x)
        sd_vars: dict[tuple[str, str], float] = {}

        def sd_var(sat: str, kind: str) -> float:
            v = sd_vars.get((sat, kind))
            if v is None:
                v = sd_vars[(sat, kind)] = self._sd_var(sr[sat].elevation_rad, kind)
            return v

        for sys, s in self._groups:
            sats = [sat for sat in common if sat[:1] == sys and (sat, s) in self.amb]
            if len(sats) < 2:
                continue
            ref = max(sats, key=lambda q: sr[q].elevation_rad)
            for kind in ("phase", "code"):
                grp = []
                for sat in sats:
                    if sat == ref:
                        continue
                    lam, lam_ref = sr[sat].wavelength_m[s], sr[ref].wavelength_m[s]
                    dd_rho = (model_r[sat][0] - model_b[sat][0]) - (model_r[ref][0] - model_b[ref][0])
                    H = np.zeros(n)
                    H[:3] = -(model_r[sat][1] - model_r[ref][1])
                    # the ionosphere advances the phase and delays the code, each satellite on its carrier
                    sign = -1.0 if kind == "phase" else 1.0
                    dd_iono = 0.0
                    if sat in self.iono and ref in self.iono:
                        f, f_ref = iono_factor(lam), iono_factor(lam_ref)
                        ii, ir_ = self.iono[sat], self.iono[ref]
                        dd_iono = sign * (f * x[ii] - f_ref * x[ir_])
                        H[ii] += sign * f
                        H[ir_] -= sign * f_ref
                    if kind == "phase":
                        # in metres, each satellite on its own carrier (GLONASS FDMA): the receiver
                        # clocks cancel, the ambiguity term is lambda_i N_i - lambda_j N_j
                        obs = (lam * (sr[sat].phase_cyc[s] - sb[sat].phase_cyc[s])
                               - lam_ref * (sr[ref].phase_cyc[s] - sb[ref].phase_cyc[s]))
                        ia, ir = self.amb[(sat, s)], self.amb[(ref, s)]
                        if fixed is not None and (sat, s) in fixed:
                            # lambda_i N_i - lambda_j N_j = lambda_i (N_i - N_j) + (lambda_i - lambda_j) N_j
                            h = dd_rho + lam * fixed[(sat, s)] + (lam - lam_ref) * x[ir] + dd_iono
                        else:
                            H[ia] += lam
                            H[ir] -= lam_ref
                            h = dd_rho + lam * x[ia] - lam_ref * x[ir] + dd_iono
                    else:
                        if fixed is not None:
                            continue
                        obs = (sr[sat].code_m[s] - sb[sat].code_m[s]) - (sr[ref].code_m[s] - sb[ref].code_m[s])
                        h = dd_rho + dd_iono
                    rows_v.append(obs - h)
                    rows_H.append(H)
                    var_sd.append((sd_var(sat, kind), sd_var(ref, kind)))
                    grp.append(len(rows_v) - 1)
                    keys.append((kind, s, sat, ref))
                groups.append(grp)
        m = len(rows_v)
        R = dd_covariance(var_sd, groups)
        return np.array(rows_v), np.array(rows_H).reshape(m, n), R, keys

    def _sd_var(self, el: float, kind: str) -> float:
        cfg = self.cfg
        return (sd_variance_m2(el, kind, cfg.phase_sigma_a_m, cfg.phase_sigma_b_m, cfg.code_phase_ratio)
                + (SPEED_OF_LIGHT_MPS * cfg.sat_clock_stability * self._age_s) ** 2)

    def _update(self, common, sr, sb) -> int:
        """Iterated EKF update with all DD rows; DD phase rows far off are dropped (counted)."""
        x0, P0 = self.x.copy(), self.P.copy()
        x = x0.copy()
        for it in range(self.cfg.iterations):
            v, H, R, keys = self._dd_rows(x, common, sr, sb)
            if len(v) == 0:
                return 0
            v = v + H @ (x - x0)                  # innovation about the prior (iterated EKF)
            if it == 0:
                bad = [i for i, k in enumerate(keys) if k[0] == "phase"
                       and abs(v[i]) > self.cfg.max_phase_innovation_m and self.P[self.amb[(k[2], k[1])], self.amb[(k[2], k[1])]] < 1.0]
                if bad:
                    self._count("phase rows rejected (innovation)", len(bad))
                    for i in bad:                      # its ambiguity is wrong: start it again
                        self._drop_amb([(keys[i][2], keys[i][1])])
                    return self._update(common, sr, sb)
            S = H @ P0 @ H.T + R
            K = np.linalg.solve(S, H @ P0).T
            x = x0 + K @ v
        I_KH = np.eye(len(x)) - K @ H
        self.P = I_KH @ P0 @ I_KH.T + K @ R @ K.T
        self.x = x
        return len(v)

    # ------------------------------------------------------------------ integer ambiguities
    def _dd_ambiguities(self, common, sr, exclude=()):
        """Transformation T (DD ambiguities = T x) and the (sat, signal, ref) of each row."""
        rows, labels = [], []
        for sys, s in self._groups:
            if sys in self._float_only:
                continue
            sats = [q for q in common if q[:1] == sys and (q, s) in self.amb and q not in exclude]
            if len(sats) < 2:
                continue
            ref = max(sats, key=lambda q: sr[q].elevation_rad)
            for q in sats:
                if q == ref:
                    continue
                t = np.zeros(len(self.x))
                t[self.amb[(q, s)]] = 1.0
                t[self.amb[(ref, s)]] = -1.0
                rows.append(t)
                labels.append((q, s, ref))
        return np.array(rows).reshape(len(rows), len(self.x)), labels

    def _try_fix(self, common, sr, sb, exclude, n_dd: int = 0):
        """The validated fix with the satellites ``exclude`` left float, None, or :data:`_TOO_FEW`
        (fewer DD ambiguities than the floor: leaving more satellites out cannot help)."""
        T, labels = self._dd_ambiguities(common, sr, exclude)
        if len(labels) < max(self.cfg.min_fix_ambiguities, self.cfg.min_fix_fraction * n_dd):
            return _TOO_FEW
        a = T @ self.x
        Qa = T @ self.P @ T.T
        Qra = self.P[:3, :] @ T.T
        try:
            res = lambda_ils(a, Qa, m=2)
        except (np.linalg.LinAlgError, RuntimeError):
            self._count("lambda failures")
            return None
        if not res.ratio >= self.cfg.ratio_threshold:
            return None
        if not res.success_rate >= self.cfg.min_success_rate:
            self._count("fixes rejected: success rate")
            return None
        afix = res.fixed[:, 0]
        gain = np.linalg.solve(Qa, a - afix)
        r_fix = self.x[:3] - Qra @ gain
        cov_fix = self.P[:3, :3] - Qra @ np.linalg.solve(Qa, Qra.T)
        if not float(np.trace(cov_fix)) <= self.cfg.max_fixed_sigma_3d_m ** 2:
            self._count("fixes rejected: position not pinned")
            return None
        # wrong-fix check: the fixed DD phase residuals against their own noise (the ionosphere
        # states conditioned on the integers as the position is)
        x_fix = self.x.copy()
        x_fix[:3] = r_fix
        if self.iono:
            idx = list(self.iono.values())
            x_fix[idx] -= (self.P[idx, :] @ T.T) @ gain
        fixed = {}
        for (q, s, ref), n_dd in zip(labels, afix):
            fixed[(q, s)] = n_dd
        v, _, R, keys = self._dd_rows(x_fix, [q for q in common if q not in exclude], sr, sb, fixed=fixed)
        sel = [i for i, k in enumerate(keys) if k[0] == "phase" and (k[2], k[1]) in fixed]
        if sel:
            z = np.abs(v[sel]) / np.sqrt(np.diag(R)[sel])
            if float(z.max()) > self.cfg.fixed_residual_sigma:
                self._count("fixes rejected: residuals")
                return None
        return r_fix, cov_fix, res, T, afix, labels

    def _resolve(self, t: float, common, sr, sb) -> RtkSolution:
        n_dd = len(self._dd_ambiguities(common, sr)[1])
        by_sys = dict(Counter(q[:1] for q in common))
        order = self._partial_fixing_order(t, common, sr)
        exclude: list[str] = []
        out = None
        while True:
            out = self._try_fix(common, sr, sb, exclude, n_dd)
            if out is not None or len(order) - len(exclude) <= 3:
                break
            exclude.append(order[len(exclude)])      # partial fixing: leave the next satellite float
        if out is None or out is _TOO_FEW:
            self._count("epochs float")
            self.consecutive_fixes = 0
            return RtkSolution(t, self.x[:3].copy(), self.P[:3, :3].copy(), Q_FLOAT, len(common),
                               0.0, 0, n_dd, counters=dict(self.counters), n_sats_by_system=by_sys,
                               age_s=self._age_s)
        r_fix, cov_fix, res, T, afix, labels = out
        if exclude:
            self._count("epochs fixed partially")
        self._count("epochs fixed")
        self.consecutive_fixes += 1
        if self.cfg.fix_and_hold and self.consecutive_fixes >= self.cfg.hold_after_fixes:
            self._hold(T, afix)
        return RtkSolution(t, r_fix, cov_fix, Q_FIX, len(common), res.ratio, len(labels), n_dd,
                           res.success_rate, counters=dict(self.counters), n_sats_by_system=by_sys,
                           age_s=self._age_s)

    def _partial_fixing_order(self, t: float, common, sr) -> list[str]:
        """The satellites partial fixing leaves float one after another: those with an ambiguity
        younger than ``young_ambiguity_s``, then the others, each group lowest first."""
        young_s = self.cfg.young_ambiguity_s

        def young(sat: str) -> bool:
            return any(abs(t - self.amb_since[(sat, s)]) < young_s
                       for s in self.sig.get(sat[:1], ()) if (sat, s) in self.amb)
        return sorted((q for q in common if q[:1] not in self._float_only),
                      key=lambda q: (not young(q), sr[q].elevation_rad))

    def _hold(self, T: np.ndarray, afix: np.ndarray) -> None:
        """Fix-and-hold: the fixed DD ambiguities as measurements of the float filter."""
        R = np.eye(len(afix)) * self.cfg.hold_sigma_cycles ** 2
        S = T @ self.P @ T.T + R
        K = np.linalg.solve(S, T @ self.P).T
        self.x = self.x + K @ (afix - T @ self.x)
        I_KT = np.eye(len(self.x)) - K @ T
        self.P = I_KT @ self.P @ I_KT.T + K @ R @ K.T


def pair_epochs(rover_epochs, base_epochs, tol_s: float = 0.5):
    """(rover, nearest base) pairs whose time tags agree within ``tol_s``."""
    base = sorted(base_epochs, key=lambda e: e.t_gps)
    ts = np.array([e.t_gps for e in base])
    out = []
    for r in rover_epochs:
        if not len(ts):
            break
        k = int(np.argmin(np.abs(ts - r.t_gps)))
        if abs(ts[k] - r.t_gps) <= tol_s:
            out.append((r, base[k]))
    return out


__all__ = ["RtkConfig", "RtkFilter", "RtkSolution", "pair_epochs", "Q_FIX", "Q_FLOAT", "FLOAT_ONLY_SYSTEMS",
           "GLONASS_AR_OPTIONS"]
