"""Post-flight smoothing: a Rauch-Tung-Striebel backward pass over the forward filter's stored states.

The forward filter (:mod:`.engine`, :mod:`.filter`) is closed-loop: every update's correction dx is
folded into the nominal state and the error state restarts at zero.  The recorder keeps, at a
*checkpoint* k (every update, and every ``checkpoint_interval_s`` without one, e.g. through a GNSS
outage):

* the prior covariance P-_k (before the update) and the summed correction dx_k of the updates of
  that IMU step,
* the link to the previous checkpoint: A_{k-1} = P+_{k-1} Phi^T (P-_k)^-1, with Phi the product
  of the per-IMU-step transitions since k-1 (accumulated at IMU rate from
  :meth:`.filter.ErrorStateKalmanFilter.dense_transition`), and
  D_{k-1} = P+_{k-1} - A_{k-1} P-_k A_{k-1}^T,

so that the backward pass is, with delta_k the smoothed error of the corrected nominal at k
(truth = nominal + delta):

    delta_N = 0,                 delta_k = A_k (dx_{k+1} + delta_{k+1})
    Ps_N = P+_N,                 Ps_k = D_k + A_k Ps_{k+1} A_k^T

(the textbook x^s_k = x+_k + A_k (x^s_{k+1} - x-_{k+1}) in closed-loop form: the prior at k+1 is
the nominal, the posterior is the nominal plus dx_{k+1}).  Only P+_N and the pairs (A_k, D_k) are
kept, not the three covariances per checkpoint.

Layout changes (float ambiguities added and removed at run time) are handled exactly by giving the
transition a rectangular form: a block that appears is a new random variable independent of the
past (zero rows of Phi, its initial variance in P-), one that disappears is marginalised (its rows
dropped).  Everything still to be linked (the accumulated Phi, the pending prior and correction) is
re-indexed by block name at each change.  A re-initialisation or a heading reset (a jump of the
nominal state the error model does not describe) closes the segment; segments are smoothed
independently.

Forward solutions (:meth:`.engine.NavEngine.solution`) are noted with the checkpoint they follow;
the smoothed one is the forward one plus the smoothed error interpolated linearly in time between
that checkpoint (delta_k) and the next (delta_{k+1} + dx_{k+1}: the forward nominal just before an
update still lacks its correction), and the smoothed covariance interpolated the same way.

Cost: nothing when the engine has no recorder (``engine.smoother is None``); with one, a product
of the dense Phi with the accumulated transition per IMU step and one Cholesky solve per checkpoint.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from scipy.linalg import LinAlgError, cho_factor, cho_solve

from ..messages import NavSolution
from .earth import C_n_e, ecef_to_geodetic, rotation_from_rotvec


def _names(layout) -> tuple[tuple[str, int], ...]:
    return tuple((b.name, b.size) for b in layout.blocks)


def _index_map(old, new) -> tuple[np.ndarray, np.ndarray]:
    """Indices (in the new layout, in the old one) of the states both layouts share, by block name."""
    start_old, i = {}, 0
    for name, size in old:
        start_old[name] = (i, size)
        i += size
    to_new, from_old, j = [], [], 0
    for name, size in new:
        o = start_old.get(name)
        if o is not None and o[1] == size:
            to_new.extend(range(j, j + size))
            from_old.extend(range(o[0], o[0] + size))
        j += size
    return np.array(to_new, dtype=int), np.array(from_old, dtype=int)


def _solve_spd(P: np.ndarray, B: np.ndarray) -> np.ndarray:
    """P^-1 B for a covariance P, on the diagonally scaled matrix (the states span rad to km);
    a least-squares solve if P is not numerically positive definite."""
    d = np.sqrt(np.maximum(np.diag(P), 1e-300))
    Ps = P / np.outer(d, d)
    Bs = B / d[:, None]
    try:
        X = cho_solve(cho_factor(Ps, lower=True, check_finite=False), Bs, check_finite=False)
    except LinAlgError:
        X = np.linalg.lstsq(Ps, Bs, rcond=None)[0]
    return X / d[:, None]


@dataclasses.dataclass
class _Checkpoint:
    t_gps: float
    layout: tuple
    dx: np.ndarray                 # correction fed back at this checkpoint (0 without an update)
    P_plus: np.ndarray | None      # kept until the link to the next checkpoint is made
    A: np.ndarray | None = None    # gain to the next checkpoint
    D: np.ndarray | None = None    # P+ - A P-_next A^T


@dataclasses.dataclass
class _Pending:
    t_gps: float
    layout: tuple
    P_minus: np.ndarray
    dx: np.ndarray


class SmootherRecorder:
    """Records the forward pass of a :class:`.engine.NavEngine` for :meth:`smoothed_solutions`.

    Use: ``rec = SmootherRecorder(); rec.attach(engine)`` before the engine is initialised (or
    at any time: recording starts then), run the forward pass, call ``rec.smoothed_solutions()``.
    """

    def __init__(self, checkpoint_interval_s: float = 1.0):
        self.checkpoint_interval_s = float(checkpoint_interval_s)
        self._segments: list[list[_Checkpoint]] = []
        self._solutions: list[tuple[NavSolution, int, int]] = []   # (forward solution, segment, checkpoint)
        self._engine = None
        self._kf = None
        self._pending: _Pending | None = None
        self._T: np.ndarray | None = None      # transition: state at the last checkpoint -> now
        self._layout = None
        self._nav_idx = None

    @classmethod
    def attached_to(cls, engine, checkpoint_interval_s: float = 1.0) -> "SmootherRecorder":
        rec = cls(checkpoint_interval_s)
        rec.attach(engine)
        return rec

    # ------------------------------------------------------------------ forward hooks (engine)
    def attach(self, engine) -> None:
        engine.smoother = self
        if engine.initialized:
            self.start(engine)

    def start(self, engine) -> None:
        """A new segment at the engine's current state (initialisation, or a jump of the nominal)."""
        self._close()
        self._engine = engine
        kf = self._kf = engine.kf
        kf.on_update = self._on_update
        L = kf.layout
        self._nav_idx = (L.att, L.pos, L.vel)
        self._layout = _names(L)
        self._segments.append([_Checkpoint(engine.t_gps, self._layout, np.zeros(L.n), kf.P.copy())])
        self._T = np.eye(L.n)

    def before_step(self, engine) -> None:
        """Before an IMU step's propagation: the posterior of the last step's updates is final."""
        if self._T is None:
            return
        if self._pending is not None:
            p = self._pending
            self._pending = None
            self._link(p.t_gps, p.P_minus, self._kf.P.copy(), p.dx)
        elif engine.t_gps - self._segments[-1][-1].t_gps >= self.checkpoint_interval_s:
            P = self._kf.P.copy()       # no update: prior and posterior are the same
            self._link(engine.t_gps, P, P, np.zeros(P.shape[0]))

    def after_step(self, engine) -> None:
        """After an IMU step's propagation: accumulate its transition (identity beyond the dense group)."""
        if self._T is None:
            return
        phi = self._kf.dense_transition()
        nd = phi.shape[0]
        self._T[:nd] = phi @ self._T[:nd]

    def layout_changed(self, engine) -> None:
        """A block was added or removed: re-index what is still to be linked, by block name."""
        if self._T is None:
            return
        new = _names(self._kf.layout)
        to_new, from_old = _index_map(self._layout, new)
        n = self._kf.layout.n
        T = np.zeros((n, self._T.shape[1]))
        T[to_new] = self._T[from_old]          # a new block: independent of the past (zero rows)
        self._T = T
        p = self._pending
        if p is not None:
            P_minus = self._kf.P.copy()         # the new blocks' initial covariance ...
            P_minus[np.ix_(to_new, to_new)] = p.P_minus[np.ix_(from_old, from_old)]   # ... the rest as before
            dx = np.zeros(n)
            dx[to_new] = p.dx[from_old]
            self._pending = _Pending(p.t_gps, new, P_minus, dx)
        self._layout = new

    def _on_update(self, P_prior: np.ndarray, dx: np.ndarray) -> None:
        """Called by the filter at each update: the first of an IMU step gives the prior."""
        if self._T is None:
            return
        if self._pending is None:
            self._pending = _Pending(self._engine.t_gps, self._layout, P_prior.copy(), dx.copy())
        else:
            self._pending.dx = self._pending.dx + dx

    def note_solution(self, sol: NavSolution) -> None:
        """A forward solution at the engine's current state (after the updates of its step)."""
        if self._T is None:
            return
        seg = self._segments[-1]
        k = len(seg) - 1 + (1 if self._pending is not None else 0)
        self._solutions.append((sol, len(self._segments) - 1, k))

    def _link(self, t_gps: float, P_minus: np.ndarray, P_plus: np.ndarray, dx: np.ndarray) -> None:
        seg = self._segments[-1]
        prev = seg[-1]
        C = prev.P_plus @ self._T.T                        # P+_{k-1} Phi^T
        A = _solve_spd(P_minus, C.T).T                     # C (P-_k)^-1
        prev.A = A
        prev.D = prev.P_plus - A @ C.T                     # P+ - A P- A^T (A P- = C)
        prev.P_plus = None
        seg.append(_Checkpoint(t_gps, self._layout, dx, P_plus))
        self._T = np.eye(P_plus.shape[0])

    def _close(self) -> None:
        if self._pending is not None and self._kf is not None:
            p = self._pending
            self._pending = None
            self._link(p.t_gps, p.P_minus, self._kf.P.copy(), p.dx)
        if self._kf is not None and self._kf.on_update == self._on_update:
            self._kf.on_update = None
        self._T = None

    # ------------------------------------------------------------------ backward pass
    @property
    def n_checkpoints(self) -> int:
        return sum(len(s) for s in self._segments)

    def finish(self) -> None:
        """End of the forward pass (implied by :meth:`smoothed_solutions`)."""
        self._close()

    def _backward(self, seg: list[_Checkpoint]):
        """Smoothed nav errors (attitude, position, velocity; 9) and their covariance per checkpoint,
        and the correction of the forward nominal just before each checkpoint (delta + dx)."""
        att, pos, vel = self._nav_idx
        nav = np.r_[att, pos, vel]
        N = len(seg)
        delta_nav = np.zeros((N, 9))
        before_nav = np.zeros((N, 9))
        Ps_nav = np.zeros((N, 9, 9))
        last = seg[-1]
        delta = np.zeros(len(last.dx))
        Ps = last.P_plus if last.P_plus is not None else np.zeros((len(last.dx),) * 2)
        for k in range(N - 1, -1, -1):
            cp = seg[k]
            if k < N - 1:
                nxt = seg[k + 1]
                after_next = nxt.dx + delta
                delta = cp.A @ after_next
                Ps = cp.D + cp.A @ Ps @ cp.A.T
            delta_nav[k] = delta[nav]
            before_nav[k] = (delta + cp.dx)[nav]
            Ps_nav[k] = Ps[np.ix_(nav, nav)]
        return np.array([c.t_gps for c in seg]), delta_nav, before_nav, Ps_nav

    def smoothed_solutions(self) -> list[NavSolution]:
        """Every noted forward solution, corrected by the smoothed error (same order)."""
        self.finish()
        back = [self._backward(seg) for seg in self._segments]
        out = []
        for sol, si, k in self._solutions:
            t, delta, before, Ps = back[si]
            N = len(t)
            if k >= N - 1 or sol.t_gps <= t[k]:
                k = min(k, N - 1)
                d, P = delta[k], Ps[k]
            else:
                f = min(max((sol.t_gps - t[k]) / (t[k + 1] - t[k]), 0.0), 1.0)
                d = (1.0 - f) * delta[k] + f * before[k + 1]
                P = (1.0 - f) * Ps[k] + f * Ps[k + 1]
            out.append(_corrected(sol, d, P))
        return out


    def smoothed(self, forward: list[NavSolution]) -> list[NavSolution]:
        """The smoothed counterpart of each of ``forward`` (solutions of the recorded engine, e.g.
        a pipeline's output); one the engine did not produce while recording is returned as it is."""
        by_id = {id(sol): sm for (sol, _, _), sm in zip(self._solutions, self.smoothed_solutions())}
        return [by_id.get(id(s), s) for s in forward]


def _corrected(sol: NavSolution, d: np.ndarray, P: np.ndarray) -> NavSolution:
    """A forward solution moved by the smoothed error d (attitude, position, velocity; truth =
    estimate + error) with the smoothed covariance P (9 x 9, ECEF) as its sigmas."""
    r = sol.r_e + d[3:6]
    lat, lon, _ = ecef_to_geodetic(r)
    Cen = C_n_e(lat, lon).T
    sig = lambda B: np.sqrt(np.maximum(np.diag(Cen @ B @ Cen.T), 0.0))   # noqa: E731
    return dataclasses.replace(
        sol, r_e=r, v_e=sol.v_e + d[6:9], C_b_e=rotation_from_rotvec(d[0:3]) @ sol.C_b_e,
        sigma_r_n_m=sig(P[3:6, 3:6]), sigma_v_n_mps=sig(P[6:9, 6:9]),
        sigma_att_rad=np.sqrt(np.maximum(np.diag(P[0:3, 0:3]), 0.0)),
        extras={**sol.extras, "smoothed": True, "smoothed_cov_nav_e": P})

