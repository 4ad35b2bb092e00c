"""The engine's nominal state packed in one float64 array, and its INS history as a ring of rows.

At IMU rate the engine's state passes into one compiled call (:mod:`.imu_fused`); numba unboxes
every array argument (~0.13 us each), so the state is a few arrays, not a dozen: ``ws`` holds
time, position, velocity, attitude, biases, clock, the gravity expansion point and the bookkeeping
scalars at the fixed offsets below; the history is ``hist`` (rows t, r_e, v_e, C_b_e row-major),
whose live rows ``start .. start+count-1`` are contiguous and in time order (when the end is
reached they are moved to the front), so a look-up is a bisection of one column.
"""
from __future__ import annotations

import numpy as np

# offsets in ws
T = 0                 # GPS time of the last IMU sample (its tag), s
R = 1                 # r_e (3), m
V = 4                 # v_e (3), m/s
C = 7                 # C_b_e (9, row-major)
BA = 16               # accelerometer bias (3), m/s^2
BG = 19               # gyro bias (3), rad/s
CLK = 22              # receiver clock bias, m
DRIFT = 23            # receiver clock drift, m/s
GRAD_OK = 24          # 1 once a gravity expansion point is set
GRAD_R = 25           # expansion point (3), m
G_REF = 28            # gravity there (3), m/s^2
GRAD = 31             # gravity gradient there (9, row-major), 1/s^2
REFRESH2 = 40         # squared distance from the point that triggers a new one, m^2
LAST_DTH = 41         # bias-corrected angle increment of the last interval (3), rad
LAST_TAU = 44         # its length, s
KTAU = 45             # the interval the filter's Phi and Qd are set for (-1: none)
TURN_CO = 46          # cos, sin of the earth's turn over KTAU
TURN_SI = 47
HIST_S = 48           # history length, s
H_START = 49          # first live history row
H_COUNT = 50          # live history rows
I_ATT, I_POS, I_VEL, I_BA, I_BG = 51, 52, 53, 54, 55   # block starts in the filter's state
OV_TAU = 56           # an interval integrated instead of the sample's (a gap, a bridged sample)
OV_TH = 57            # (3)
OV_DV = 60            # (3)
SCR_ON = 63           # the IMU screen's quick path (companion.nav.imu_screen), see imu_fused
SCR_N, SCR_K, SCR_PREV_OK, SCR_HAS_GOOD = 64, 65, 66, 67
SCR_CW, SCR_CF, SCR_JW, SCR_JF = 68, 69, 70, 71
SCR_PREV = 72         # (6)
SCR_GOOD = 78         # (6)
ST_ON = 84            # stillness ring (companion.nav.stillness) on
ST_CAP, ST_MAXLEN, ST_NVALID, ST_HEAD = 85, 86, 87, 88
ST_SINCE_CHECK, ST_SINCE_UPDATE, ST_WINDOW = 89, 90, 91
SCR_WIN = 96          # the screen's window, 6 x SCR_N
HEADER = SCR_WIN

HIST_COLS = 16


def new_ws(screen_window: int, still_capacity: int) -> np.ndarray:
    """A zeroed state array with room for the screen's window and the stillness ring (7 per row)."""
    ws = np.zeros(HEADER + 6 * screen_window + 7 * still_capacity)
    ws[SCR_N] = screen_window
    ws[ST_CAP] = still_capacity
    ws[KTAU] = -1.0
    return ws


def still_offset(ws: np.ndarray) -> int:
    return HEADER + 6 * int(ws[SCR_N])


class InsHistory:
    """The INS state at every IMU sample over the last ``history_s`` (ring rows in ``hist``)."""

    def __init__(self, ws: np.ndarray, capacity: int = 4096):
        self.ws = ws
        self.hist = np.zeros((capacity, HIST_COLS))
        # the compiled :meth:`correct` and :meth:`interpolate` (companion.nav.imu_fused's
        # history_correct, history_interpolate), set by the engine with its compiled path; None: numpy
        self.correct_kernel = None
        self.interpolate_kernel = None

    def clear(self) -> None:
        self.ws[H_START] = 0.0
        self.ws[H_COUNT] = 0.0

    def grow(self) -> None:
        """Twice the rows (the kernel asks when the live rows fill the ring)."""
        s, n = self.span()
        new = np.zeros((2 * len(self.hist), HIST_COLS))
        new[:n] = self.hist[s:s + n]
        self.hist = new
        self.ws[H_START] = 0.0

    def span(self) -> tuple[int, int]:
        return int(self.ws[H_START]), int(self.ws[H_COUNT])

    def push_current(self) -> None:
        """Append the state in ws (the pure-Python path; the kernel does the same in place)."""
        s, n = self.span()
        if n + 1 > len(self.hist):
            self.grow()
            s, n = self.span()
        if s + n >= len(self.hist):
            self.hist[:n] = self.hist[s:s + n]
            s = 0
        self.hist[s + n] = self.ws[T:C + 9]
        n += 1
        h = self.hist
        while h[s + n - 1, 0] - h[s, 0] > self.ws[HIST_S]:
            s += 1
            n -= 1
        self.ws[H_START], self.ws[H_COUNT] = s, n

    def rows(self) -> np.ndarray:
        s, n = self.span()
        return self.hist[s:s + n]

    def times(self) -> np.ndarray:
        return self.rows()[:, 0]

    def correct(self, dr_e, dv_e, R_e) -> None:
        """Add dr_e to every position, dv_e to every velocity, rotate every attitude by R_e (None:
        leave it), e.g. a closed-loop correction applied to the history too."""
        if self.correct_kernel is not None and dr_e is not None and dv_e is not None and R_e is not None:
            s, n = self.span()
            self.correct_kernel(self.hist, s, n, np.asarray(dr_e, float), np.asarray(dv_e, float),
                                np.asarray(R_e, float))
            return
        rows = self.rows()
        if dr_e is not None:
            rows[:, R:R + 3] += dr_e
        if dv_e is not None:
            rows[:, V:V + 3] += dv_e
        if R_e is not None:
            # R_e C row by row as three products summed in order, as the compiled version does
            # (np.matmul may sum in another order or fuse: a replay would then differ by rounding)
            Cs = rows[:, C:C + 9].reshape(-1, 3, 3)
            Rk = np.asarray(R_e, float)[None, :, :, None]          # (1, 3, 3, 1): R[i, k]
            rows[:, C:C + 9] = (Rk[:, :, 0] * Cs[:, 0:1, :] + Rk[:, :, 1] * Cs[:, 1:2, :]
                                + Rk[:, :, 2] * Cs[:, 2:3, :]).reshape(-1, 9)

    def set_last(self) -> None:
        """The newest row := the state in ws."""
        s, n = self.span()
        if n:
            self.hist[s + n - 1] = self.ws[T:C + 9]

    def interpolate(self, t_gps: float):
        """(r, v, C) linearly interpolated to t_gps (attitude: the nearer sample's), or None outside."""
        if self.interpolate_kernel is not None:
            s, n = self.span()
            out = np.empty(15)
            if not self.interpolate_kernel(self.hist, s, n, float(t_gps), out):
                return None
            return out[0:3], out[3:6], out[6:15].reshape(3, 3)
        rows = self.rows()
        if not len(rows) or t_gps > rows[-1, 0] or t_gps < rows[0, 0]:
            return None
        ts = rows[:, 0]
        k = int(np.searchsorted(ts, t_gps, side="left"))
        row1 = rows[k]
        t1 = float(row1[0])
        if k == 0 or t1 == t_gps:
            return row1[R:R + 3].copy(), row1[V:V + 3].copy(), row1[C:C + 9].reshape(3, 3).copy()
        row0 = rows[k - 1]
        t0 = float(row0[0])
        a = (t_gps - t0) / (t1 - t0)
        r = row0[R:R + 3] * (1.0 - a) + row1[R:R + 3] * a
        v = row0[V:V + 3] * (1.0 - a) + row1[V:V + 3] * a
        Cm = (row0 if a < 0.5 else row1)[C:C + 9].reshape(3, 3).copy()
        return r, v, Cm

    def first_last_t(self) -> tuple[float, float]:
        s, n = self.span()
        return float(self.hist[s, 0]), float(self.hist[s + n - 1, 0])
