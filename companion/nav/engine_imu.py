"""The engine's IMU-rate path: mechanization, covariance propagation, history, stillness.

The nominal state lives in :mod:`.nav_state`'s packed array (``_ws``); ``r_e``, ``v_e``,
``C_b_e``, ``b_a``, ``b_g``, ``t_gps`` and the clock are properties over it (a read returns a copy,
a write copies in), so the rest of the engine reads and assigns them as plain attributes.

Two implementations of one step, chosen at :meth:`initialize` time:

* compiled (numba there and not disabled, :mod:`.imu_kernel`): one call of
  :func:`.imu_fused.imu_step` per sample; the rare branches (time gaps, bridged samples, a
  smoother attached, new gravity point or interval) come back to Python by the call's flag;
* :meth:`_imu_reference`, the readable pure-Python path (and the one without numba).

The IMU screen's and the stillness test's state is kept in ``_ws`` on the compiled path and in the
:class:`.imu_screen.ImuScreen` / :class:`.stillness.StillnessDetector` objects on the other; they
are copied across when the path changes (an initialisation) and when Python needs them.
"""
from __future__ import annotations

import math

import numpy as np

from . import imu_fused as F
from . import imu_kernel
from . import nav_state as S
from ..messages import ImuSample
from .earth import OMEGA_IE_RADPS, gravity_ecef, gravity_gradient_ecef
from .strapdown import strapdown_step_with_force

# over lost IMU samples the last sample's rate and specific force are held; the change the vehicle
# could have made meanwhile (1-sigma, a manoeuvring multirotor) widens the covariance
IMU_GAP_ACCEL_SIGMA_MPS2 = 1.0
IMU_GAP_RATE_SIGMA_RADPS = 0.1


def _vector(sl):
    def get(self):
        return None if self._ws_none.get(sl.start) else self._ws[sl].copy()

    def put(self, x):
        if x is None:
            self._ws_none[sl.start] = True
            self._ws[sl] = math.nan
        else:
            self._ws_none[sl.start] = False
            self._ws[sl] = np.ravel(x)
    return property(get, put)


def _matrix(start):
    sl = slice(start, start + 9)

    def get(self):
        return None if self._ws_none.get(start) else self._ws[sl].reshape(3, 3).copy()

    def put(self, x):
        if x is None:
            self._ws_none[start] = True
            self._ws[sl] = math.nan
        else:
            self._ws_none[start] = False
            self._ws[sl] = np.ravel(x)
    return property(get, put)


def _scalar(i):
    def get(self):
        return float(self._ws[i])

    def put(self, x):
        self._ws[i] = x
    return property(get, put)


class ImuPath:
    """Mixin of :class:`.engine.NavEngine`: the IMU path and the INS history."""

    t_gps = _scalar(S.T)
    r_e = _vector(slice(S.R, S.R + 3))
    v_e = _vector(slice(S.V, S.V + 3))
    C_b_e = _matrix(S.C)
    b_a = _vector(slice(S.BA, S.BA + 3))
    b_g = _vector(slice(S.BG, S.BG + 3))
    clock_bias_m = _scalar(S.CLK)
    clock_drift_mps = _scalar(S.DRIFT)

    def _init_imu_state(self) -> None:
        cfg = self.cfg
        window = max(3, int(cfg.imu_median_window))
        cap = max(64, int(cfg.zupt_window_s * 2000.0) + 2)      # the stillness window up to 2 kHz
        self._ws = S.new_ws(window, cap)
        self._ws_none: dict = {}
        self._ws[S.HIST_S] = cfg.history_s
        self._ws[S.REFRESH2] = cfg.gravity_gradient_refresh_m ** 2
        self._ws[S.LAST_TAU] = 1.0
        self._hist = S.InsHistory(self._ws)
        self._grad = None               # the gravity gradient (pure-Python path: its object identity)
        self._fused = False             # the compiled path is in use
        self._fused_out = np.zeros(2, dtype=np.int64)
        self._still_stats = np.zeros(5)  # the stillness window's largest gyro / accel std, gyro mean (compiled)
        self._P_checked = None          # the covariance array last seen contiguous float64 (checked once)

    # ------------------------------------------------------------------ path selection
    def _select_imu_path(self) -> None:
        """At an initialisation: the compiled path if the kernels are there, else the reference;
        the screen and stillness state follow."""
        if self._fused:
            self._state_to_objects()
        self._fused = imu_kernel.compiled() is not None
        ws = self._ws
        L = self.kf.layout
        ws[S.I_ATT], ws[S.I_POS], ws[S.I_VEL] = L.att.start, L.pos.start, L.vel.start
        ws[S.I_BA], ws[S.I_BG] = L.ba.start, L.bg.start
        ws[S.KTAU] = -1.0
        self._hist.correct_kernel = self._hist.interpolate_kernel = None
        if self._fused:
            k = F.ensure_compiled()
            self._hist.correct_kernel, self._hist.interpolate_kernel = k.history_correct, k.history_interpolate
            self._objects_to_state()

    def _objects_to_state(self) -> None:
        self._screen_to_state()
        self._still_to_state()

    def _screen_to_state(self) -> None:
        ws, scr = self._ws, self.imu_screen
        ws[S.SCR_ON] = 1.0 if scr is not None else 0.0
        if scr is not None:
            n = int(ws[S.SCR_N])
            ws[S.SCR_K] = scr._k
            ws[S.SCR_PREV_OK] = 1.0 if scr._prev_ok else 0.0
            ws[S.SCR_PREV:S.SCR_PREV + 6] = scr._prev
            ws[S.SCR_HAS_GOOD] = 1.0 if scr._good is not None else 0.0
            ws[S.SCR_GOOD:S.SCR_GOOD + 6] = scr._good if scr._good is not None else 0.0
            ws[S.SCR_WIN:S.SCR_WIN + 6 * n] = np.ravel(scr._win)
            ws[S.SCR_CW], ws[S.SCR_CF] = scr._clip_w, scr._clip_f
            ws[S.SCR_JW], ws[S.SCR_JF] = scr.gyro_jump_radps, scr.accel_jump_mps2

    def _still_to_state(self) -> None:
        ws, st = self._ws, self._still
        ws[S.ST_ON] = 1.0 if st is not None else 0.0
        if st is not None:
            cap = int(ws[S.ST_CAP])
            rows = list(st.buf)[-cap:]
            o = S.still_offset(ws)
            ws[o:o + 7 * len(rows)] = np.ravel(rows) if rows else 0.0
            ws[S.ST_HEAD] = len(rows) % cap
            ws[S.ST_NVALID] = len(rows)
            ws[S.ST_MAXLEN] = min(st.buf.maxlen, cap)
            ws[S.ST_SINCE_CHECK], ws[S.ST_SINCE_UPDATE] = st._since_check_s, st._since_update_s
            ws[S.ST_WINDOW] = st.window_s

    def _screen_from_state(self) -> None:
        ws, scr = self._ws, self.imu_screen
        n = int(ws[S.SCR_N])
        scr._k = int(ws[S.SCR_K])
        scr._prev_ok = bool(ws[S.SCR_PREV_OK])
        scr._prev = tuple(ws[S.SCR_PREV:S.SCR_PREV + 6].tolist())
        scr._good = tuple(ws[S.SCR_GOOD:S.SCR_GOOD + 6].tolist()) if ws[S.SCR_HAS_GOOD] else None
        scr._win = [ws[S.SCR_WIN + i * n:S.SCR_WIN + (i + 1) * n].tolist() for i in range(6)]

    def _state_to_objects(self) -> None:
        from collections import deque
        if self.imu_screen is not None:
            self._screen_from_state()
        st = self._still
        if st is not None:
            ws = self._ws
            st.buf = deque((tuple(r) for r in self._still_rows(int(ws[S.ST_NVALID])).tolist()),
                           maxlen=int(ws[S.ST_MAXLEN]))
            st._since_check_s, st._since_update_s = float(ws[S.ST_SINCE_CHECK]), float(ws[S.ST_SINCE_UPDATE])

    def _still_rows(self, m: int) -> np.ndarray:
        """The last m stillness rows, oldest first."""
        ws = self._ws
        cap, head = int(ws[S.ST_CAP]), int(ws[S.ST_HEAD])
        ring = ws[S.still_offset(ws):S.still_offset(ws) + 7 * cap].reshape(cap, 7)
        if m <= head:
            return ring[head - m:head]          # a view: no copy when the window does not wrap
        return np.concatenate((ring[cap - (m - head):], ring[:head]))

    def _still_due(self, tau_sample: float) -> bool:
        """The stillness test, due after a compiled step (StillnessDetector.add's second half)."""
        ws, st = self._ws, self._still
        ws[S.ST_SINCE_CHECK] = 0.0
        m = st.window_samples(tau_sample)
        if ws[S.ST_MAXLEN] != m:
            if m > ws[S.ST_CAP]:
                self.counters["stillness window longer than its buffer (not tested)"] += 1
                return False
            ws[S.ST_NVALID] = min(ws[S.ST_NVALID], m)
            ws[S.ST_MAXLEN] = m
        if ws[S.ST_NVALID] < m:
            return False
        st._since_update_s = float(ws[S.ST_SINCE_UPDATE])
        stats = self._still_stats
        F.kernels().still_window_std(ws, m, stats)
        still = st.decide(float(stats[0]), float(stats[1]), stats[2:5], m)
        ws[S.ST_SINCE_UPDATE] = st._since_update_s
        return still

    # ------------------------------------------------------------------ the step
    def process_imu(self, s):
        if not self.initialized:
            self.counters["imu before init"] += 1
            return None
        if self._fused and self.smoother is None:
            kf = self.kf
            P = kf.P
            if P is not self._P_checked:        # a new array (an update replaced it): check it once
                if not P.flags.c_contiguous or P.dtype != np.float64:
                    P = kf.P = np.ascontiguousarray(P, dtype=float)
                self._P_checked = P
            ws = self._ws
            ws[S.KTAU] = kf._last_tau
            f = F.kernels().imu_step(ws, self._hist.hist, P, kf._kernel_buf, s.t_gps, s.dt_s, s.dtheta_b, s.dv_b,
                                     False)
            if f == F.OK:
                if self._pending or self.cfg.nhc_enabled:
                    self._after_step(s.dt_s)
                return None
            return self._fused_flag(s, f)
        if self._fused:
            return self._imu_python(s)
        return self._imu_reference(s)

    def process_imu_batch(self, t_gps, dt_s, dtheta_b, dv_b) -> None:
        """IMU samples as arrays (t_gps, dt_s: (N,); dtheta_b, dv_b: (N, 3)), the same as
        :meth:`process_imu` on each in turn, to the bit: on the compiled path one call runs the
        kernel over the samples until one needs Python (replay, benchmarks)."""
        t = np.ascontiguousarray(t_gps, dtype=float)
        tau = np.ascontiguousarray(dt_s, dtype=float)
        th = np.ascontiguousarray(dtheta_b, dtype=float)
        dv = np.ascontiguousarray(dv_b, dtype=float)
        n, i = len(t), 0
        out = self._fused_out
        while i < n:
            if not (self._fused and self.initialized and self.smoother is None and not self._pending
                    and not self.cfg.nhc_enabled):
                self.process_imu(ImuSample(float(t[i]), float(tau[i]), th[i], dv[i]))
                i += 1
                continue
            kf = self.kf
            if not kf.P.flags.c_contiguous or kf.P.dtype != np.float64:
                kf.P = np.ascontiguousarray(kf.P, dtype=float)
            self._ws[S.KTAU] = kf._last_tau
            F.kernels().imu_run(self._ws, self._hist.hist, kf.P, kf._kernel_buf, t, tau, th, dv, i, math.inf, out)
            i, f = int(out[0]), int(out[1])
            if f == F.STILL_DUE:
                if self._still_due(float(tau[i - 1])) and self.ground_mode:
                    self._zero_motion_update()
                self._after_step(float(tau[i - 1]))
            elif f != F.OK:
                self.process_imu(ImuSample(float(t[i]), float(tau[i]), th[i], dv[i]))
                i += 1

    def _fused_flag(self, s, f):
        """A compiled step that came back to Python."""
        if f == F.STILL_DUE:
            if self._still_due(s.dt_s) and self.ground_mode:
                self._zero_motion_update()
            self._after_step(s.dt_s)
            return None
        if f == F.NOT_AFTER:
            self.counters["imu sample not after previous (dropped)"] += 1
            return None
        if f == F.INVALID:
            self.counters["imu sample invalid (dropped)"] += 1
            return None
        if f == F.SLOW:
            return self._imu_python(s)
        self._fix_prerequisite(f, s.dt_s)
        return self.process_imu(s)

    def _fix_prerequisite(self, f: int, tau: float) -> None:
        """What the kernel asked for before it could step: interval constants, gravity, room."""
        ws = self._ws
        if f == F.INTERVAL:
            self.kf._set_interval(tau)
            ang = OMEGA_IE_RADPS * tau
            ws[S.TURN_CO], ws[S.TURN_SI] = math.cos(ang), math.sin(ang)
            ws[S.KTAU] = tau
        elif f == F.GRAVITY:
            r0 = self.r_e
            self._set_gravity_point(r0)
        elif f == F.HIST_FULL:
            self._hist.grow()
        else:
            raise RuntimeError(f"IMU kernel flag {f}")

    def _set_gravity_point(self, r0) -> None:
        ws = self._ws
        self._grad = gravity_gradient_ecef(r0)
        ws[S.GRAD_R:S.GRAD_R + 3] = r0
        ws[S.G_REF:S.G_REF + 3] = gravity_ecef(r0)
        ws[S.GRAD:S.GRAD + 9] = self._grad.ravel()
        ws[S.GRAD_OK] = 1.0

    def _screen_and_gap(self, s):
        """Validity, the IMU screen and the time gap, in Python: (dtheta, dv, tau, bridged) to
        integrate, or None (dropped)."""
        tau = s.dt_s
        if not (s.t_gps > self.t_gps):
            self.counters["imu sample not after previous (dropped)"] += 1
            return None
        th = s.dtheta_b.tolist()
        dvl = s.dv_b.tolist()
        if not (0.0 < tau < 0.1) or not math.isfinite(th[0] + th[1] + th[2] + dvl[0] + dvl[1] + dvl[2]):
            self.counters["imu sample invalid (dropped)"] += 1
            return None
        scr = self.imu_screen
        bridged = False
        if scr is not None:
            if self._fused:
                self._screen_from_state()
            ok = scr.check(th, dvl, tau, s.t_gps)
            if self._fused:
                self._screen_to_state()
            if not ok:
                if not scr.bridged:
                    return None            # nothing good to hold yet (counted by the screen)
                th, dvl, bridged = scr.dtheta_b, scr.dv_b, True
        if self.smoother is not None:
            self.smoother.before_step(self)
        gap = s.t_gps - self.t_gps - tau
        if abs(gap) > 0.5 * tau:
            self.counters["imu time gap"] += 1
        if gap > 0.5 * tau:
            # lost samples (a link drops IMU messages; the decoder restarts its chain after a long
            # interval): hold this sample's rate and specific force over the gap -- integrating
            # only its own interval left the position behind by v x gap (4 m per 0.5 s at 9 m/s,
            # unseen by the covariance) -- and widen the covariance by what the vehicle could have
            # done meanwhile (IMU_GAP_*)
            k = (tau + gap) / tau
            th = [x * k for x in th]
            dvl = [x * k for x in dvl]
            tau += gap
            self.counters["imu gap bridged (s, x1000)"] += int(round(gap * 1000.0))
            va, vw = (IMU_GAP_ACCEL_SIGMA_MPS2 * gap) ** 2, (IMU_GAP_RATE_SIGMA_RADPS * gap) ** 2
            self.kf.add_body_noise(self.C_b_e, (vw, vw, vw), (va, va, va))
        return th, dvl, tau, bridged

    def _imu_python(self, s):
        """The compiled path's slow branch: screen and gap in Python, the step by the kernel."""
        x = self._screen_and_gap(s)
        if x is None:
            return None
        th, dvl, tau, bridged = x
        ws = self._ws
        C0 = self.C_b_e
        ws[S.OV_TAU] = tau
        ws[S.OV_TH:S.OV_TH + 3] = th
        ws[S.OV_DV:S.OV_DV + 3] = dvl
        kf = self.kf
        while True:
            if not kf.P.flags.c_contiguous or kf.P.dtype != np.float64:
                kf.P = np.ascontiguousarray(kf.P, dtype=float)
            ws[S.KTAU] = kf._last_tau
            f = F.kernels().imu_step(ws, self._hist.hist, kf.P, kf._kernel_buf, s.t_gps, s.dt_s, s.dtheta_b, s.dv_b,
                                     True)
            if f in (F.OK, F.STILL_DUE):
                break
            self._fix_prerequisite(f, tau)
        if bridged:
            scr = self.imu_screen
            kf.add_body_noise(C0, scr.var_dtheta_b, scr.var_dv_b)    # what the sample could have hidden
        if self.smoother is not None:
            self.smoother.after_step(self)
        if f == F.STILL_DUE and self._still_due(s.dt_s) and self.ground_mode:
            self._zero_motion_update()
        self._after_step(tau)
        return None

    def _imu_reference(self, s):
        """The readable pure-Python step (and the path without numba)."""
        x = self._screen_and_gap(s)
        if x is None:
            return None
        th, dvl, tau, bridged = x
        ws = self._ws
        bg, ba = ws[S.BG:S.BG + 3].tolist(), ws[S.BA:S.BA + 3].tolist()
        dtheta = (th[0] - bg[0] * tau, th[1] - bg[1] * tau, th[2] - bg[2] * tau)
        dv = (dvl[0] - ba[0] * tau, dvl[1] - ba[1] * tau, dvl[2] - ba[2] * tau)
        C0 = self.C_b_e
        r0 = self.r_e
        # gravity: exact model at a reference point, first-order Taylor expansion around it
        # (second-order error < 1e-7 m/s^2 within the refresh distance)
        d = r0 - ws[S.GRAD_R:S.GRAD_R + 3] if ws[S.GRAD_OK] else None
        if d is None or float(d @ d) > ws[S.REFRESH2]:
            self._set_gravity_point(r0)
            g = ws[S.G_REF:S.G_REF + 3].copy()
        else:
            g = ws[S.G_REF:S.G_REF + 3] + self._grad @ d
        r1, v1, C1, dv_e = strapdown_step_with_force(r0, self.v_e, C0, dtheta, dv, tau, g)
        self.kf.propagate(C0, dv_e, self._grad, tau)
        if bridged:
            scr = self.imu_screen
            self.kf.add_body_noise(C0, scr.var_dtheta_b, scr.var_dv_b)    # what the sample could have hidden
        if self.smoother is not None:
            self.smoother.after_step(self)
        ws[S.R:S.R + 3], ws[S.V:S.V + 3], ws[S.C:S.C + 9] = r1, v1, C1.ravel()
        ws[S.LAST_DTH:S.LAST_DTH + 3] = dtheta
        ws[S.LAST_TAU] = tau
        ws[S.CLK] += ws[S.DRIFT] * (s.t_gps - ws[S.T])
        ws[S.T] = s.t_gps
        self._hist.push_current()
        # ZUPT/ZARU on the ground only: a hovering multirotor with a quiet IMU looks still too
        if self._still is not None and self._still.add(s.dtheta_b.tolist(), s.dv_b.tolist(), s.dt_s) \
                and self.ground_mode:
            self._zero_motion_update()
        self._after_step(tau)
        return None

    def _after_step(self, tau: float) -> None:
        """The non-holonomic constraint's clock and the GNSS messages the IMU has now passed."""
        if self.cfg.nhc_enabled:
            self._nhc_countdown_s -= tau
            if self._nhc_countdown_s <= 0.0:
                self._nhc_countdown_s += 1.0 / self.cfg.nhc_rate_hz
                self._nhc_update()
        if self._pending:
            self._release_pending()

    # ------------------------------------------------------------------ history
    def _push_history(self) -> None:
        self._hist.push_current()

    ACCELERATION_HALF_WINDOW_S = 0.05

    def ins_at(self, t_gps: float):
        """INS state linearly interpolated to ``t_gps`` (an IMU tag) between the bracketing IMU
        samples, with the mean acceleration over +-ACCELERATION_HALF_WINDOW_S (for the dt_imu
        columns: a window, not one interval, so one sample's noise does not enter the Jacobian)."""
        from .measurements import InsPoint
        x = self._hist.interpolate(t_gps)
        if x is None:
            return None
        r, v, C = x
        first, last = self._hist.first_last_t()
        h = self.ACCELERATION_HALF_WINDOW_S
        t0, t1 = max(t_gps - h, first), min(t_gps + h, last)
        a = (self._hist.interpolate(t1)[1] - self._hist.interpolate(t0)[1]) / (t1 - t0) if t1 - t0 > 1e-3 \
            else np.zeros(3)
        clk = self.clock_bias_m - self.clock_drift_mps * (self.t_gps - t_gps)
        return InsPoint(t_gps, r, v, C, self.omega_ib_b, clk, self.clock_drift_mps, a,
                        dict(self.block_states) if self.block_states else None)

    @property
    def omega_ib_b(self) -> np.ndarray:
        """Body angular rate over the last IMU interval (bias-corrected), rad/s."""
        return self._ws[S.LAST_DTH:S.LAST_DTH + 3] / self._ws[S.LAST_TAU]
