"""Pieces of double-differenced (DD) carrier phase and code shared by the post-processing RTK
filter (:mod:`.rtk`) and the engine's RTK update (:mod:`companion.nav.rtk_update`).

* :func:`receiver_sats`: one receiver's epoch as satellite geometry and observables, the satellite
  at its own transmit time from that receiver's pseudorange (light time, Sagnac rotation to the
  reception frame, satellite clock).  Each receiver is modelled **at its own epoch**: a rover
  tagged x.987 s and a base tagged x.000 s each give their own observed-minus-computed, and what
  the DD of the two keeps from the 13-ms offset is the change of the per-satellite errors
  (atmosphere, orbit and clock errors: mm/s) over it; receiver clocks cancel between satellites.
* :func:`cross_pair`: a carrier the rover tracks only as L2C and the base only as L2 P(Y) (or the
  reverse) renamed on both sides to the pair's own code (:mod:`companion.rtk_signals`).
* :func:`at_reference_point`: a receiver's observables moved from each carrier's phase centre to
  its antenna reference point (the calibration of :mod:`.antenna_calibration`).
* :func:`model_range_m`: geometric range + Saastamoinen troposphere at the receiver's height -
  satellite clock, and the unit line of sight.
* :func:`sd_variance_m2`: between-receiver single-difference variance, ``2 (a^2 + b^2/sin^2 el)``
  (RTKLIB's default a = b = 3 mm), code = ``code_phase_ratio`` x phase.
* :func:`dd_covariance`: the DD covariance of rows sharing a reference satellite: each row's own
  SD variance plus the reference's, the reference's share off the diagonal.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..messages import SPEED_OF_LIGHT_MPS, GnssEpoch
from ..nav.earth import OMEGA_IE_RADPS, C_n_e, ecef_to_geodetic
from ..rtk_signals import RTK_CROSS_PAIRS_BY_SYSTEM
from .atmosphere import tropo_delay_m
from .ephemeris import satellite_clock, satellite_state
from .ephemeris_store import EphemerisStore
from .glonass import GlonassEphemeris
from .glonass import wavelength_m as glonass_wavelength_m


@dataclass
class ReceiverSat:
    """One satellite as seen by one receiver at one epoch."""

    r_sat_e: np.ndarray             # reception-frame satellite position (m)
    clock_m: float                  # c x satellite clock bias
    code_m: dict                    # signal -> pseudorange (m)
    phase_cyc: dict                 # signal -> carrier (cycles)
    wavelength_m: dict
    slip: dict                      # signal -> receiver loss-of-lock flag
    elevation_rad: float = 0.0
    half_cycle: dict | None = None  # signal -> unresolved half-cycle flag
    lock_time_s: dict | None = None  # signal -> continuous lock time (s)
    eph: object = None              # the ephemeris used (both receivers must use the same one)


def at_reference_point(sats: dict[str, ReceiverSat], antenna, r_rx_e: np.ndarray,
                       llh=None) -> dict[str, ReceiverSat]:
    """``sats`` with each carrier's phase and code moved from its phase centre to the antenna
    reference point: what ``antenna`` (:class:`~.antenna_calibration.AntennaCalibration`, None:
    ``sats`` as they are) adds to the range along each line of sight from ``r_rx_e`` taken off the
    observation, where RTKLIB's ``antmodel`` adds it to the modelled range.  New dicts: the
    observables' dicts are shared with other users of the epoch."""
    if antenna is None or not sats:
        return sats
    lat, lon, _ = ecef_to_geodetic(r_rx_e) if llh is None else llh
    C_e_n = C_n_e(lat, lon).T
    out = {}
    for sat, q in sats.items():
        d = q.r_sat_e - r_rx_e
        n, e, dn = C_e_n @ (d / np.linalg.norm(d))
        u_enu = np.array([e, n, -dn])
        off = {s: antenna.range_offset_m(sat[:1], s[1], u_enu) for s in {*q.code_m, *q.phase_cyc}}
        out[sat] = dataclasses.replace(q, code_m={s: v - off[s] for s, v in q.code_m.items()},
                                       phase_cyc={s: v - off[s] / q.wavelength_m.get(s, math.nan)
                                                  for s, v in q.phase_cyc.items()})
    return out


def signals_of(signals, sat: str) -> tuple[str, ...]:
    """The signal list of ``sat``: ``signals`` itself (one list for every system) or, a mapping
    system -> list, its system's (empty when absent)."""
    return tuple(signals.get(sat[:1], ())) if isinstance(signals, dict) else tuple(signals)


def receiver_sats(epoch: GnssEpoch, store: EphemerisStore, r_rx_e: np.ndarray, signals) -> dict[str, ReceiverSat]:
    """Satellite geometry and observables of one receiver's epoch (satellites with ephemerides
    and a pseudorange on the first of their signals).  ``signals``: one list for every satellite,
    or a mapping system -> list (a multi-system RTK: 'L1C' is GPS L1 C/A and Galileo E1, BeiDou is
    placed by its B1I 'L2I').  :func:`transmit_states` then :func:`place_at`."""
    return place_at(transmit_states(epoch, store, signals), r_rx_e)


@dataclass
class TransmitState:
    """One satellite of one receiver's epoch at its transmit time: everything of
    :class:`ReceiverSat` that does not depend on the receiver's position (the transmit time comes
    from the pseudorange alone), so that the epoch can be placed at several positions
    (:func:`place_at`) for the price of the light time and the Sagnac rotation."""

    r_s: np.ndarray                 # ECEF of the transmit time (m), velocity (m/s)
    v_s: np.ndarray
    clock_m: float
    fields: tuple                   # ReceiverSat's observables (dicts, not copied by place_at)
    eph: object
    t_tx: float = math.nan          # transmit time from the pseudorange (s, GPS time) ...
    clock1_s: float = math.nan      # ... the satellite clock there (the first iteration's) ...
    drift_sps: float = 0.0          # ... and the clock drift (s/s)
    clock_s: float = math.nan       # the satellite clock of the transmit time (s)


#: the transmit times of two receivers' epochs (a base and a rover tagged alike) closer than this
#: share the satellite's orbit: the other's state carried over by its velocity.  Half the
#: acceleration (0.6 m/s^2) times the interval squared is 1e-10 m; measured against a fresh
#: evaluation (sitl rtk-gec, intervals of 1-4 x 1.2e-7 s) it is off by up to 1.5e-7 m, which is
#: the evaluation's own noise: Kepler's equation is solved to 1e-14 rad (2.6e-7 m of orbit), and a
#: GPS time of 7e8 s is resolved to 1.2e-7 s (0.5 mm of the satellite's motion)
SHARE_MAX_DT_S = 2e-5             # negative: never shared


def transmit_states(epoch: GnssEpoch, store: EphemerisStore, signals,
                    near: dict[str, TransmitState] | None = None) -> dict[str, TransmitState]:
    """The position-independent part of :func:`receiver_sats` (the satellites it keeps).
    ``near``: another receiver's states of (nearly) the same time (the rover's for the base):
    a satellite on the same ephemeris whose transmit time is within :data:`SHARE_MAX_DT_S` of
    that one's is carried over from it (the orbit evaluated once per epoch for both receivers)."""
    by_sat: dict[str, dict] = {}
    for o in epoch.observations:
        if o.signal in signals_of(signals, o.sat):
            by_sat.setdefault(o.sat, {})[o.signal] = o
    out = {}
    for sat, obs in by_sat.items():
        first = obs.get(signals_of(signals, sat)[0])
        if first is None or not _present(first.pseudorange_m):
            continue
        eph = store.select(sat, epoch.t_gps)
        if eph is None:
            continue
        t_tx = epoch.t_gps - first.pseudorange_m / SPEED_OF_LIGHT_MPS
        o_st = near.get(sat) if near is not None else None
        if o_st is not None and o_st.eph is eph and abs(t_tx - o_st.t_tx) <= SHARE_MAX_DT_S:
            # the same two clock iterations, each carried over linearly from the other's
            drift = o_st.drift_sps
            clk1 = o_st.clock1_s + drift * (t_tx - o_st.t_tx)
            dt = (t_tx - clk1) - (o_st.t_tx - o_st.clock1_s)
            r_s = o_st.r_s + o_st.v_s * dt
            v_s = o_st.v_s
            clk = o_st.clock_s + drift * dt
        else:
            clk1 = satellite_clock(eph, t_tx)[0]        # satellite_state's clock, without the orbit
            r_s, v_s, clk, drift = satellite_state(eph, t_tx - clk1)
        fields = ({s: o.pseudorange_m for s, o in obs.items() if _present(o.pseudorange_m)},
                  {s: o.carrier_cycles for s, o in obs.items() if _present(o.carrier_cycles)},
                  _wavelengths(obs, eph),
                  {s: bool(o.loss_of_lock) for s, o in obs.items()},
                  {s: bool(o.half_cycle_ambiguous) for s, o in obs.items()},
                  {s: float(o.lock_time_s) for s, o in obs.items()})
        out[sat] = TransmitState(r_s, v_s, clk * SPEED_OF_LIGHT_MPS, fields, eph, t_tx, clk1, drift, clk)
    return out


def _present(value: float) -> bool:
    """An observable that was measured: finite and not 0.0 (RINEX's, RTKLIB's and many a
    receiver's mark of a missing one; no real pseudorange or carrier phase is exactly zero)."""
    return math.isfinite(value) and value != 0.0


def _wavelengths(obs: dict, eph) -> dict:
    """signal -> carrier wavelength (m): the observation's, or for a GLONASS FDMA signal that
    comes without one (RINEX) the one of the ephemeris's frequency channel."""
    out = {s: o.wavelength_m for s, o in obs.items()}
    if isinstance(eph, GlonassEphemeris):
        for s, lam in out.items():
            if not math.isfinite(lam):
                out[s] = glonass_wavelength_m(s, eph.frequency_channel)
    return out


def place_at(states: dict[str, TransmitState], r_rx_e: np.ndarray) -> dict[str, ReceiverSat]:
    """:func:`receiver_sats` of the receiver at ``r_rx_e``: the light time from there and the
    rotation into the reception frame (:func:`~.ephemeris.rotate_to_reception_frame`'s, for all
    satellites at once; the observables' dicts are shared, not copied)."""
    if not states:
        return {}
    R = np.array([st.r_s for st in states.values()])
    tau = np.sqrt(np.einsum("ij,ij->i", R - r_rx_e, R - r_rx_e)) / SPEED_OF_LIGHT_MPS
    a = OMEGA_IE_RADPS * tau
    c, s = np.cos(a), np.sin(a)
    rot = np.empty_like(R)
    rot[:, 0] = c * R[:, 0] + s * R[:, 1]
    rot[:, 1] = -s * R[:, 0] + c * R[:, 1]
    rot[:, 2] = R[:, 2]
    out = {}
    for (sat, st), r_rot in zip(states.items(), rot):
        code, phase, wl, slip, half, lock = st.fields
        out[sat] = ReceiverSat(r_rot, st.clock_m, code, phase, wl, slip, half_cycle=half, lock_time_s=lock, eph=st.eph)
    return out


def _tracks(q: ReceiverSat, signal: str) -> bool:
    return signal in q.phase_cyc or signal in q.code_m


def _renamed(q: ReceiverSat, names: dict[str, str]) -> ReceiverSat:
    """``q`` with its observables' signals renamed by ``names`` (new dicts: the originals may be
    shared with a cached epoch)."""
    def keyed(d):
        return None if d is None else {names.get(k, k): v for k, v in d.items()}
    return dataclasses.replace(q, code_m=keyed(q.code_m), phase_cyc=keyed(q.phase_cyc),
                               wavelength_m=keyed(q.wavelength_m), slip=keyed(q.slip),
                               half_cycle=keyed(q.half_cycle), lock_time_s=keyed(q.lock_time_s))


def cross_pair(sr: dict[str, ReceiverSat], sb: dict[str, ReceiverSat],
               pairs_by_system=RTK_CROSS_PAIRS_BY_SYSTEM) -> tuple[dict[str, ReceiverSat], dict[str, ReceiverSat]]:
    """(rover, base) satellites with every carrier the rover tracks only under one family and the
    base only under another (:data:`companion.rtk_signals.RTK_CROSS_PAIRS_BY_SYSTEM`) renamed to
    that pair's code on both sides, so that it forms double differences in a group of its own;
    the inputs are not changed (satellites without such a carrier are the same objects)."""
    out_r = out_b = None
    for sat in sr.keys() & sb.keys():
        pairs = pairs_by_system.get(sat[:1])
        if not pairs:
            continue
        q_r, q_b = sr[sat], sb[sat]
        names_r, names_b = {}, {}
        for (fam_r, fam_b), code in pairs.items():
            if _tracks(q_r, fam_r) and not _tracks(q_r, fam_b) and _tracks(q_b, fam_b) and not _tracks(q_b, fam_r):
                names_r[fam_r] = names_b[fam_b] = code
        if names_r:
            out_r = dict(sr) if out_r is None else out_r
            out_b = dict(sb) if out_b is None else out_b
            out_r[sat], out_b[sat] = _renamed(q_r, names_r), _renamed(q_b, names_b)
    return (sr, sb) if out_r is None else (out_r, out_b)


def elevation_rad(r_rx_e: np.ndarray, r_sat_e: np.ndarray) -> float:
    lat, lon, _ = ecef_to_geodetic(r_rx_e)
    up = C_n_e(lat, lon)[:, 2] * -1.0
    d = r_sat_e - r_rx_e
    return math.asin(float(up @ d) / float(np.linalg.norm(d)))


def model_range_m(r_rx_e: np.ndarray, sat: ReceiverSat, llh=None) -> tuple[float, np.ndarray]:
    """Modelled range (geometric + troposphere - satellite clock) and its unit line of sight
    (receiver to satellite).  ``llh``: the receiver's geodetic position if known already."""
    d = sat.r_sat_e - r_rx_e
    rho = float(np.linalg.norm(d))
    lat, lon, h = ecef_to_geodetic(r_rx_e) if llh is None else llh
    up = -C_n_e(lat, lon)[:, 2]
    el = max(math.asin(float(up @ d) / rho), math.radians(1.0))
    return rho + tropo_delay_m(lat, h, el) - sat.clock_m, d / rho


def sd_variance_m2(el_rad: float, kind: str, sigma_a_m: float, sigma_b_m: float, code_phase_ratio: float) -> float:
    """Between-receiver single-difference variance of a phase or code observation (m^2)."""
    s_el = max(math.sin(el_rad), 0.1)
    v = 2.0 * (sigma_a_m ** 2 + (sigma_b_m / s_el) ** 2)    # two receivers
    return v * (code_phase_ratio ** 2 if kind == "code" else 1.0)


def dd_covariance(var_sd: list[tuple[float, float]], groups: list[list[int]]) -> np.ndarray:
    """DD covariance: row i has SD variances (own, reference's); rows of one group share the
    reference, so they correlate by the reference's SD variance."""
    m = len(var_sd)
    R = np.zeros((m, m))
    for grp in groups:
        for i in grp:
            R[i, i] = var_sd[i][0] + var_sd[i][1]
            for j in grp:
                if j != i:
                    R[i, j] = var_sd[i][1]          # the reference satellite's share
    return R


__all__ = ["ReceiverSat", "TransmitState", "receiver_sats", "transmit_states", "place_at", "cross_pair", "SHARE_MAX_DT_S", "signals_of", "elevation_rad", "model_range_m", "sd_variance_m2", "dd_covariance"]
