"""Compiled IMU-rate kernels (numba): the strapdown step and the covariance propagation.

At 200-400 Hz the IMU path is a few hundred floating-point operations spread over dozens of
Python-level calls; their interpretation, not the arithmetic, is the cost.  These are the same
equations as the readable references, :func:`.strapdown.strapdown_step_with_force_reference` and
:meth:`.filter.ErrorStateKalmanFilter.propagate_reference`, written as loops that numba compiles
to machine code.  The public functions in those modules call a kernel when it is available and
fall back to the reference otherwise, with the same signatures and return types.

* **Strapdown**: the reference's float arithmetic term for term, in the same order (numba keeps
  IEEE semantics and evaluation order without ``fastmath``), so both give the same numbers.
* **Propagation**: ``P_cc <- Phi_c P_cc Phi_c^T + Q_c``, ``P_cx <- Phi_c P_cx``, ``P_xx += Q_x`` in
  place, the products by the same BLAS routine as the reference's numpy (``np.dot`` in numba
  calls dgemm), so that both give the same numbers when numpy and scipy use the same BLAS
  (their wheels do); tests/test_imu_kernel.py checks it and bounds the difference otherwise.
  What the kernel saves is the Python around them: ~15 numpy calls and element writes per step.
  (A loop that skips Phi's zeros -- ~60 of its 324 core entries are non-zero -- is ~1 us faster
  at n = 18, but sums in another order: results would move by rounding from the reference.)

Compilation happens on first use, not on import (``import numba`` alone costs ~0.5 s and ~64 MB,
the kernels loaded ~100 MB in all, which a process that never runs the filter should not pay),
and is cached on disk (``cache=True``: in ``__pycache__`` beside this file, or numba's user-wide
cache directory when that is not writable; ``NUMBA_CACHE_DIR`` overrides both), so a restart
loads machine code (~0.5-0.9 s) instead of compiling again (8-26 s on a loaded 2-core x86 machine,
more on a Raspberry Pi: :func:`warm_up` at install time).

``COMPANION_NUMBA=0`` in the environment disables the kernels (the pure-Python reference runs);
without numba installed (a dependency where it has wheels, x86_64 and aarch64; not on 32-bit
Raspberry Pi OS) that is the default.
"""
from __future__ import annotations

import logging
import math
import os

import numpy as np

log = logging.getLogger(__name__)

ENV_SWITCH = "COMPANION_NUMBA"

_kernels = None       # the compiled namespace once built
_tried = False        # compilation attempted (successfully or not)


def strapdown(r, v, C, ax, ay, az, bx, by, bz, tau, gx, gy, gz, co, si, omega, r_new, v_new, C_new):
    """One strapdown step (see :func:`.strapdown.strapdown_step_with_force_reference`) into
    ``r_new``, ``v_new``, ``C_new`` (allocated by the caller: an array returned by a kernel costs
    ~0.7 us to box, three times the allocation); returns (dvx, dvy, dvz).  ``co, si``: cos/sin of
    the earth's turn over ``tau``."""
    cx = bx + 0.5 * (ay * bz - az * by)
    cy = by + 0.5 * (az * bx - ax * bz)
    cz = bz + 0.5 * (ax * by - ay * bx)
    c00, c01, c02 = C[0, 0], C[0, 1], C[0, 2]
    c10, c11, c12 = C[1, 0], C[1, 1], C[1, 2]
    c20, c21, c22 = C[2, 0], C[2, 1], C[2, 2]
    dvx = c00 * cx + c01 * cy + c02 * cz
    dvy = c10 * cx + c11 * cy + c12 * cz
    dvz = c20 * cx + c21 * cy + c22 * cz
    vx, vy, vz = v[0], v[1], v[2]
    w2t = 2.0 * omega * tau
    nvx = vx + dvx + gx * tau + w2t * vy
    nvy = vy + dvy + gy * tau - w2t * vx
    nvz = vz + dvz + gz * tau
    h = 0.5 * tau
    r_new[0] = r[0] + (vx + nvx) * h
    r_new[1] = r[1] + (vy + nvy) * h
    r_new[2] = r[2] + (vz + nvz) * h
    v_new[0] = nvx
    v_new[1] = nvy
    v_new[2] = nvz
    a2 = ax * ax + ay * ay + az * az
    if a2 < 1e-12:
        sa = 1.0 - a2 / 6.0
        ca = 0.5 - a2 / 24.0
    else:
        a = math.sqrt(a2)
        sa = math.sin(a) / a
        ca = (1.0 - math.cos(a)) / a2
    R00 = 1.0 - ca * (ay * ay + az * az)
    R11 = 1.0 - ca * (ax * ax + az * az)
    R22 = 1.0 - ca * (ax * ax + ay * ay)
    R01 = -sa * az + ca * ax * ay
    R10 = sa * az + ca * ax * ay
    R02 = sa * ay + ca * ax * az
    R20 = -sa * ay + ca * ax * az
    R12 = -sa * ax + ca * ay * az
    R21 = sa * ax + ca * ay * az
    m00 = c00 * R00 + c01 * R10 + c02 * R20
    m01 = c00 * R01 + c01 * R11 + c02 * R21
    m02 = c00 * R02 + c01 * R12 + c02 * R22
    m10 = c10 * R00 + c11 * R10 + c12 * R20
    m11 = c10 * R01 + c11 * R11 + c12 * R21
    m12 = c10 * R02 + c11 * R12 + c12 * R22
    m20 = c20 * R00 + c21 * R10 + c22 * R20
    m21 = c20 * R01 + c21 * R11 + c22 * R21
    m22 = c20 * R02 + c21 * R12 + c22 * R22
    C_new[0, 0] = co * m00 + si * m10
    C_new[0, 1] = co * m01 + si * m11
    C_new[0, 2] = co * m02 + si * m12
    C_new[1, 0] = co * m10 - si * m00
    C_new[1, 1] = co * m11 - si * m01
    C_new[1, 2] = co * m12 - si * m02
    C_new[2, 0] = m20
    C_new[2, 1] = m21
    C_new[2, 2] = m22
    return dvx, dvy, dvz


def propagate(phi, P, Qd, tail_q, C, fx, fy, fz, tau, i_att, i_vel, i_ba, i_bg, work, work_cc):
    """Covariance propagation in place (see :meth:`.filter.ErrorStateKalmanFilter.propagate`).

    ``phi`` (nc x nc): the densely propagated group's transition, its attitude-dependent entries
    rewritten here (-C tau for the biases, -[f x] tau for the attitude); ``Qd`` its process noise;
    ``tail_q`` (n - nc): the noise of the identity states after it; ``work`` (nc x n) and
    ``work_cc`` (nc x nc): buffers.  The products are BLAS's (np.dot), as in the reference."""
    for a in range(3):
        for b in range(3):
            x = C[a, b] * -tau
            phi[i_att + a, i_bg + b] = x
            phi[i_vel + a, i_ba + b] = x
    phi[i_vel + 0, i_att + 1] = fz
    phi[i_vel + 0, i_att + 2] = -fy
    phi[i_vel + 1, i_att + 0] = -fz
    phi[i_vel + 1, i_att + 2] = fx
    phi[i_vel + 2, i_att + 0] = fy
    phi[i_vel + 2, i_att + 1] = -fx
    nc = phi.shape[0]
    n = P.shape[0]
    if nc == n:                                   # the whole state densely
        np.dot(phi, P, work)
        np.dot(work, phi.T, work_cc)
        for i in range(n):
            for j in range(n):
                P[i, j] = work_cc[i, j] + Qd[i, j]
        return
    np.dot(phi, P[:nc], work)                     # [Phi_c P_cc | Phi_c P_cx]
    np.dot(np.ascontiguousarray(work[:, :nc]), phi.T, work_cc)
    for i in range(nc):
        for j in range(nc):
            P[i, j] = work_cc[i, j] + Qd[i, j]
        for j in range(nc, n):
            P[i, j] = work[i, j]
            P[j, i] = work[i, j]
    for t in range(n - nc):
        P[nc + t, nc + t] += tail_q[t]


def jit_options(numba) -> dict:
    """numba.njit options: cached on disk when numba finds a writable cache directory (beside the
    source, or the user's cache; ``NUMBA_CACHE_DIR`` overrides both), else compiled in memory at
    every start (numba refuses ``cache=True`` without a place to write: say so, go on)."""
    def probe(x):
        return x
    try:
        numba.njit(cache=True)(probe)
        return {"cache": True, "nogil": True}
    except RuntimeError as e:          # "cannot cache function ...: no locator available"
        log.warning("numba cannot cache its compiled kernels (%s): they compile at every start; "
                    "set NUMBA_CACHE_DIR to a writable directory", e)
        return {"cache": False, "nogil": True}


class _Compiled:
    """The jitted kernels (attributes named as the Python functions above)."""

    def __init__(self, numba):
        jit = numba.njit(**jit_options(numba))
        self.strapdown = jit(strapdown)
        self.propagate = jit(propagate)


def enabled_by_environment() -> bool:
    return os.environ.get(ENV_SWITCH, "1").strip().lower() not in ("0", "false", "no", "off")


def numba_or_none():
    """The numba module, or None (not installed, or disabled by ``COMPANION_NUMBA=0``)."""
    if not enabled_by_environment():
        return None
    try:
        import numba
    except ImportError:
        return None
    except Exception as e:             # e.g. a numba too old for this numpy refuses to import
        log.warning("numba does not import (%s): the pure-Python IMU path runs", e)
        return None
    return numba


def compiled():
    """The compiled kernels, or None (numba not installed, or ``COMPANION_NUMBA=0``).  The first
    call imports numba; each kernel compiles (or loads from the disk cache) on its first call."""
    global _kernels, _tried
    if _tried:
        return _kernels
    _tried = True
    numba = numba_or_none()
    if numba is not None:
        _kernels = _Compiled(numba)
    return _kernels


def use_reference_paths():
    """From now on in this process, the pure-Python references instead of the compiled kernels
    (IMU and LAMBDA; the results are the same).  The live service without RTK takes them: there
    the engine is a small part of the service's CPU (`python -m sitl fly --duration 60`: 20.0 %
    of a core without the kernels, 20.2 % with), and numba costs about 100 MB of memory.
    Returns a function that restores the previous choice (the service calls it at shutdown)."""
    global _kernels, _tried
    from ..gnss import lambda_kernel
    before = (_kernels, _tried, lambda_kernel._kernels, lambda_kernel._tried)
    _kernels, _tried = None, True
    lambda_kernel._kernels, lambda_kernel._tried = None, True

    def restore() -> None:
        global _kernels, _tried
        _kernels, _tried, lambda_kernel._kernels, lambda_kernel._tried = before
    return restore


def warm_up() -> float:
    """Compile (or load from the disk cache) every kernel now, on tiny data: the IMU kernels in
    both propagation forms (dense, by blocks), the satellite state's and LAMBDA's.  Returns the
    seconds it took.  An install runs it (scripts/_venv.sh) so that a first flight does not stall
    ~3-10 s compiling at its first IMU sample or RTK fix; a service may call it at start-up (~0.5 s
    from the cache)."""
    import time
    t0 = time.perf_counter()
    if compiled() is None:
        return 0.0
    from ..gnss.lambda_kernel import lambda_ils
    from .filter import ErrorStateKalmanFilter, ProcessNoise
    from .strapdown import strapdown_step_with_force
    r, C = np.array([6378137.0, 0.0, 0.0]), np.eye(3)
    *_, dv_e = strapdown_step_with_force(r, np.zeros(3), C, (0.0, 0.0, 0.0), (0.0, 0.0, -0.049), 0.005,
                                         np.array([-9.8, 0.0, 0.0]))
    for extra in (0, 30):
        kf = ErrorStateKalmanFilter(np.eye(18), ProcessNoise(1e-4, 1e-3, 1e-5, 1e-4))
        for i in range(extra):
            kf.add_block(f"warm-up {i}", 1, 1.0)
        kf.propagate(C, dv_e, np.zeros((3, 3)), 0.005)
    _warm_up_engine()
    from ..gnss import sat_state_kernel
    sat_state_kernel.warm_up()
    lambda_ils(np.array([0.2, 1.4, -2.7]), np.array([[1.0, 0.5, 0.2], [0.5, 1.0, 0.3], [0.2, 0.3, 1.0]]))
    return time.perf_counter() - t0


def _warm_up_engine() -> None:
    """The fused IMU step (companion.nav.imu_fused), per sample and by batch, through an engine,
    and the kernels beside it."""
    from ..messages import ImuSample
    from .engine import EngineConfig, NavEngine
    from .filter import ProcessNoise
    eng = NavEngine(EngineConfig(noise=ProcessNoise(1e-4, 1e-3, 1e-5, 1e-4), zupt_enabled=True))
    eng.initialize(0.0, np.array([6378137.0, 0.0, 0.0]), np.zeros(3), np.eye(3),
                   {"att_rad": 0.01, "pos_m": 1.0, "vel_mps": 0.1, "ba_mps2": 0.1, "bg_radps": 0.01})
    dv = np.array([0.0, 0.0, -0.049])
    eng.process_imu(ImuSample(0.005, 0.005, np.zeros(3), dv))
    eng.process_imu_batch(np.array([0.01, 0.015]), np.full(2, 0.005), np.zeros((2, 3)), np.tile(dv, (2, 1)))
    # the stillness statistics and the history correction and look-up, called from Python when due
    from . import imu_fused
    imu_fused.kernels().still_window_std(eng._ws, 2, np.zeros(5))
    eng._hist.correct(np.zeros(3), np.zeros(3), np.eye(3))
    eng._hist.interpolate(0.0125)


if __name__ == "__main__":            # python -m companion.nav.imu_kernel
    from companion.nav import imu_kernel as _package_module   # the instance the filter uses
    s = _package_module.warm_up()
    print(f"compiled kernels ready in {s:.1f} s" if _package_module.compiled() is not None
          else "compiled kernels off (numba not installed or COMPANION_NUMBA=0): pure Python")
