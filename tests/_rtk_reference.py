"""The RTK epoch as it was formulated before it was made cheaper (commit 3ed8431): the oracle
that tests/test_rtk_epoch_numerics.py compares the current formulation against on the same data.
The methods below are that commit's ``RtkUpdate`` methods verbatim (the rest of the class is
shared); with ``ErrorStateKalmanFilter.update_joseph`` (the dense Joseph form) as the update.
Not used by the service."""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_triangular

from companion.gnss.double_difference import dd_covariance, model_range_m, receiver_sats, sd_variance_m2
from companion.gnss.lambda_kernel import lambda_ils
from companion.messages import SPEED_OF_LIGHT_MPS, GnssEpoch
from companion.nav.earth import ecef_to_geodetic, skew
from companion.nav.filter import MeasurementBatch, UpdateReport
from companion.nav.rtk_update import FIX_FIXED, FIX_FLOAT, RtkEpochRows, RtkStatus, RtkUpdate, _up

REFERENCE_METHODS = ('rows', 'observe', '_slip_test', 'build', 'gate', 'resolve', '_try')


class ReferenceRtkUpdate(RtkUpdate):
    """RtkUpdate with the former formulation of the epoch's rows, gate and resolution."""

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
        # (the others carry an inter-system bias of up to tens of metres)
        sys0 = next(iter(self.sig), None)
        sig0 = {sys0: self.sig[sys0]} if sys0 is not None else {}
        sr0 = receiver_sats(epoch, eng.ephemerides, r_ant_e, sig0)
        if len(sr0) >= 2:
            p0 = self.sig[sys0][0]
            bias_m = float(np.median([q.code_m[p0] - model_range_m(r_ant_e, q)[0]
                                      for q in sr0.values() if p0 in q.code_m]))
            if math.isfinite(bias_m):
                r_ant_e = r_ant_e - v_ant_e * (bias_m / SPEED_OF_LIGHT_MPS)
        obs = self.observe(eng, epoch, r_ant_e)
        if obs is None:
            return None
        t, common, sr, sb, model_r, model_b = obs
        self._manage(eng, t, common, sr, sb)
        self._slip_test(eng, t, common, sr, sb, model_r, model_b)
        return self.build(eng, obs, l_e, v_ant_e, code_variance_factor)

    def observe(self, eng, epoch: GnssEpoch, r_ant_e: np.ndarray):
        """The rover epoch and its base epoch modelled (rover at the antenna position ``r_ant_e``):
        (t, common satellites above the mask, rover sats, base sats, rover and base models);
        changes nothing but the base epoch's cached geometry."""
        cfg = self.cfg
        b = self._base_for(epoch.t_gps)
        if b is None:
            self.counters["rtk epochs without a base epoch"] += 1
            return None
        if b[2] is None:
            b[2] = receiver_sats(b[1], eng.ephemerides, eng.base.r_e, self.sig)
        sb = b[2]
        sr = receiver_sats(epoch, eng.ephemerides, r_ant_e, self.sig)
        llh_r = ecef_to_geodetic(r_ant_e)
        llh_b = ecef_to_geodetic(eng.base.r_e)
        up = _up(llh_r)
        mask = math.radians(cfg.elevation_mask_deg)
        model_r, model_b, common = {}, {}, []
        for sat in sorted(set(sr) & set(sb)):
            if sr[sat].eph is not sb[sat].eph:
                self.counters["rtk satellite skipped: base and rover ephemerides differ"] += 1
                continue
            mr = model_range_m(r_ant_e, sr[sat], llh_r)
            el = math.asin(max(-1.0, min(1.0, float(mr[1] @ up))))
            if el < mask:
                continue
            sr[sat].elevation_rad = el
            model_r[sat] = mr
            model_b[sat] = model_range_m(eng.base.r_e, sb[sat], llh_b)
            common.append(sat)
        return epoch.t_gps, common, sr, sb, model_r, model_b

    def _slip_test(self, eng, t, common, sr, sb, model_r, model_b) -> None:
        """INS-predicted phase: per ambiguity, the change of its SD residual since the last epoch,
        minus the median change of the signal (the receiver clocks); a jump re-initialises it."""
        cfg = self.cfg
        L = eng.layout
        P = eng.kf.P
        sig_v2 = float(np.trace(P[L.vel, L.vel])) / 3.0
        for sys, s in self._groups:
            keys, d, var = [], [], []
            for sat in common:
                if sat[:1] != sys:
                    continue
                key = (sat, s)
                prev = self._resid.get(key)
                if key not in self.amb or prev is None or not 0.0 < t - prev[0] <= cfg.slip_max_interval_s:
                    continue
                e = self._sd_residual(eng, key, sr, sb, model_r, model_b, self._iono_values(eng))
                keys.append(key)
                d.append(e - prev[1])
                v = sd_variance_m2(sr[sat].elevation_rad, "phase", cfg.sigma_phase_a_m, cfg.sigma_phase_b_m, 1.0)
                var.append(2.0 * v + sig_v2 * (t - prev[0]) ** 2)
            if len(keys) < 4:
                continue
            d = np.asarray(d)
            dev = np.abs(d - np.median(d))
            lim = np.maximum(cfg.slip_min_m, cfg.slip_sigmas * np.sqrt(var))
            for key, bad in zip(keys, dev > lim):
                if bad:
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
        layout, DD covariance) of the modelled epoch ``obs`` (:meth:`observe`)."""
        t, common, sr, sb, model_r, model_b = obs
        cfg = self.cfg
        L = eng.layout
        n = L.n
        H_att = skew(l_e)
        z, Hs, var_sd, kinds, labels, refs, pairs = [], [], [], [], [], {}, []
        groups = []
        for sys, s in self._groups:
            sats = [q for q in common if q[:1] == sys and (q, s) in self.amb]
            if len(sats) < 2:
                continue
            ref = max(sats, key=lambda q: sr[q].elevation_rad)
            refs[(sys, s)] = ref
            kref = (ref, s)
            for kind in ("phase", "code"):
                grp = []
                for sat in sats:
                    if sat == ref:
                        continue
                    key = (sat, s)
                    du = model_r[sat][1] - model_r[ref][1]
                    dd_rho = (model_r[sat][0] - model_b[sat][0]) - (model_r[ref][0] - model_b[ref][0])
                    h = np.zeros(n)
                    h[L.pos] = -du
                    h[L.att] = du @ H_att
                    h[L.toff] = du @ v_ant_e
                    # the differential ionosphere: a delay on the code, an advance on the phase,
                    # (f_L1 / f)^2 of the delay on L1
                    sign = -1.0 if kind == "phase" else 1.0
                    if key[0] in self.iono:
                        mu = (self.amb[key].wavelength_m * 1575.42e6 / SPEED_OF_LIGHT_MPS) ** 2
                        n_sat, n_ref = self.iono[sat], self.iono[ref]
                        h[L.index(n_sat)] = sign * mu
                        h[L.index(n_ref)] = -sign * mu
                        dd_rho = dd_rho + sign * mu * (float(eng.block_states[n_sat][0])
                                                       - float(eng.block_states[n_ref][0]))
                    if kind == "phase":
                        a, ar = self.amb[key], self.amb[kref]
                        lam = a.wavelength_m
                        obs = lam * ((sr[sat].phase_cyc[s] - sb[sat].phase_cyc[s])
                                     - (sr[ref].phase_cyc[s] - sb[ref].phase_cyc[s]))
                        amb = float(eng.block_states[a.name][0]) - float(eng.block_states[ar.name][0])
                        h[L.index(a.name)] = lam
                        h[L.index(ar.name)] = -lam
                        z.append(obs - dd_rho - lam * amb)
                        pairs.append((key, kref))
                    else:
                        obs = (sr[sat].code_m[s] - sb[sat].code_m[s]) - (sr[ref].code_m[s] - sb[ref].code_m[s])
                        z.append(obs - dd_rho)
                    Hs.append(h)
                    f = code_variance_factor if kind == "code" else 1.0
                    var_sd.append(tuple(f * sd_variance_m2(sr[q].elevation_rad, kind, cfg.sigma_phase_a_m,
                                                           cfg.sigma_phase_b_m, cfg.code_phase_ratio)
                                        for q in (sat, ref)))
                    kinds.append(kind)
                    labels.append(f"{sat}-{ref} {s} {kind}")
                    grp.append(len(z) - 1)
                groups.append(grp)
        if not z:
            self.counters["rtk epochs without DD rows"] += 1
            return None
        sd_resid = {}
        for key, a in self.amb.items():
            if key[0] in model_r:
                ion = self._iono_values(eng)
                sd_resid[key] = (self._sd_residual(eng, key, sr, sb, model_r, model_b, ion), model_r[key[0]][1],
                                 float(eng.block_states[a.name][0]), ion.get(key[0], 0.0))
        order = [i for i, k in enumerate(kinds) if k == "phase"] + [i for i, k in enumerate(kinds) if k == "code"]
        R = dd_covariance(var_sd, groups)[np.ix_(order, order)]
        phase_pairs = pairs          # phase rows come first, in the order they were built
        return RtkEpochRows(t, np.asarray(z)[order], np.asarray(Hs)[order], R, [kinds[i] for i in order],
                            [labels[i] for i in order], refs, phase_pairs, sd_resid)

    def gate(self, eng, rows: RtkEpochRows) -> tuple[list[MeasurementBatch], list[UpdateReport]]:
        """Per-row chi-square test against the predicted variance (correlations ignored for the
        test only).  A failing phase row of a held ambiguity set means a wrong fix (dropped at
        once); any other failing phase row re-initialises that satellite's ambiguity.  Returns the
        whitened phase and code batches with their reports."""
        P = eng.kf.P
        S = np.einsum("ij,jk,ik->i", rows.H, P, rows.H) + np.diag(rows.R)
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
        for kind in ("phase", "code"):
            sel = np.flatnonzero(keep & (phase if kind == "phase" else ~phase))
            if not len(sel):
                continue
            Rk = rows.R[np.ix_(sel, sel)]
            C = np.linalg.cholesky(Rk)
            zw = solve_triangular(C, rows.z[sel], lower=True)
            Hw = solve_triangular(C, rows.H[sel], lower=True)
            labels = [rows.labels[i] for i in sel]
            b = MeasurementBatch(f"rtk_{kind}", labels, zw, Hw, np.ones(len(sel)))
            Sw = np.einsum("ij,jk,ik->i", Hw, P, Hw) + 1.0
            reports.append(UpdateReport(b.kind, labels, zw, Sw, ratio[sel], np.ones(len(sel), bool), {}))
            batches.append(b)
            self.counters[f"rtk_{kind} used"] += len(sel)
        self.counters["rtk code rows rejected: innovation gate"] += int(np.count_nonzero(~phase & ~ok))
        return batches, reports

    def resolve(self, eng, rows: RtkEpochRows, dx_float: np.ndarray) -> RtkStatus:
        """LAMBDA on the DD ambiguities after the float update; a validated fix is held (applied to
        the filter).  Returns the epoch's fix status."""
        cfg = self.cfg
        L = eng.layout
        keep = rows.keep if rows.keep is not None else np.ones(len(rows.z), bool)
        pairs = [rows.amb_pairs[i] for i, k in enumerate(rows.kinds) if k == "phase" and keep[i]]
        n_dd = len(pairs)
        if n_dd < cfg.min_fix_ambiguities:
            return self._set_status(rows.t_gps, FIX_FLOAT, math.nan, 0, n_dd)
        T = np.zeros((n_dd, L.n))
        for i, (k, r) in enumerate(pairs):
            T[i, L.index(self.amb[k].name)] = 1.0
            T[i, L.index(self.amb[r].name)] = -1.0
        a = np.array([float(eng.block_states[self.amb[k].name][0] - eng.block_states[self.amb[r].name][0])
                      for k, r in pairs])
        P = eng.kf.P
        idx = np.flatnonzero(np.any(T != 0.0, axis=0))
        Tc = T[:, idx]
        Qa_full = Tc @ P[np.ix_(idx, idx)] @ Tc.T
        active = list(np.argsort(-np.diag(Qa_full)))        # the least certain first out
        while len(active) >= cfg.min_fix_ambiguities:
            sel = np.array(sorted(active))
            out = self._try(eng, rows, dx_float, T[sel], a[sel], Qa_full[np.ix_(sel, sel)])
            if out is not None:
                res, afix = out
                if len(sel) < n_dd:
                    self.counters["rtk epochs fixed partially"] += 1
                self.counters["rtk fixed epochs"] += 1
                if not self.held:
                    self.counters["rtk fixes (from float)"] += 1
                self._hold(eng, T[sel], a[sel], afix)
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

    def _try(self, eng, rows, dx_float, T, a, Qa):
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
        P = eng.kf.P
        PTt = P @ T.T
        S = T @ PTt + np.eye(len(a)) * cfg.hold_sigma_cycles ** 2
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
        # against the INS prediction: the position the fix implies, relative to the predicted one
        L = eng.layout
        if rows.P_prior_pos is not None:
            d = dx_float[L.pos] + dx_hold[L.pos]
            if float(d @ np.linalg.solve(rows.P_prior_pos, d)) > self.ins_chi2_3:
                self.counters["rtk fixes rejected: INS prediction"] += 1
                return None
        return res, afix
