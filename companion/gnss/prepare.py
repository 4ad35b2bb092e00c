"""Per-epoch preparation of GNSS measurements for the filter and for SPP.

:func:`prepare_epoch` turns one :class:`GnssEpoch` into arrays over the usable satellites whose
pseudorange model is exactly::

    pseudorange_m[i] = |r_sat_e[i] - r_antenna_e| + receiver_clock_bias_m + isb_m[system(i)]
                       + noise(sigma_pseudorange_m[i])

for the satellites of the selected ``systems`` (GPS, Galileo, BeiDou, QZSS; ``isb_m`` is 0 for the
reference system and a constant inter-system bias for the others, which SPP estimates).  Satellite
times are GPS time throughout: the ephemerides carry their system's offset (BDT + 14 s).

* ``r_sat_e`` / ``v_sat_e``: satellite state at the GPS transmit time, rotated into the ECEF frame
  of the reception time (Sagnac).  The rotation angle uses the *geometric* travel time
  |r_sat - r_approx|/c, iterated twice, never P/c (P contains the receiver clock error).
* ``signal='L1C'`` (default): each system's single-frequency code (:mod:`companion.gnss.signals`:
  GPS/QZSS L1 C/A, Galileo E1, BeiDou B1I).  Standalone: P + c*dt_sat (relativistic term included)
  - group delay (GPS/QZSS TGD, Galileo BGD of the clock's message, BeiDou TGD1: the B1I code
  against the B3I clock) - Klobuchar x (f_L1/f)^2 (the GPS coefficients for every system, as
  RTKLIB does) - tropo.
* DGPS: P + c*dt_sat + PRC (the corrector works on the same signal; TGD, iono and tropo are in the PRC).
* ``signal='IF'``: ionosphere-free combination of each system's pair (GPS C1/P2: L1 code with the
  first of L2W/L2P/L2X/L2C/L2L/L2S, then L5; Galileo E1/E5b, then E1/E5a; BeiDou B1I/B3I, then
  B1I/B2I; QZSS L1/L2C, then L1/L5); GPS, Galileo and QZSS clocks refer to such a combination (no
  group delay), BeiDou's to B3I (TGD1 and TGD2 combined); no iono.  Carrier/Doppler columns then
  come from the first code's signal.
* Satellites with carrier phase but no pseudorange are KEPT with ``pseudorange_m = NaN`` (the TDCP
  model uses their phase); their transmit time is t_rx - rx_clock_bias_m/c - rho/c (GPS time), so pass
  ``rx_clock_bias_m`` when known (else the position error is ~3.9 km/s x receiver clock error).
  In DGPS mode they need no correction.  SPP ignores them.
* With ``r_approx_e`` unknown (norm < 1000 km, e.g. the earth centre) elevation/azimuth are NaN, the
  mask is not applied, no atmosphere model is applied and sigmas use zenith values; re-prepare at a
  better position (see :func:`companion.gnss.spp.spp_epoch`).

Sigma model (variances add):
  code noise (a^2 + b^2/sin^2 E) with a = b = ``CODE_SIGMA_A_M``/``CODE_SIGMA_B_M`` (x the noise
  amplification of the pair for IF: 2.98 for GPS L1/L2, 2.81 for Galileo E1/E5b, 3.53 for B1I/B3I);
  standalone adds URA^2, (``IONO_MODEL_ERROR_FRAC`` x Klobuchar)^2 (``IONO_NO_MODEL_SIGMA_M``^2
  without a model), (``TROPO_ZENITH_ERROR_M`` x mapping)^2;
  DGPS uses 2 x code noise (base + rover) + ``DGPS_SIGMA_M``^2 + (``DGPS_AGE_SIGMA_MPS`` x age)^2.
  Everything but the code noise is slow (minutes to hours: ``sigma_pseudorange_slow_m``); a filter
  that averages epochs must not treat it as white (``companion.nav.engine``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from ..messages import GPS_L1_HZ, GPS_L2_HZ, SPEED_OF_LIGHT_MPS, GnssEpoch, SatObservation
from ..nav.earth import OMEGA_IE_RADPS, ecef_to_geodetic
from .atmosphere import klobuchar_delay_m, saastamoinen_zenith_m, tropo_mapping
from .sat_state import orbit_constants
from .sat_state import state as sat_state
from .sat_state import transmit_time as sat_transmit_time
from .sat_state_kernel import compiled as compiled_state
from .ephemeris_store import EphemerisStore
from .glonass import GlonassEphemeris
from .glonass import satellite_state as glonass_state
from .glonass import with_channel_wavelength
from .signals import (GLONASS, GLONASS_CODE_SIGMA_FACTOR, IF_FIRST_SIGNALS, IF_SECOND_SIGNALS, PRIMARY_SIGNALS,
                      PREPARED_SYSTEMS, group_delay_m, iono_free_noise_factor, is_transmitted, pair_frequencies_hz)

if TYPE_CHECKING:  # pragma: no cover
    from .dgps import DgpsCorrector

C = SPEED_OF_LIGHT_MPS
CODE_SIGMA_A_M = 0.3          # code noise, elevation-independent part, m (RTKLIB default)
CODE_SIGMA_B_M = 0.3          # code noise, scaled by 1/sin(E), m
IF_NOISE_FACTOR = 2.98        # noise amplification of the L1/L2 iono-free combination
IONO_MODEL_ERROR_FRAC = 0.5   # Klobuchar removes ~50 % rms of the delay
IONO_NO_MODEL_SIGMA_M = 5.0   # no model at all: the whole delay is error (RTKLIB ERR_ION), m
TROPO_ZENITH_ERROR_M = 0.1    # Saastamoinen + standard atmosphere zenith error, m
DGPS_SIGMA_M = 0.2            # spatial/temporal decorrelation of a short-baseline PRC, m
DGPS_AGE_SIGMA_MPS = 0.01     # growth of the correction error with age, m/s
UNKNOWN_POSITION_NORM_M = 1.0e6
GAMMA_L1_L2 = (GPS_L1_HZ / GPS_L2_HZ) ** 2


@dataclass
class PreparedEpoch:
    """Arrays over the n usable satellites of one epoch (n may be 0).  See module docstring."""

    t_gps: float
    signal: str
    r_approx_e: np.ndarray
    sats: list[str]
    r_sat_e: np.ndarray
    v_sat_e: np.ndarray
    pseudorange_m: np.ndarray
    sigma_pseudorange_m: np.ndarray
    sat_clock_bias_m: np.ndarray
    sat_clock_drift_mps: np.ndarray
    carrier_cycles: np.ndarray
    wavelength_m: np.ndarray
    doppler_hz: np.ndarray
    cn0_dbhz: np.ndarray
    lock_time_s: np.ndarray
    half_cycle: np.ndarray
    loss_of_lock: np.ndarray
    elevation_rad: np.ndarray
    azimuth_rad: np.ndarray
    iode: np.ndarray
    dgps_age_s: np.ndarray
    iono_m: np.ndarray            # ionospheric delay removed (m, 0 if none)
    tropo_m: np.ndarray           # tropospheric delay removed (m, 0 if none)
    rejected: dict[str, str] = field(default_factory=dict)
    # the part of sigma_pseudorange_m from slowly varying errors (orbit and clock, atmosphere
    # model, DGPS decorrelation: minutes to hours), which averaging over epochs does not reduce
    sigma_pseudorange_slow_m: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def n(self) -> int:
        return len(self.sats)

    def subset(self, idx) -> "PreparedEpoch":
        """A copy restricted to the index array/list ``idx`` (rejections kept)."""
        idx = np.asarray(idx, dtype=int)
        kw = {}
        for name in self.__dataclass_fields__:
            v = getattr(self, name)
            if isinstance(v, np.ndarray) and name != "r_approx_e":
                kw[name] = v[idx]
            elif name == "sats":
                kw[name] = [self.sats[i] for i in idx]
            elif name == "rejected":
                kw[name] = dict(v)
            else:
                kw[name] = v
        return PreparedEpoch(**kw)


def group_by_sat(epoch: GnssEpoch) -> dict[str, dict[str, SatObservation]]:
    """sat -> signal -> observation, in first-seen satellite order; signals the satellite does not
    transmit (:func:`~companion.gnss.signals.is_transmitted`: false locks) are left out."""
    out: dict[str, dict[str, SatObservation]] = {}
    for o in epoch.observations:
        if is_transmitted(o.sat, o.signal):
            out.setdefault(o.sat, {})[o.signal] = o
    return out


def form_pseudorange(sig: dict[str, SatObservation], signal: str, system: str = "G"):
    """(pseudorange m or NaN, observation carrying phase/Doppler or None, codes used, TGD factor,
    iono factor, code-noise factor) of one satellite of ``system``.

    ``signal``: 'L1C' = the system's single-frequency code (:data:`PRIMARY_SIGNALS`: GPS/QZSS L1 C/A,
    Galileo E1, BeiDou B1I); 'IF' = the iono-free combination of the system's first pair found
    (:data:`IF_FIRST_SIGNALS` x :data:`IF_SECOND_SIGNALS`); any other code ('L2W') = that code.
    TGD factor multiplies c*TGD to subtract for GPS/Galileo/QZSS ((f_L1/f)^2 on one code, 0 for IF;
    BeiDou: :func:`group_delay_m` from the codes); iono factor scales the L1 Klobuchar delay
    (f_L1/f)^2 (0 for IF)."""
    nan = float("nan")
    if signal == "IF":
        o1 = code1 = None
        for code1 in IF_FIRST_SIGNALS.get(system, ()):
            o1 = sig.get(code1)
            if o1 is not None:
                break
        if o1 is None:
            return nan, None, (), 0.0, 0.0, 1.0
        p2 = nan
        code2 = None
        for s in IF_SECOND_SIGNALS.get(system, ()):
            o2 = sig.get(s)
            if o2 is not None and o2.pseudorange_m == o2.pseudorange_m:
                p2, code2 = o2.pseudorange_m, s
                break
        p1 = o1.pseudorange_m
        if code2 is None or (system == "G" and code2[1] == "2"):   # GPS L1/L2: the historical constants
            g1, g2 = GPS_L1_HZ * GPS_L1_HZ, GPS_L2_HZ * GPS_L2_HZ
            noise = IF_NOISE_FACTOR
        else:
            f1, f2 = pair_frequencies_hz(o1.sat, code1, code2)
            g1, g2 = f1 * f1, f2 * f2
            noise = iono_free_noise_factor(f1, f2)
        p = (g1 * p1 - g2 * p2) / (g1 - g2)
        return p, o1, (code1, code2) if code2 else (code1,), 0.0, 0.0, noise
    code = signal
    if signal == "L1C":
        for code in PRIMARY_SIGNALS.get(system, ("L1C",)):
            if code in sig:
                break
    o = sig.get(code)
    if o is None:
        return nan, None, (), 0.0, 0.0, 1.0
    wl = o.wavelength_m
    ratio = (wl / (C / GPS_L1_HZ)) ** 2 if wl == wl else 1.0  # (f_L1 / f)^2
    return o.pseudorange_m, o, (code,), ratio, ratio, 1.0


#: the numeric columns of a row of :func:`prepare_epoch`, in :class:`PreparedEpoch` field order
_FLOAT_COLS = ("pseudorange_m", "sigma_pseudorange_m", "sat_clock_bias_m", "sat_clock_drift_mps", "carrier_cycles",
               "wavelength_m", "doppler_hz", "cn0_dbhz", "lock_time_s", "elevation_rad", "azimuth_rad",
               "dgps_age_s", "iono_m", "tropo_m", "sigma_pseudorange_slow_m")


def _empty(t_rx, signal, r0, rejected) -> PreparedEpoch:
    z = np.zeros(0)
    return PreparedEpoch(
        t_gps=t_rx, signal=signal, r_approx_e=r0.copy(), sats=[], r_sat_e=np.zeros((0, 3)),
        v_sat_e=np.zeros((0, 3)), pseudorange_m=z, sigma_pseudorange_m=z, sat_clock_bias_m=z,
        sat_clock_drift_mps=z, carrier_cycles=z, wavelength_m=z, doppler_hz=z, cn0_dbhz=z, lock_time_s=z,
        half_cycle=np.zeros(0, bool), loss_of_lock=np.zeros(0, bool), elevation_rad=z, azimuth_rad=z,
        iode=np.zeros(0, int), dgps_age_s=z, iono_m=z, tropo_m=z, rejected=rejected)


def _glonass_at_transmit(eph: GlonassEphemeris, t_rx: float, pseudorange_m: float | None, rx_clock_bias_m: float,
                         r_approx_e: tuple | None) -> tuple:
    """(x, y, z, vx, vy, vz, clock bias s, drift s/s) of a GLONASS satellite at its transmit time
    (GPS time) for a signal received at ``t_rx``: from the pseudorange and the satellite clock as
    for the Keplerian systems, or without one from the geometric range (phase only)."""
    if pseudorange_m is not None:
        t_tx = t_rx - pseudorange_m / C
        t_tx -= eph.clock_bias_s + eph.clock_rate * (t_tx - eph.t_oe_gps)
    else:
        t_tx = t_rx - rx_clock_bias_m / C - 0.075
        if r_approx_e is not None:
            r, _, _, _ = glonass_state(eph, t_tx)
            t_tx = t_rx - rx_clock_bias_m / C - math.dist(r.tolist(), r_approx_e) / C
    r, v, dts, ddts = glonass_state(eph, t_tx)
    return (*r.tolist(), *v.tolist(), dts, ddts)


def _keplerian_at_transmit(eph, t_rx: float, pseudorange_m: float | None, rx_clock_bias_m: float,
                           r_approx_e: tuple | None, kern) -> tuple:
    """The same for a Keplerian ephemeris (:mod:`.sat_state`; compiled by ``kern`` when given, the
    same numbers): the transmit time from the pseudorange, or without one from the geometric
    range (GPS time: no satellite clock term)."""
    k = orbit_constants(eph)
    t_guess = t_rx - rx_clock_bias_m / C - 0.075
    if kern is not None and not k.geo:
        if pseudorange_m is not None:
            return kern(k.vec, t_rx, pseudorange_m, math.nan)[1:]
        s0 = kern(k.vec, t_rx, 0.0, t_guess)
        tau = math.dist(s0[1:4], r_approx_e) / C if r_approx_e is not None else 0.075
        return kern(k.vec, t_rx, 0.0, t_rx - rx_clock_bias_m / C - tau)[1:]
    if pseudorange_m is not None:
        t_tx = sat_transmit_time(k, t_rx, pseudorange_m)
    else:
        s0 = sat_state(k, t_guess)
        tau = math.dist(s0[:3], r_approx_e) / C if r_approx_e is not None else 0.075
        t_tx = t_rx - rx_clock_bias_m / C - tau
    return sat_state(k, t_tx)


def prepare_epoch(epoch: GnssEpoch, store: EphemerisStore, r_approx_e, *,
                  dgps: "DgpsCorrector | None" = None, elevation_mask_rad: float = math.radians(10.0),
                  klobuchar=None, signal: str = "L1C", rx_clock_bias_m: float = 0.0,
                  apply_models: bool = True, tropo: bool = True, systems: str = "G") -> PreparedEpoch:
    """Corrected measurements of one epoch (see module docstring for the model and conventions).

    ``systems``: the constellations used, letters of :data:`PREPARED_SYSTEMS` ('G' by default:
    GPS only, as the single-clock filter needs; 'GECJ' for the four CDMA systems, R for GLONASS).
    Satellites of other systems are rejected as 'system not selected' ('unsupported system' for
    SBAS, NavIC).  GLONASS: the integrated orbit (:mod:`.glonass`), the FDMA wavelengths from the
    ephemeris's frequency channel where the observations have none, no group delay (its clock
    refers to L1), its code sigma x :data:`~.signals.GLONASS_CODE_SIGMA_FACTOR` and its broadcast
    orbit's ``ura_m``.  The
    pseudorange model is the same for all; each system has its own clock offset, estimated by
    :func:`companion.gnss.spp.solve_spp` as an inter-system bias.

    ``klobuchar``: (alpha[4], beta[4]) or None (then no iono correction standalone).
    ``apply_models=False`` applies the satellite clock only (used by the DGPS base: raw P + c*dt_sat).

    The satellite states come from :mod:`.sat_state` (the expressions of :mod:`.ephemeris` in
    plain floats, each ephemeris's constants computed once), compiled (:mod:`.sat_state_kernel`,
    the same numbers) while the engine's kernels are loaded; the rows are gathered as floats and
    turned into arrays once.
    """
    t_rx = epoch.t_gps
    r0 = np.asarray(r_approx_e, dtype=float)
    rx, ry, rz = float(r0[0]), float(r0[1]), float(r0[2])
    r0_t = (rx, ry, rz)
    known = math.sqrt(rx * rx + ry * ry + rz * rz) > UNKNOWN_POSITION_NORM_M
    ztd = 0.0
    if known:
        lat, lon, h = ecef_to_geodetic(r0)
        sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
        e0, e1 = -so, co
        n0, n1, n2 = -sl * co, -sl * so, cl
        u0, u1, u2 = cl * co, cl * so, sl
        if apply_models and dgps is None and tropo and -1000.0 < h < 20000.0:
            zhd, zwd = saastamoinen_zenith_m(lat, h)
            ztd = zhd + zwd
        else:
            ztd = 0.0
    rejected: dict[str, str] = {}
    sats: list[str] = []
    rows: list[tuple] = []
    use_iono = apply_models and dgps is None and klobuchar is not None and known
    alpha, beta = (klobuchar if klobuchar is not None else (None, None))
    nan = float("nan")
    two_pi = 2.0 * math.pi
    w_ie = OMEGA_IE_RADPS
    cos, sin, dist, isfinite = math.cos, math.sin, math.dist, math.isfinite
    select = store.select_with_reason
    kern = compiled_state()
    for sat, sig in group_by_sat(epoch).items():
        sys_ = sat[0]
        if sys_ not in systems or sys_ not in PREPARED_SYSTEMS:
            rejected[sat] = "system not selected" if sys_ in PREPARED_SYSTEMS else "unsupported system"
            continue
        glo_eph = None
        if sys_ == GLONASS:
            # the ephemeris first: its frequency channel gives the FDMA wavelengths a RINEX file
            # leaves out (NaN), which the iono scaling and the phase need
            glo_eph, reason = select(sat, t_rx)
            if glo_eph is None:
                rejected[sat] = "no ephemeris" if reason == "outside fit interval" else reason
                continue
            sig = {c: with_channel_wavelength(o, glo_eph.frequency_channel) for c, o in sig.items()}
        p, o, codes, tgd_fac, iono_fac, code_scale = form_pseudorange(sig, signal, sys_)
        if o is None:
            rejected[sat] = "no pseudorange"
            continue
        has_p = p == p and isfinite(p)
        has_l = o.carrier_cycles == o.carrier_cycles
        if not has_p and not has_l:
            rejected[sat] = "no pseudorange"
            continue
        eph, reason = (glo_eph, "") if glo_eph is not None else select(sat, t_rx)
        if eph is None:
            rejected[sat] = "no ephemeris" if reason == "outside fit interval" else reason
            continue
        prc = nan
        age = nan
        if dgps is not None and has_p:
            iode_c = dgps.iode(sat)
            if iode_c is None:
                rejected[sat] = "no DGPS correction"
                continue
            if iode_c != eph.iode:
                eph2, _ = select(sat, t_rx, iode=iode_c)
                if eph2 is None:
                    rejected[sat] = "IODE mismatch"
                    continue
                eph = eph2
            prc, age, why = dgps.correction(sat, t_rx, eph.iode)
            if why:
                rejected[sat] = why
                continue
        if glo_eph is not None:
            x, y, z, vx, vy, vz, dts, ddts = _glonass_at_transmit(eph, t_rx, p if has_p else None,
                                                                 rx_clock_bias_m, r0_t if known else None)
            code_scale *= GLONASS_CODE_SIGMA_FACTOR
        else:
            x, y, z, vx, vy, vz, dts, ddts = _keplerian_at_transmit(eph, t_rx, p if has_p else None,
                                                                   rx_clock_bias_m, r0_t if known else None, kern)
        # geometric travel time, two iterations (the first from the unrotated position)
        a = w_ie * (dist((x, y, z), r0_t) / C)
        c, s = cos(a), sin(a)
        tau = dist((c * x + s * y, -s * x + c * y, z), r0_t) / C
        a = w_ie * tau
        c, s = cos(a), sin(a)
        rr0, rr1 = c * x + s * y, -s * x + c * y
        dx, dy, dz = rr0 - rx, rr1 - ry, z - rz
        rho = math.sqrt(dx * dx + dy * dy + dz * dz)
        if known:
            ux, uy, uz = dx / rho, dy / rho, dz / rho
            e_ = ux * e0 + uy * e1
            n_ = ux * n0 + uy * n1 + uz * n2
            u_ = ux * u0 + uy * u1 + uz * u2
            el = math.asin(max(-1.0, min(1.0, u_)))
            az = math.atan2(e_, n_) % two_pi
            if el < elevation_mask_rad:
                rejected[sat] = "below elevation mask"
                continue
            sin_el = max(sin(el), 0.05)
        else:
            el = az = nan
            sin_el = 1.0
        iono = tro = 0.0
        var = (CODE_SIGMA_A_M * code_scale) ** 2 + (CODE_SIGMA_B_M * code_scale) ** 2 / (sin_el * sin_el)
        var_slow = 0.0
        pr = nan
        if has_p:
            pr = p + C * dts
            if dgps is not None:
                pr += prc
                var_slow = DGPS_SIGMA_M ** 2 + (DGPS_AGE_SIGMA_MPS * age) ** 2
                var = 2.0 * var + var_slow
            elif apply_models:
                pr -= group_delay_m(eph, codes, tgd_fac)
                if use_iono and iono_fac:
                    iono = iono_fac * klobuchar_delay_m(t_rx, lat, lon, az, el, alpha, beta)
                    pr -= iono
                if ztd and known:
                    tro = ztd * tropo_mapping(el)
                    pr -= tro
                var_slow = eph.ura_m ** 2 + (IONO_MODEL_ERROR_FRAC * iono) ** 2
                if not use_iono and iono_fac:
                    var_slow += IONO_NO_MODEL_SIGMA_M ** 2
                if known:
                    var_slow += (TROPO_ZENITH_ERROR_M * tropo_mapping(el)) ** 2
                var += var_slow
            if not isfinite(pr):
                rejected[sat] = "non-finite"
                continue
        if not (isfinite(rr0) and isfinite(dts)):
            rejected[sat] = "non-finite"
            continue
        sats.append(sat)
        # the order of _FLOAT_COLS, then r_sat, v_sat, half-cycle, loss of lock, IODE
        rows.append((pr, math.sqrt(var), C * dts, C * ddts, o.carrier_cycles, o.wavelength_m, o.doppler_hz,
                     o.cn0_dbhz, o.lock_time_s, el, az, age, iono, tro, math.sqrt(var_slow),
                     rr0, rr1, z, c * vx + s * vy, -s * vx + c * vy, vz,
                     o.half_cycle_ambiguous, o.loss_of_lock, eph.iode))
    if not rows:
        return _empty(t_rx, signal, r0, rejected)
    cols = np.array(rows, dtype=float).T.copy()       # one conversion; each column contiguous
    kw = dict(zip(_FLOAT_COLS, cols))
    nf = len(_FLOAT_COLS)
    return PreparedEpoch(
        t_gps=t_rx, signal=signal, r_approx_e=r0.copy(), sats=sats,
        r_sat_e=cols[nf:nf + 3].T.copy(), v_sat_e=cols[nf + 3:nf + 6].T.copy(),
        half_cycle=cols[nf + 6] != 0.0, loss_of_lock=cols[nf + 7] != 0.0,
        iode=np.array([r[-1] for r in rows], dtype=int), rejected=rejected, **kw)


# ---------------------------------------------------------------------------------------------
# carrier smoothing
# ---------------------------------------------------------------------------------------------

class CarrierSmoother:
    """Hatch filter of code with carrier, per satellite; returns epochs with smoothed pseudoranges.

    Each system's single-frequency code (GPS/QZSS L1 C/A, Galileo E1, BeiDou B1I) is smoothed, with
    the second code of its iono-free pair when that has phase (GPS/QZSS L2, Galileo E5b/E5a,
    BeiDou B3I/B2I).  With both phases the *divergence-free* phase combinations are used (no
    ionospheric code-carrier divergence)::

        Phi_DF1 = Phi1 + 2 (Phi1 - Phi2)/(gamma - 1),   Phi_DF2 = Phi2 + 2 gamma (Phi1 - Phi2)/(gamma - 1)

    (phases in metres, gamma = (f1/f2)^2), which follow P1 and P2 exactly up to a constant.  Without
    a second phase the single-frequency Hatch filter is used with a shorter window
    (``window_single_s``).  Smoothing restarts on: loss-of-lock / half-cycle flags, a gap longer than
    ``max_gap_s``, a geometry-free phase jump larger than ``gf_jump_m`` between epochs, or a
    code-minus-smoothed-code disagreement larger than ``max_code_jump_m``.  ``window_s`` is the
    averaging length (N = window / interval epochs, growing from 1 after each restart).
    """

    def __init__(self, window_s: float = 600.0, window_single_s: float = 100.0, max_gap_s: float = 65.0,
                 gf_jump_m: float = 0.15, max_code_jump_m: float = 10.0):
        self.window_s = window_s
        self.window_single_s = window_single_s
        self.max_gap_s = max_gap_s
        self.gf_jump_m = gf_jump_m
        self.max_code_jump_m = max_code_jump_m
        self._state: dict[str, dict] = {}
        self.resets: dict[str, int] = {}

    def _reset(self, sat: str, reason: str) -> None:
        self.resets[reason] = self.resets.get(reason, 0) + 1
        self._state.pop(sat, None)

    def apply(self, epoch: GnssEpoch) -> GnssEpoch:
        from dataclasses import replace
        t = epoch.t_gps
        out = []
        for sat, sig in group_by_sat(epoch).items():
            sys_ = sat[0]
            o1 = None
            for s in PRIMARY_SIGNALS.get(sys_, ()):
                if s in sig:
                    o1 = sig[s]
                    break
            o2 = None
            for s in IF_SECOND_SIGNALS.get(sys_, ()):
                if s in sig and sig[s].carrier_cycles == sig[s].carrier_cycles:
                    o2 = sig[s]
                    break
            if o2 is None or (sys_ == "G" and o2.signal[1] == "2"):
                g = GAMMA_L1_L2
            else:
                f1, f2 = pair_frequencies_hz(sat, o1.signal if o1 is not None else "L1", o2.signal)
                g = (f1 / f2) ** 2
            if o1 is None or o1.carrier_cycles != o1.carrier_cycles or o1.pseudorange_m != o1.pseudorange_m:
                self._state.pop(sat, None)
                out.extend(sig.values())
                continue
            phi1 = o1.carrier_cycles * o1.wavelength_m
            dual = o2 is not None and o2.pseudorange_m == o2.pseudorange_m
            if dual:
                phi2 = o2.carrier_cycles * o2.wavelength_m
                gf = phi1 - phi2
                df1 = phi1 + 2.0 * gf / (g - 1.0)
                df2 = phi2 + 2.0 * g * gf / (g - 1.0)
            else:
                gf = float("nan")
                df1, df2 = phi1, float("nan")
            st = self._state.get(sat)
            slip = o1.loss_of_lock or o1.half_cycle_ambiguous or (dual and (o2.loss_of_lock or o2.half_cycle_ambiguous))
            if st is not None:
                if slip:
                    self._reset(sat, "loss of lock"); st = None
                elif t - st["t"] > self.max_gap_s:
                    self._reset(sat, "gap"); st = None
                elif st["dual"] != dual:
                    self._reset(sat, "signal change"); st = None
                elif dual and abs(gf - st["gf"]) > self.gf_jump_m:
                    self._reset(sat, "geometry-free jump"); st = None
            p1 = o1.pseudorange_m
            p2 = o2.pseudorange_m if dual else float("nan")
            if st is None:
                st = {"n": 1, "s1": p1, "s2": p2}
            else:
                nmax = max(1.0, (self.window_s if dual else self.window_single_s) / max(t - st["t"], 1e-3))
                n = min(st["n"] + 1, nmax)
                s1 = p1 / n + (st["s1"] + df1 - st["df1"]) * (n - 1.0) / n
                s2 = p2 / n + (st["s2"] + df2 - st["df2"]) * (n - 1.0) / n if dual else float("nan")
                if abs(s1 - p1) > self.max_code_jump_m or (dual and abs(s2 - p2) > self.max_code_jump_m):
                    self._reset(sat, "code jump")
                    st = {"n": 1, "s1": p1, "s2": p2}
                else:
                    st = {"n": n, "s1": s1, "s2": s2}
            st.update(t=t, df1=df1, df2=df2, gf=gf, dual=dual)
            self._state[sat] = st
            for s, o in sig.items():
                if o is o1:
                    out.append(replace(o, pseudorange_m=st["s1"]))
                elif dual and o is o2:
                    out.append(replace(o, pseudorange_m=st["s2"]))
                else:
                    out.append(o)
        return GnssEpoch(t_gps=t, observations=tuple(out), source=epoch.source)
