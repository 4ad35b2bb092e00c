"""Compiled satellite state (numba): :func:`.sat_state.transmit_time` then :func:`.sat_state.state`
in one call, the same expressions in the same order (numba keeps IEEE semantics and evaluation
order without ``fastmath``, and calls the C library's sin/cos/atan2 as CPython's math does), so
both give the same numbers bit for bit (tests/test_gnss_epoch_fast.py).  What it saves is the
interpretation: three Kepler solutions and ~150 float operations per satellite.

Used only when the engine's compiled kernels are already loaded in this process
(:func:`companion.nav.imu_kernel.compiled` has built them): a process that never ran the IMU
kernels (SPP, post-processing, the service without RTK) does not import numba for this, and
``COMPANION_NUMBA=0`` / :func:`~companion.nav.imu_kernel.use_reference_paths` switch it off with
them.  BeiDou GEO satellites take the Python path (their numpy rotation is the reference's).
"""
from __future__ import annotations

import math

import numpy as np

from ..messages import SPEED_OF_LIGHT_MPS

#: the layout of :func:`constants_vector`
_FIELDS = ("t_oe", "t_oc", "a", "e", "n", "m0", "sq", "rel", "af0", "af1", "af2", "omega_arg", "cus", "cuc", "crs",
           "crc", "cis", "cic", "i0", "idot", "omega0", "omega_rate", "omega_e_toe")

_kernel = None
_tried = False


def constants_vector(k) -> np.ndarray:
    """An :class:`.sat_state.OrbitConstants` as the kernel's float64 vector."""
    return np.array([getattr(k, f) for f in _FIELDS], dtype=float)


def _wrap(dt):
    if dt > 302400.0:
        return dt - 604800.0
    if dt < -302400.0:
        return dt + 604800.0
    return dt


def _kepler(m0, n, e, tk):
    m = m0 + n * tk
    e_anom = m
    for _ in range(30):
        d = (e_anom - e * math.sin(e_anom) - m) / (1.0 - e * math.cos(e_anom))
        e_anom -= d
        if abs(d) < 1e-14:
            break
    return e_anom


def _clock_bias(c, t):
    dt = _wrap(t - c[1])
    bias = c[8] + c[9] * dt + c[10] * dt * dt
    return bias + c[7] * math.sin(_kepler(c[5], c[4], c[3], _wrap(t - c[0])))


def tx_state(c, t_rx, pseudorange_m, t_given):
    """(t_tx, x, y, z, vx, vy, vz, clock bias s, drift s/s): the transmit time from the
    pseudorange (``t_given`` NaN) or ``t_given`` itself, and the (non-GEO) state there."""
    if t_given == t_given:
        t = t_given
    else:
        t_sv = t_rx - pseudorange_m / 299792458.0
        bias = _clock_bias(c, t_sv)
        t = t_sv - _clock_bias(c, t_sv - bias)
    tk = _wrap(t - c[0])
    a, e, n = c[2], c[3], c[4]
    e_anom = _kepler(c[5], n, e, tk)
    sin_e, cos_e = math.sin(e_anom), math.cos(e_anom)
    one_m_ecos = 1.0 - e * cos_e
    e_dot = n / one_m_ecos
    sq = c[6]
    nu = math.atan2(sq * sin_e, cos_e - e)
    nu_dot = e_dot * sq / one_m_ecos
    phi = nu + c[11]
    s2, c2 = math.sin(2.0 * phi), math.cos(2.0 * phi)
    cus, cuc, crs, crc, cis, cic = c[12], c[13], c[14], c[15], c[16], c[17]
    du = cus * s2 + cuc * c2
    dr = crs * s2 + crc * c2
    di = cis * s2 + cic * c2
    u = phi + du
    r = a * one_m_ecos + dr
    i = c[18] + di + c[19] * tk
    u_dot = nu_dot * (1.0 + 2.0 * (cus * c2 - cuc * s2))
    r_dot = a * e * sin_e * e_dot + 2.0 * nu_dot * (crs * c2 - crc * s2)
    i_dot = c[19] + 2.0 * nu_dot * (cis * c2 - cic * s2)
    cu, su = math.cos(u), math.sin(u)
    x_orb, y_orb = r * cu, r * su
    x_orb_dot = r_dot * cu - y_orb * u_dot
    y_orb_dot = r_dot * su + x_orb * u_dot
    omega = c[20] + c[21] * tk - c[22]
    omega_dot = c[21]
    so, co = math.sin(omega), math.cos(omega)
    si, ci = math.sin(i), math.cos(i)
    x = x_orb * co - y_orb * ci * so
    y = x_orb * so + y_orb * ci * co
    z = y_orb * si
    vx = x_orb_dot * co - y_orb_dot * ci * so + y_orb * si * so * i_dot - y * omega_dot
    vy = x_orb_dot * so + y_orb_dot * ci * co - y_orb * si * co * i_dot + x * omega_dot
    vz = y_orb_dot * si + y_orb * ci * i_dot
    dt = _wrap(t - c[1])
    bias = c[8] + c[9] * dt + c[10] * dt * dt + c[7] * sin_e
    drift = c[9] + 2.0 * c[10] * dt + c[7] * cos_e * e_dot
    return t, x, y, z, vx, vy, vz, bias, drift


assert SPEED_OF_LIGHT_MPS == 299792458.0     # the literal in tx_state (a global would be frozen anyway)


def compiled():
    """The jitted :func:`tx_state`, or None: only while the IMU kernels are loaded in this process
    (followed at every call, so :func:`~companion.nav.imu_kernel.use_reference_paths` applies)."""
    global _kernel, _tried, _wrap, _kepler, _clock_bias
    import sys
    ik = sys.modules.get("companion.nav.imu_kernel")
    if ik is None or ik._kernels is None:
        return None
    if not _tried:
        _tried = True
        from ..nav.imu_kernel import jit_options, numba_or_none
        numba = numba_or_none()
        if numba is not None:
            jit = numba.njit(**jit_options(numba))
            # the helpers jitted under their own names, so that tx_state compiles against them
            _wrap, _kepler = jit(_wrap), jit(_kepler)
            _clock_bias = jit(_clock_bias)
            _kernel = jit(tx_state)
    return _kernel


def warm_up() -> bool:
    """Compile (or load from numba's disk cache) the kernel now, if the IMU kernels are loaded,
    so that the first GNSS epoch does not pay it (~3 s cold on a loaded 2-core machine).  For
    :func:`companion.nav.imu_kernel.warm_up`.  Returns whether the kernel is on."""
    kern = compiled()
    if kern is None:
        return False
    kern(np.zeros(len(_FIELDS)) + 1.0, 0.0, 2.0e7, math.nan)
    return True
