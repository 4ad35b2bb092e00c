"""The per-epoch GNSS code as it was before issue 16's cheaper epoch (commit 3ed8431), kept as
the reference that tests/test_gnss_epoch_fast.py holds the fast versions to (bit for bit).

Readable and slow: one satellite at a time through :func:`companion.gnss.ephemeris.satellite_state`
and :func:`~companion.gnss.ephemeris.transmit_time` (three Kepler solutions and two numpy
arrays per satellite), PRC slopes in four passes, TDCP one row at a time.  Not used by the
package."""
from __future__ import annotations

import math
from collections import deque
from statistics import median

import numpy as np

from companion.gnss.atmosphere import klobuchar_delay_m, saastamoinen_zenith_m, tropo_mapping
from companion.gnss.dgps import (BASE_ELEVATION_MASK_RAD, CLOCK_MAX_GAP_S, CLOCK_MIN_ELEVATION_RAD,
                                 CLOCK_OUTLIER_FLOOR_M, CLOCK_PULL, DgpsCorrector)
from companion.gnss.ephemeris import satellite_state, transmit_time
from companion.gnss.phase import BASE_HISTORY_EPOCHS, BaseCarrierBook, PhaseRecord, RoverCarrierBook, _line_of_sight
from companion.gnss.prepare import (CODE_SIGMA_A_M, CODE_SIGMA_B_M, DGPS_AGE_SIGMA_MPS, DGPS_SIGMA_M,
                                    IONO_MODEL_ERROR_FRAC, IONO_NO_MODEL_SIGMA_M, TROPO_ZENITH_ERROR_M,
                                    UNKNOWN_POSITION_NORM_M, PreparedEpoch, form_pseudorange, group_by_sat)
from companion.gnss.signals import SUPPORTED_SYSTEMS, clock_group, group_delay_m
from companion.gnss.ephemeris_store import EphemerisStore
from companion.messages import SPEED_OF_LIGHT_MPS, BaseStationPosition, GnssEpoch
from companion.nav.earth import OMEGA_IE_RADPS, ecef_to_geodetic, skew
from companion.nav.filter import LAYOUT, MeasurementBatch
from companion.nav.measurements import InsPoint, antenna_state

C = SPEED_OF_LIGHT_MPS
_TEN_DEG_RAD = math.radians(10.0)


def _rotate(r, v, tau):
    a = OMEGA_IE_RADPS * tau
    c, s = math.cos(a), math.sin(a)
    return ((c * r[0] + s * r[1], -s * r[0] + c * r[1], r[2]),
            (c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]))


def prepare_epoch(epoch: GnssEpoch, store: EphemerisStore, r_approx_e, *,
                  dgps: "DgpsCorrector | None" = None, elevation_mask_rad: float = math.radians(10.0),
                  klobuchar=None, signal: str = "L1C", rx_clock_bias_m: float = 0.0,
                  apply_models: bool = True, tropo: bool = True, systems: str = "G") -> PreparedEpoch:
    """Corrected measurements of one epoch (see module docstring for the model and conventions).

    ``systems``: the constellations used, letters of :data:`SUPPORTED_SYSTEMS` ('G' by default:
    GPS only, as the single-clock filter needs; 'GECJ' for all four).  Satellites of other systems
    are rejected as 'system not selected' ('unsupported system' for GLONASS, SBAS, NavIC).  The
    pseudorange model is the same for all; each system has its own clock offset, estimated by
    :func:`companion.gnss.spp.solve_spp` as an inter-system bias.

    ``klobuchar``: (alpha[4], beta[4]) or None (then no iono correction standalone).
    ``apply_models=False`` applies the satellite clock only (used by the DGPS base: raw P + c*dt_sat).
    """
    t_rx = epoch.t_gps
    r0 = np.asarray(r_approx_e, dtype=float)
    rx, ry, rz = float(r0[0]), float(r0[1]), float(r0[2])
    known = math.sqrt(rx * rx + ry * ry + rz * rz) > UNKNOWN_POSITION_NORM_M
    ztd = 0.0
    if known:
        lat, lon, h = ecef_to_geodetic(r0)
        sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
        east = (-so, co, 0.0)
        north = (-sl * co, -sl * so, cl)
        up = (cl * co, cl * so, sl)
        if apply_models and dgps is None and tropo and -1000.0 < h < 20000.0:
            zhd, zwd = saastamoinen_zenith_m(lat, h)
            ztd = zhd + zwd
        else:
            ztd = 0.0
    rejected: dict[str, str] = {}
    rows = []
    use_iono = apply_models and dgps is None and klobuchar is not None and known
    alpha, beta = (klobuchar if klobuchar is not None else (None, None))
    nan = float("nan")
    for sat, sig in group_by_sat(epoch).items():
        sys_ = sat[0]
        if sys_ not in systems or sys_ not in SUPPORTED_SYSTEMS:
            rejected[sat] = "system not selected" if sys_ in SUPPORTED_SYSTEMS else "unsupported system"
            continue
        p, o, codes, tgd_fac, iono_fac, code_scale = form_pseudorange(sig, signal, sys_)
        a2 = (CODE_SIGMA_A_M * code_scale) ** 2
        b2 = (CODE_SIGMA_B_M * code_scale) ** 2
        if o is None:
            rejected[sat] = "no pseudorange"
            continue
        has_p = p == p and math.isfinite(p)
        has_l = o.carrier_cycles == o.carrier_cycles
        if not has_p and not has_l:
            rejected[sat] = "no pseudorange"
            continue
        eph, reason = store.select_with_reason(sat, t_rx)
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
                eph2, _ = store.select_with_reason(sat, t_rx, iode=iode_c)
                if eph2 is None:
                    rejected[sat] = "IODE mismatch"
                    continue
                eph = eph2
            prc, age, why = dgps.correction(sat, t_rx, eph.iode)
            if why:
                rejected[sat] = why
                continue
        if has_p:
            t_tx = transmit_time(t_rx, p, eph)
        else:
            t_tx = None
        # geometric travel time, two iterations (the first from the unrotated position)
        if t_tx is None:  # phase only: transmit time from the geometric range
            r_s, v_s, dts, ddts = satellite_state(eph, t_rx - rx_clock_bias_m / C - 0.075)
            tau = math.dist(r_s, r0) / C if known else 0.075
            t_tx = t_rx - rx_clock_bias_m / C - tau      # GPS time: no satellite clock term here
        r_s, v_s, dts, ddts = satellite_state(eph, t_tx)
        tau = math.dist(r_s, r0) / C
        rr, vv = _rotate(r_s, v_s, tau)
        tau = math.dist(rr, r0) / C
        rr, vv = _rotate(r_s, v_s, tau)
        dx, dy, dz = rr[0] - rx, rr[1] - ry, rr[2] - rz
        rho = math.sqrt(dx * dx + dy * dy + dz * dz)
        if known:
            ux, uy, uz = dx / rho, dy / rho, dz / rho
            e_ = ux * east[0] + uy * east[1]
            n_ = ux * north[0] + uy * north[1] + uz * north[2]
            u_ = ux * up[0] + uy * up[1] + uz * up[2]
            el = math.asin(max(-1.0, min(1.0, u_)))
            az = math.atan2(e_, n_) % (2.0 * math.pi)
            if el < elevation_mask_rad:
                rejected[sat] = "below elevation mask"
                continue
            sin_el = max(math.sin(el), 0.05)
        else:
            el = az = nan
            sin_el = 1.0
        iono = tro = 0.0
        var = a2 + b2 / (sin_el * sin_el)
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
            if not math.isfinite(pr):
                rejected[sat] = "non-finite"
                continue
        if not (math.isfinite(rr[0]) and math.isfinite(dts)):
            rejected[sat] = "non-finite"
            continue
        rows.append((sat, rr, vv, pr, math.sqrt(var), C * dts, C * ddts, o.carrier_cycles, o.wavelength_m,
                     o.doppler_hz, o.cn0_dbhz, o.lock_time_s, o.half_cycle_ambiguous, o.loss_of_lock,
                     el, az, eph.iode, age, iono, tro, math.sqrt(var_slow)))
    n = len(rows)
    if n:
        cols = list(zip(*rows))
        arr = lambda k: np.array(cols[k], dtype=float)
        return PreparedEpoch(
            t_gps=t_rx, signal=signal, r_approx_e=r0.copy(), sats=list(cols[0]),
            r_sat_e=np.array(cols[1], dtype=float), v_sat_e=np.array(cols[2], dtype=float),
            pseudorange_m=arr(3), sigma_pseudorange_m=arr(4), sat_clock_bias_m=arr(5),
            sat_clock_drift_mps=arr(6), carrier_cycles=arr(7), wavelength_m=arr(8), doppler_hz=arr(9),
            cn0_dbhz=arr(10), lock_time_s=arr(11), half_cycle=np.array(cols[12], dtype=bool),
            loss_of_lock=np.array(cols[13], dtype=bool), elevation_rad=arr(14), azimuth_rad=arr(15),
            iode=np.array(cols[16], dtype=int), dgps_age_s=arr(17), iono_m=arr(18), tropo_m=arr(19),
            rejected=rejected, sigma_pseudorange_slow_m=arr(20))
    z = np.zeros(0)
    return PreparedEpoch(
        t_gps=t_rx, signal=signal, r_approx_e=r0.copy(), sats=[], r_sat_e=np.zeros((0, 3)),
        v_sat_e=np.zeros((0, 3)), pseudorange_m=z, sigma_pseudorange_m=z, sat_clock_bias_m=z,
        sat_clock_drift_mps=z, carrier_cycles=z, wavelength_m=z, doppler_hz=z, cn0_dbhz=z, lock_time_s=z,
        half_cycle=np.zeros(0, bool), loss_of_lock=np.zeros(0, bool), elevation_rad=z, azimuth_rad=z,
        iode=np.zeros(0, int), dgps_age_s=z, iono_m=z, tropo_m=z, rejected=rejected)



def tdcp_batch(ins: InsPoint, prep, previous: dict[str, PhaseRecord], lever_arm_b: np.ndarray,
               sigma_phase_m: float, sigma_rate_floor_mps: float, max_interval_s: float,
               layout=LAYOUT, phase_correction_m: dict[str, float] | None = None,
               elevation_scaling: bool = False, specific_force_e: np.ndarray | None = None) -> MeasurementBatch:
    """Pseudorange rate from time-differenced carrier phase (seed 000 eqs 2-7, 14).

    Over one epoch interval the integer ambiguity cancels.  The *prediction* uses the INS
    displacement between the two epochs (not the current velocity times the interval), so
    vehicle acceleration inside the interval costs nothing:

        z = [lambda (phi_k - phi_k-1) + c (dt_sat,k - dt_sat,k-1) + corr]/T
            - [ |r_sat,k - r_ant,k| - range_k-1 + drift T ] / T

    The error of the INS displacement is modelled as dv_k T (the velocity error over the
    interval), giving the paper's range-rate Jacobian H_v = -u plus the receiver clock drift.
    With ``specific_force_e`` (the mean specific force over the interval, ECEF, m/s^2) the
    displacement error also carries how the velocity error grew inside the interval,
    ``(T^2 / 2) ([f x] psi + C_b_e dba)``: with a heading uncertain by degrees (an initialisation
    in flight) and the vehicle accelerating, that term is several TDCP sigmas, and leaving it out
    made the gate reject good rows until the filter re-initialised again.
    A time-tag error dt_imu is common to both epochs (it is a slowly varying state): it changes the
    interval's range difference by (u_k.v_ant,k - u_k-1.v_ant,k-1) dt_imu, the change of the
    line-of-sight velocity over the interval (``PhaseRecord.los_rate_mps`` holds the earlier one).
    ``phase_correction_m`` optionally removes common errors (e.g. a base station's time-differenced
    carrier, see :mod:`companion.nav.engine`).  With ``elevation_scaling`` the carrier noise grows as
    1/sin(elevation) (multipath), floored at 10 degrees.
    """
    r_ant, v_ant, _ = antenna_state(ins, lever_arm_b)
    rows, labels, zs, rvar = [], [], [], []
    f_cross = skew(specific_force_e) if specific_force_e is not None else None
    for i, sat in enumerate(prep.sats):
        prev = previous.get(sat)
        phi = prep.carrier_cycles[i]
        if prev is None or not math.isfinite(phi):
            continue
        T = prep.t_gps - prev.t_gps
        if not (0.0 < T <= max_interval_s) or prep.wavelength_m[i] != prev.wavelength_m:
            continue
        corr = 0.0
        if phase_correction_m is not None:
            c = phase_correction_m.get(sat)
            if c is None:
                continue
            corr = c
        d = prep.r_sat_e[i] - r_ant
        rho = math.sqrt(float(d @ d))
        u = d / rho
        dphase_m = prep.wavelength_m[i] * (phi - prev.carrier_cycles)
        meas = (dphase_m + prep.sat_clock_bias_m[i] - prev.sat_clock_bias_m + corr) / T
        pred = (rho - prev.geometric_range_m) / T + ins.clock_drift_mps
        u_mid = u + prev.los_e
        u_mid /= math.sqrt(float(u_mid @ u_mid))
        h = np.zeros(layout.n)
        h[layout.vel] = -u_mid
        h[layout.pos] = (prev.los_e - u) / T
        h[layout.drift] = 1.0
        # no lever-arm attitude column: see antenna_velocity_attitude_partial
        if f_cross is not None:
            h[layout.att] = -0.5 * T * (u_mid @ f_cross)
            h[layout.ba] = -0.5 * T * (u_mid @ ins.C_b_e)
        # dt_imu: the same tag error at both epochs moved both ranges by u . v_ant of their epoch
        h[layout.toff] = (float(u @ v_ant) - prev.los_rate_mps) / T
        rows.append(h)
        labels.append(sat)
        zs.append(meas - pred)
        sig = sigma_phase_m
        if elevation_scaling:
            sig /= math.sin(max(float(prep.elevation_rad[i]), _TEN_DEG_RAD))
        rvar.append(2.0 * sig * sig / (T * T) + sigma_rate_floor_mps ** 2)
    H = np.array(rows) if rows else np.zeros((0, layout.n))
    return MeasurementBatch("tdcp", labels, np.array(zs), H, np.array(rvar))


class ReferenceDgpsCorrector(DgpsCorrector):
    """DgpsCorrector with the reference update_base (and prepare_epoch)."""

    def update_base(self, base_epoch: GnssEpoch, base: BaseStationPosition, store: EphemerisStore) -> int:
        """Compute corrections from one base epoch; returns the number of satellites corrected."""
        r_base = np.asarray(base.r_e, dtype=float)
        prep = prepare_epoch(base_epoch, store, r_base, elevation_mask_rad=BASE_ELEVATION_MASK_RAD,
                             signal=self.signal, apply_models=False, systems=self.systems)
        t = base_epoch.t_gps
        self.last_prepared = prep      # reused by the engine's base-carrier bookkeeping
        for sat, why in prep.rejected.items():
            self.counters["base: " + why] += 1
        for i, sat in enumerate(prep.sats):
            if prep.carrier_cycles[i] == prep.carrier_cycles[i]:
                self._phase[sat] = (t, float(prep.carrier_cycles[i]), float(prep.wavelength_m[i]))
            else:
                self._phase.pop(sat, None)
        ok = np.isfinite(prep.pseudorange_m)
        if not np.any(ok):
            self.counters["base epoch without pseudoranges"] += 1
            return 0
        rho = np.linalg.norm(prep.r_sat_e - r_base, axis=1)
        raw = rho - prep.pseudorange_m
        w = 1.0 / prep.sigma_pseudorange_m ** 2
        sys_of = np.array([clock_group(sat) for sat in prep.sats])
        raw_now = {sat: float(raw[i]) for i, sat in enumerate(prep.sats) if ok[i]}
        continuing = self.t_base_gps is not None and 0.0 < t - self.t_base_gps <= CLOCK_MAX_GAP_S
        clocks: dict[str, float] = {}
        for sys_ in dict.fromkeys(sys_of[ok]):      # each system's receiver clock (inter-system biases)
            clocks[sys_] = self._system_clock(raw, w, ok & (sys_of == sys_), prep, raw_now, continuing, sys_)
        self._raw_prev = raw_now
        self.base_clocks_m = clocks
        self.base_clock_m = next(iter(clocks.values()))
        self.t_base_gps = t
        n = 0
        new_prc = {}
        for i, sat in enumerate(prep.sats):
            if not ok[i]:
                continue
            prc = float(raw[i] - clocks[clock_group(sat)])
            iode = int(prep.iode[i])
            h = self._hist.get(sat)
            if h is None or (h and (h[-1][2] != iode or prep.loss_of_lock[i])):
                h = deque()
                self._hist[sat] = h
            h.append((t, prc, iode))
            while h and t - h[0][0] > self.rrc_window_s + 1e-6:
                h.popleft()
            rrc = 0.0
            if len(h) >= 2:
                # least-squares slope of PRC against time (plain floats: ~30 points, every epoch)
                n_h = len(h)
                tm = sum(x[0] - t for x in h) / n_h
                pm = sum(x[1] for x in h) / n_h
                den = sum((x[0] - t - tm) ** 2 for x in h)
                if den > 0:
                    rrc = sum((x[0] - t - tm) * (x[1] - pm) for x in h) / den
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
        for _ in range(5):
            clk = float(np.sum(w[use] * raw[use]) / np.sum(w[use]))
            dev = np.abs(raw - clk)
            mad = 1.4826 * float(np.median(dev[use]))
            new_use = use & (dev <= max(3.0 * mad, CLOCK_OUTLIER_FLOOR_M))
            if new_use.sum() == use.sum() or new_use.sum() < 2:
                break
            use = new_use
        prev = self._raw_prev
        common = [sat for sat in raw_now if sat in prev and clock_group(sat) == sys_]
        last = self.base_clocks_m.get(sys_, float("nan"))
        if len(common) >= 2 and continuing and math.isfinite(last):
            step = median([raw_now[sat] - prev[sat] for sat in common])
            continued = last + step
            clk = continued + CLOCK_PULL * (clk - continued)
        return clk


class ReferenceRoverCarrierBook(RoverCarrierBook):
    def remember(self, prep, r_ant_e: np.ndarray, v_ant_e: np.ndarray) -> None:
        """Replace the records by this epoch's carriers, ranges taken from the antenna state given
        (the corrected one); satellites without a usable carrier now are forgotten."""
        seen = set()
        finite = np.isfinite(prep.carrier_cycles)
        if np.any(finite):
            rho, u = _line_of_sight(prep.r_sat_e[finite], r_ant_e)
            for j, i in enumerate(np.flatnonzero(finite)):
                sat = prep.sats[i]
                if bool(prep.half_cycle[i]):
                    continue   # unresolved half-cycle: do not build on this carrier
                self.records[sat] = PhaseRecord(prep.t_gps, float(prep.carrier_cycles[i]),
                                                float(prep.wavelength_m[i]), float(rho[j]),
                                                float(prep.sat_clock_bias_m[i]), u[j], float(prep.lock_time_s[i]),
                                                float(u[j] @ v_ant_e))
                seen.add(sat)
        for sat in [s for s in self.records if s not in seen]:
            del self.records[sat]


class ReferenceBaseCarrierBook(BaseCarrierBook):
    def remember(self, prep, r_base_e: np.ndarray) -> None:
        """``prep``: the base epoch as the DGPS corrector prepared it (same satellites, same clocks)."""
        finite = np.isfinite(prep.carrier_cycles)
        if not np.any(finite):
            return
        rho, _ = _line_of_sight(prep.r_sat_e[finite], r_base_e)
        for j, i in enumerate(np.flatnonzero(finite)):
            sat = prep.sats[i]
            hist = self.history.setdefault(sat, deque(maxlen=BASE_HISTORY_EPOCHS))
            if prep.loss_of_lock[i] or prep.half_cycle[i]:
                hist.clear()
                if prep.half_cycle[i]:
                    continue
            hist.append((prep.t_gps, float(prep.carrier_cycles[i]), float(prep.wavelength_m[i]),
                         float(rho[j]), float(prep.sat_clock_bias_m[i])))

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
            a = min(hist, key=lambda rec: abs(rec[0] - t_a), default=None)
            b = min(hist, key=lambda rec: abs(rec[0] - t_b), default=None)
            if (a is None or a is b or abs(a[0] - t_a) > tol_s or abs(b[0] - t_b) > tol_s
                    or a[2] != b[2]):
                continue
            resid[sat] = b[2] * (b[1] - a[1]) + (b[4] - a[4]) - (b[3] - a[3])
        if len(resid) < 2:
            return {}
        common = median(resid.values())
        return {sat: -(e - common) for sat, e in resid.items()}
