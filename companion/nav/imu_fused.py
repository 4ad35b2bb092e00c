"""One compiled call per IMU sample (or per run of samples): validity, the IMU screen's quick
test, bias removal, gravity (first-order Taylor about a reference point), strapdown, Phi and the
covariance propagation, the clock, the history row and the stillness ring.

The same equations as the engine's pure-Python path (:meth:`.engine.NavEngine._imu_reference`),
through the same compiled pieces (:func:`.imu_kernel.strapdown`, :func:`.imu_kernel.propagate`).
Whatever is rare stays in Python: the kernel returns a flag *before changing anything* when it
needs it -- a time gap, a sample the screen's quick test does not pass (Python runs the whole
screen and bridges), a new gravity expansion point, a new interval length (Phi and Qd constants),
a full history ring -- and, after a step, when the stillness window is due for its test.  The
state is :mod:`.nav_state`'s ``ws`` and ``hist`` plus the filter's matrices.

:func:`imu_run` loops the step over arrays of samples and stops at the first flag or at a time
limit (the next GNSS message): the same step, so the same numbers as one call per sample.
"""
from __future__ import annotations

import math

import numpy as np

from . import imu_kernel
from . import nav_state as S
from .earth import OMEGA_IE_RADPS

OK = 0
NOT_AFTER = 1        # tag not after the last sample: dropped
INVALID = 2          # interval out of range or non-finite increments: dropped
SLOW = 3             # time gap, or the screen's quick test failed: the Python path
GRAVITY = 4          # a new gravity expansion point is due
INTERVAL = 5         # a new interval length: Phi and Qd constants
HIST_FULL = 6        # the history ring needs more rows
STILL_DUE = 16       # (bit, after a completed step) the stillness window is due for its test

#: the filter buffer's scratch (unpack_filter_buffer): the state before and after a step
FILTER_BUFFER_SCRATCH = 30

# the compiled callees (imu_kernel.strapdown / propagate and the functions below), module globals
# that numba resolves when it compiles imu_step / imu_run (set by ensure_compiled)
_strapdown = _propagate = _screen_quick = _screen_commit = _unpack = _imu_step = None
_compiled = None


def new_filter_buffer(nd: int, n: int) -> np.ndarray:
    """A zeroed buffer in the layout :func:`unpack_filter_buffer` reads, ``nd`` in its first element."""
    buf = np.zeros(1 + 3 * nd * nd + (n - nd) + nd * n + FILTER_BUFFER_SCRATCH)
    buf[0] = nd
    return buf


def unpack_filter_buffer(kbuf, n):
    """Views of the filter's buffer (companion.nav.filter.ErrorStateKalmanFilter._kernel_buf) for a
    state of ``n``: Phi, Qd (nd x nd), the identity tail's noise (n - nd), work (nd x n), work_cc
    (nd x nd), the step's scratch (FILTER_BUFFER_SCRATCH); nd is its first element."""
    nd = int(kbuf[0])
    o = 1
    phi = kbuf[o:o + nd * nd].reshape((nd, nd))
    o += nd * nd
    Qd = kbuf[o:o + nd * nd].reshape((nd, nd))
    o += nd * nd
    tail_q = kbuf[o:o + n - nd]
    o += n - nd
    work = kbuf[o:o + nd * n].reshape((nd, n))
    o += nd * n
    work_cc = kbuf[o:o + nd * nd].reshape((nd, nd))
    o += nd * nd
    return phi, Qd, tail_q, work, work_cc, kbuf[o:o + FILTER_BUFFER_SCRATCH]


def imu_step(ws, hist, P, kbuf, t, tau_s, th, dv, override):
    """One sample ending at ``t`` (increments ``th``, ``dv`` over ``tau_s``).  ``override``: the
    screen and gap tests were done in Python, which put the interval to integrate in ws[OV_*].
    ``kbuf``: the filter's Phi, Qd and work buffers (:func:`unpack_filter_buffer`)."""
    t_prev = ws[S.T]
    a0, a1, a2 = th[0], th[1], th[2]
    b0, b1, b2 = dv[0], dv[1], dv[2]
    scr_pass = False
    if override:
        tau = ws[S.OV_TAU]
        a0, a1, a2 = ws[S.OV_TH], ws[S.OV_TH + 1], ws[S.OV_TH + 2]
        b0, b1, b2 = ws[S.OV_DV], ws[S.OV_DV + 1], ws[S.OV_DV + 2]
    else:
        if not (t > t_prev):
            return NOT_AFTER
        tau = tau_s
        if not (0.0 < tau < 0.1) or not math.isfinite(a0 + a1 + a2 + b0 + b1 + b2):
            return INVALID
        gap = t - t_prev - tau
        if abs(gap) > 0.5 * tau:
            return SLOW
        if ws[S.SCR_ON] != 0.0:
            if not _screen_quick(ws, a0 / tau, a1 / tau, a2 / tau, b0 / tau, b1 / tau, b2 / tau):
                return SLOW
            scr_pass = True
    if tau != ws[S.KTAU]:
        return INTERVAL
    if ws[S.GRAD_OK] == 0.0:
        return GRAVITY
    d0 = ws[S.R] - ws[S.GRAD_R]
    d1 = ws[S.R + 1] - ws[S.GRAD_R + 1]
    d2 = ws[S.R + 2] - ws[S.GRAD_R + 2]
    if d0 * d0 + d1 * d1 + d2 * d2 > ws[S.REFRESH2]:
        return GRAVITY
    h_start, h_count = int(ws[S.H_START]), int(ws[S.H_COUNT])
    if h_count + 1 > hist.shape[0]:
        return HIST_FULL
    # ---- from here on the step is committed
    if scr_pass:
        _screen_commit(ws, a0 / tau, a1 / tau, a2 / tau, b0 / tau, b1 / tau, b2 / tau)
    G = S.GRAD
    gx = ws[S.G_REF] + (ws[G] * d0 + ws[G + 1] * d1 + ws[G + 2] * d2)
    gy = ws[S.G_REF + 1] + (ws[G + 3] * d0 + ws[G + 4] * d1 + ws[G + 5] * d2)
    gz = ws[S.G_REF + 2] + (ws[G + 6] * d0 + ws[G + 7] * d1 + ws[G + 8] * d2)
    ax = a0 - ws[S.BG] * tau
    ay = a1 - ws[S.BG + 1] * tau
    az = a2 - ws[S.BG + 2] * tau
    bx = b0 - ws[S.BA] * tau
    by = b1 - ws[S.BA + 1] * tau
    bz = b2 - ws[S.BA + 2] * tau
    phi, Qd, tail_q, work, work_cc, scratch = _unpack(kbuf, P.shape[0])
    # the state before and after the step in the buffer's scratch (views: no allocation per sample)
    r0, v0, C0 = scratch[0:3], scratch[3:6], scratch[6:15].reshape((3, 3))
    r1, v1, C1 = scratch[15:18], scratch[18:21], scratch[21:30].reshape((3, 3))
    for i in range(3):
        r0[i] = ws[S.R + i]
        v0[i] = ws[S.V + i]
        for j in range(3):
            C0[i, j] = ws[S.C + 3 * i + j]
    fx, fy, fz = _strapdown(r0, v0, C0, ax, ay, az, bx, by, bz, tau, gx, gy, gz, ws[S.TURN_CO], ws[S.TURN_SI],
                            OMEGA_IE_RADPS, r1, v1, C1)
    i_pos, i_vel = int(ws[S.I_POS]), int(ws[S.I_VEL])
    for i in range(3):
        for j in range(3):
            phi[i_vel + i, i_pos + j] = ws[G + 3 * i + j] * tau
    _propagate(phi, P, Qd, tail_q, C0, fx, fy, fz, tau, int(ws[S.I_ATT]), i_vel, int(ws[S.I_BA]),
               int(ws[S.I_BG]), work, work_cc)
    for i in range(3):
        ws[S.R + i] = r1[i]
        ws[S.V + i] = v1[i]
        for j in range(3):
            ws[S.C + 3 * i + j] = C1[i, j]
    ws[S.LAST_DTH] = ax
    ws[S.LAST_DTH + 1] = ay
    ws[S.LAST_DTH + 2] = az
    ws[S.LAST_TAU] = tau
    ws[S.CLK] += ws[S.DRIFT] * (t - t_prev)
    ws[S.T] = t
    # history row
    if h_start + h_count >= hist.shape[0]:
        for k in range(h_count):
            for c in range(S.HIST_COLS):
                hist[k, c] = hist[h_start + k, c]
        h_start = 0
    row = h_start + h_count
    for c in range(S.HIST_COLS):
        hist[row, c] = ws[c]
    h_count += 1
    hs = ws[S.HIST_S]
    while hist[h_start + h_count - 1, 0] - hist[h_start, 0] > hs:
        h_start += 1
        h_count -= 1
    ws[S.H_START] = h_start
    ws[S.H_COUNT] = h_count
    # stillness ring: the raw increments and the sample's own interval
    if ws[S.ST_ON] != 0.0:
        o = S.HEADER + 6 * int(ws[S.SCR_N])
        cap = int(ws[S.ST_CAP])
        head = int(ws[S.ST_HEAD])
        q = o + 7 * head
        ws[q] = th[0]
        ws[q + 1] = th[1]
        ws[q + 2] = th[2]
        ws[q + 3] = dv[0]
        ws[q + 4] = dv[1]
        ws[q + 5] = dv[2]
        ws[q + 6] = tau_s
        ws[S.ST_HEAD] = (head + 1) % cap
        ws[S.ST_NVALID] = min(ws[S.ST_NVALID] + 1.0, ws[S.ST_MAXLEN])
        ws[S.ST_SINCE_CHECK] += tau_s
        ws[S.ST_SINCE_UPDATE] += tau_s
        if not (ws[S.ST_SINCE_CHECK] < 0.5 * ws[S.ST_WINDOW]):
            return STILL_DUE
    return OK


def screen_quick(ws, w0, w1, w2, f0, f1, f2):
    """The screen's common case (companion.nav.imu_screen.ImuScreen.check): no axis clipped, and
    either the window not full yet or every axis within the jump limits of the previous sample."""
    cw, cf = ws[S.SCR_CW], ws[S.SCR_CF]
    if abs(w0) >= cw or abs(w1) >= cw or abs(w2) >= cw or abs(f0) >= cf or abs(f1) >= cf or abs(f2) >= cf:
        return False
    if ws[S.SCR_K] < ws[S.SCR_N]:
        return True
    if ws[S.SCR_PREV_OK] == 0.0:
        return False
    jw, jf, p = ws[S.SCR_JW], ws[S.SCR_JF], S.SCR_PREV
    return (abs(w0 - ws[p]) <= jw and abs(w1 - ws[p + 1]) <= jw and abs(w2 - ws[p + 2]) <= jw
            and abs(f0 - ws[p + 3]) <= jf and abs(f1 - ws[p + 4]) <= jf and abs(f2 - ws[p + 5]) <= jf)


def screen_commit(ws, w0, w1, w2, f0, f1, f2):
    n = int(ws[S.SCR_N])
    k = int(ws[S.SCR_K])
    j = k % n
    o = S.SCR_WIN
    ws[o + j] = w0
    ws[o + n + j] = w1
    ws[o + 2 * n + j] = w2
    ws[o + 3 * n + j] = f0
    ws[o + 4 * n + j] = f1
    ws[o + 5 * n + j] = f2
    ws[S.SCR_K] = k + 1
    ws[S.SCR_PREV_OK] = 1.0
    ws[S.SCR_HAS_GOOD] = 1.0
    ws[S.SCR_PREV], ws[S.SCR_PREV + 1], ws[S.SCR_PREV + 2] = w0, w1, w2
    ws[S.SCR_PREV + 3], ws[S.SCR_PREV + 4], ws[S.SCR_PREV + 5] = f0, f1, f2
    for i in range(6):
        ws[S.SCR_GOOD + i] = ws[S.SCR_PREV + i]


def imu_run(ws, hist, P, kbuf, t, tau, th, dv, i0, t_stop, out):
    """:func:`imu_step` over samples i0.. of the arrays (t, tau: (N,); th, dv: (N, 3)) while
    t[i] <= t_stop; stops after a STILL_DUE step or before a sample with another flag.  out[0]:
    the index of the next sample to process, out[1]: the flag that stopped the run (OK: the
    end of the arrays or t_stop reached)."""
    n = t.shape[0]
    i = i0
    out[1] = OK
    while i < n and t[i] <= t_stop:
        f = _imu_step(ws, hist, P, kbuf, t[i], tau[i], th[i], dv[i], False)
        if f == OK:
            i += 1
            continue
        if f == STILL_DUE:
            i += 1
        out[1] = f
        break
    out[0] = i


def still_window_std(ws, m, out):
    """The stillness test's statistics on the ring's last ``m`` rows (raw dtheta 3, dv 3, tau),
    with the rates increment/tau: out[0] the largest population standard deviation of the three
    gyro axes', out[1] of the three accelerometer axes', out[2:5] the gyro axes' means -- numpy's
    mean and std to the bit (the same sums in the same order;
    companion.nav.stillness.StillnessDetector.decide).  numpy on the same window costs ~25 us a
    call, four times a second."""
    o = S.HEADER + 6 * int(ws[S.SCR_N])
    cap = int(ws[S.ST_CAP])
    first = int(ws[S.ST_HEAD]) - m
    if first < 0:
        first += cap
    mean = np.zeros(6)
    for k in range(m):
        q = o + 7 * ((first + k) % cap)
        tau = ws[q + 6]
        for c in range(6):
            mean[c] += ws[q + c] / tau
    for c in range(6):
        mean[c] /= m
    var = np.zeros(6)
    for k in range(m):
        q = o + 7 * ((first + k) % cap)
        tau = ws[q + 6]
        for c in range(6):
            d = ws[q + c] / tau - mean[c]
            var[c] += d * d
    out[0] = math.sqrt(max(var[0], var[1], var[2]) / m)
    out[1] = math.sqrt(max(var[3], var[4], var[5]) / m)
    for c in range(3):
        out[2 + c] = mean[c]


def history_correct(hist, start, count, dr_e, dv_e, R_e):
    """A closed-loop correction on the history's live rows (companion.nav.nav_state.InsHistory.correct):
    dr_e added to every position, dv_e to every velocity, every attitude turned to R_e C_b_e.
    numpy costs ~40 us on a 2-s history at 200 Hz, at every GNSS update."""
    for k in range(start, start + count):
        for i in range(3):
            hist[k, 1 + i] += dr_e[i]
            hist[k, 4 + i] += dv_e[i]
        for j in range(3):
            c0, c1, c2 = hist[k, 7 + j], hist[k, 10 + j], hist[k, 13 + j]
            for i in range(3):
                hist[k, 7 + 3 * i + j] = R_e[i, 0] * c0 + R_e[i, 1] * c1 + R_e[i, 2] * c2


def history_interpolate(hist, start, count, t, out):
    """companion.nav.nav_state.InsHistory.interpolate on the live rows, the same arithmetic: False
    outside them, else True with out[0:3] r_e, out[3:6] v_e (linear in time between the two
    bracketing rows), out[6:15] C_b_e row-major (the nearer row's).  numpy costs ~12 us a call,
    three a GNSS epoch."""
    if count == 0:
        return False
    if t > hist[start + count - 1, 0] or t < hist[start, 0]:
        return False
    lo, hi = start, start + count            # the first row at or after t (searchsorted, left)
    while lo < hi:
        mid = (lo + hi) // 2
        if hist[mid, 0] < t:
            lo = mid + 1
        else:
            hi = mid
    k = lo
    t1 = hist[k, 0]
    if k == start or t1 == t:
        for c in range(15):
            out[c] = hist[k, 1 + c]
        return True
    t0 = hist[k - 1, 0]
    a = (t - t0) / (t1 - t0)
    for c in range(6):
        out[c] = hist[k - 1, 1 + c] * (1.0 - a) + hist[k, 1 + c] * a
    near = k - 1 if a < 0.5 else k
    for c in range(6, 15):
        out[c] = hist[near, 1 + c]
    return True


class _Kernels:
    def __init__(self, imu_step, imu_run, still_window_std, history_correct, history_interpolate):
        self.imu_step, self.imu_run = imu_step, imu_run
        self.still_window_std, self.history_correct = still_window_std, history_correct
        self.history_interpolate = history_interpolate


def ensure_compiled():
    """The compiled imu_step / imu_run (compiled, or loaded from numba's disk cache, at their first
    call); None without the kernels (:func:`.imu_kernel.compiled`)."""
    global _strapdown, _propagate, _screen_quick, _screen_commit, _unpack, _imu_step, _compiled
    if _compiled is not None:
        return _compiled
    k = imu_kernel.compiled()
    if k is None:
        return None
    import numba
    jit = numba.njit(**imu_kernel.jit_options(numba))
    _strapdown, _propagate = k.strapdown, k.propagate
    _screen_quick, _screen_commit = jit(screen_quick), jit(screen_commit)
    _unpack = jit(unpack_filter_buffer)
    _imu_step = jit(imu_step)
    _compiled = _Kernels(_imu_step, jit(imu_run), jit(still_window_std), jit(history_correct),
                         jit(history_interpolate))
    return _compiled


def kernels():
    return _compiled
