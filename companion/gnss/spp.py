"""Weighted least-squares single point positioning (SPP / code DGPS) with RAIM FDE, DOPs and
Doppler velocity.

Model (from :mod:`companion.gnss.prepare`): P_i = |r_sat,i - r| + b + isb_s(i) + e_i,
e_i ~ N(0, sigma_i^2), with one receiver clock b (of the reference system: the first of G, E, C, J
present) and one inter-system bias isb_s per other system present (RTKLIB's pntpos has the same
columns).  A system with a single satellite is dropped (its bias would absorb it: it adds nothing
and cannot be checked); with fewer satellites than unknowns the system with the fewest is dropped
until the set is solvable.  Gauss-Newton on (r_e, b, isb) with weights 1/sigma_i^2.  RAIM FDE:
after convergence with n >= m + 1 satellites (m = 3 + number of systems), the weighted sum of
squared residuals is tested against chi^2_{n-m}(1 - RAIM_P_FA); on failure the satellite with the
largest normalized residual |v_i| / sqrt(Qvv_ii) is removed and the solution repeated, as long as
m + 1 satellites remain (so every accepted set is itself testable).  DOPs come from the position
and reference-clock block of the unweighted cofactor matrix.  Velocity and clock drift: WLS on
Doppler range rates -lambda D_i + c ddt_sat,i = u_i . (v_sat,i - v) + d, using the satellites of
the position solution; one drift for all systems (inter-system biases are constant).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from ..nav.chi2 import chi2_ppf

from ..messages import GnssEpoch
from ..nav.earth import C_n_e, ecef_to_geodetic
from .ephemeris_store import EphemerisStore
from .prepare import PreparedEpoch, prepare_epoch
from .signals import SUPPORTED_SYSTEMS as SYSTEM_ORDER
from .signals import clock_group

RAIM_P_FA = 1e-3              # false-alarm probability of the global chi-square test
MAX_ITER = 12
CONVERGED_M = 1e-4
MAX_GDOP = 30.0
DOPPLER_SIGMA_MPS = 0.1       # range-rate noise from Doppler at zenith (scaled by 1/sin E)


@dataclass
class SppSolution:
    t_gps: float
    r_e: np.ndarray
    clock_bias_m: float
    v_e: np.ndarray | None
    clock_drift_mps: float
    sats: list[str]                      # satellites used
    excluded: dict[str, str]             # satellite -> reason (RAIM, no pseudorange, prepare rejections)
    residuals_m: np.ndarray              # post-fit residuals of the used satellites
    sigma_m: np.ndarray                  # their a-priori sigmas
    gdop: float
    pdop: float
    hdop: float
    vdop: float
    n_iter: int
    chi2: float = float("nan")
    chi2_threshold: float = float("nan")
    raim_ok: bool | None = None          # None: not testable (n < 4 + number of clock groups)
    cov_r_e: np.ndarray = field(default_factory=lambda: np.full((3, 3), np.nan))
    clock_system: str = "G"              # clock group of clock_bias_m: the first of G (GPS and QZSS), E, C used
    n_sats_by_system: dict[str, int] = field(default_factory=dict)   # satellites used per system
    isb_m: dict[str, float] = field(default_factory=dict)  # clock group -> its clock minus clock_system's, m

    @property
    def n_sats(self) -> int:
        return len(self.sats)


def _design(r_sat, x, sys_col):
    """(residuals' geometry: ranges, H) at state x = (r, b, isb...); ``sys_col[i]`` is the column
    of satellite i's inter-system bias (0: the reference system, none)."""
    d = r_sat - x[:3]
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    u = d / rho[:, None]
    h = np.zeros((len(rho), len(x)))
    h[:, :3] = -u
    h[:, 3] = 1.0
    rows = np.flatnonzero(sys_col)
    h[rows, 3 + sys_col[rows]] = 1.0
    return rho, h


def _wls(r_sat, pr, w, x0, sys_col, max_iter=MAX_ITER):
    x = x0.copy()
    for it in range(1, max_iter + 1):
        rho, h = _design(r_sat, x, sys_col)
        v = pr - (rho + h[:, 3:] @ x[3:])
        hw = h * w[:, None]
        n = h.T @ hw
        try:
            dx = np.linalg.solve(n, hw.T @ v)
        except np.linalg.LinAlgError:
            return None
        x += dx
        if np.linalg.norm(dx) < CONVERGED_M:
            break
    rho, h = _design(r_sat, x, sys_col)
    v = pr - (rho + h[:, 3:] @ x[3:])
    return x, v, h, it


def _system_columns(sats: list[str], idx: list[int], excluded: dict[str, str]) -> tuple[list[int], list[str]]:
    """(satellite indices kept, clock groups in column order: reference first) after dropping
    groups with one satellite and, while n < 3 + number of groups, the group with the fewest."""
    by_sys: dict[str, list[int]] = {}
    for i in idx:
        by_sys.setdefault(clock_group(sats[i]), []).append(i)
    order = sorted(by_sys, key=lambda c: (SYSTEM_ORDER.find(c) % 99, c))
    keep = [c for c in order if len(by_sys[c]) >= 2 or len(by_sys) == 1]
    while keep and sum(len(by_sys[c]) for c in keep) < 3 + len(keep) and len(keep) > 1:
        keep.remove(min(reversed(keep), key=lambda c: len(by_sys[c])))
    for c in order:
        if c not in keep:
            for i in by_sys[c]:
                excluded[sats[i]] = "too few satellites of its system"
    kept = [i for i in idx if clock_group(sats[i]) in keep]
    return kept, keep


def solve_spp(prepared: PreparedEpoch, r_init_e=None, *, raim: bool = True) -> SppSolution | None:
    """WLS position + clock (+ one inter-system bias per extra system) from a :class:`PreparedEpoch`;
    None with fewer usable satellites than unknowns + 0 (4 for one system), a singular geometry,
    GDOP > ``MAX_GDOP`` or no convergence to a point near the earth surface."""
    excluded = dict(prepared.rejected)
    ok = np.isfinite(prepared.pseudorange_m)
    for i in np.flatnonzero(~ok):
        excluded[prepared.sats[i]] = "no pseudorange"
    idx, systems = _system_columns(prepared.sats, list(np.flatnonzero(ok)), excluded)
    if len(idx) < 4:
        return None
    if r_init_e is None:
        r_init_e = prepared.r_approx_e
    x0 = np.zeros(3 + len(systems))
    x0[:3] = np.asarray(r_init_e, dtype=float)
    r_sat_all, pr_all = prepared.r_sat_e, prepared.pseudorange_m
    sig_all = prepared.sigma_pseudorange_m
    chi2_val = thr = float("nan")
    raim_ok = None
    while True:
        ii = np.array(idx)
        col = {c: k for k, c in enumerate(systems)}
        sys_col = np.array([col[clock_group(prepared.sats[i])] for i in ii], dtype=int)
        w = 1.0 / sig_all[ii] ** 2
        res = _wls(r_sat_all[ii], pr_all[ii], w, x0, sys_col)
        if res is None:
            return None
        x, v, h, n_iter = res
        nsat, m = len(ii), len(x)
        if not raim or nsat < m + 1:
            break
        chi2_val = float(np.sum(w * v * v))
        thr = float(chi2_ppf(1.0 - RAIM_P_FA, nsat - m))
        if chi2_val <= thr:
            raim_ok = True
            break
        raim_ok = False
        if nsat - 1 < m + 1:
            break
        hw = h * w[:, None]
        q = np.linalg.inv(h.T @ hw)
        qvv = 1.0 / w - np.einsum("ij,jk,ik->i", h, q, h)
        norm = np.abs(v) / np.sqrt(np.maximum(qvv, 1e-12))
        k = int(np.argmax(norm))
        rest, rest_sys = _system_columns(prepared.sats, idx[:k] + idx[k + 1:], {})
        if len(rest) < 3 + len(rest_sys) + 1:     # the set without it could not be tested
            break
        excluded[prepared.sats[ii[k]]] = f"RAIM (normalized residual {norm[k]:.1f})"
        idx, systems_new = _system_columns(prepared.sats, idx[:k] + idx[k + 1:], excluded)
        keep_cols = [0, 1, 2, 3] + [3 + col[c] for c in systems_new[1:] if c in col and col[c] > 0]
        x0 = x[keep_cols] if systems_new[0] == systems[0] else np.concatenate([x[:4], np.zeros(len(systems_new) - 1)])
        systems = systems_new
    r = x[:3]
    if not (6.0e6 < np.linalg.norm(r) < 4.3e7):  # 20 000 km altitude allowed
        return None
    try:
        q_unw = np.linalg.inv(h.T @ h)
        q_w = np.linalg.inv(h.T @ (h * w[:, None]))
    except np.linalg.LinAlgError:
        return None
    lat, lon, _ = ecef_to_geodetic(r)
    cne = C_n_e(lat, lon)
    q_n = cne.T @ q_unw[:3, :3] @ cne
    gdop = math.sqrt(max(np.trace(q_unw[:4, :4]), 0.0))
    if gdop > MAX_GDOP:
        return None
    sats = [prepared.sats[i] for i in idx]
    v_e, drift = _doppler_velocity(prepared, np.array(idx), r)
    n_by_sys: dict[str, int] = {}
    for s_ in sats:
        n_by_sys[s_[0]] = n_by_sys.get(s_[0], 0) + 1
    return SppSolution(
        t_gps=prepared.t_gps, r_e=r.copy(), clock_bias_m=float(x[3]), v_e=v_e, clock_drift_mps=drift,
        sats=sats, excluded=excluded, residuals_m=v, sigma_m=sig_all[np.array(idx)].copy(), gdop=gdop,
        pdop=math.sqrt(max(np.trace(q_unw[:3, :3]), 0.0)), hdop=math.sqrt(max(q_n[0, 0] + q_n[1, 1], 0.0)),
        vdop=math.sqrt(max(q_n[2, 2], 0.0)), n_iter=n_iter, chi2=chi2_val, chi2_threshold=thr,
        raim_ok=raim_ok, cov_r_e=q_w[:3, :3], clock_system=systems[0], n_sats_by_system=n_by_sys,
        isb_m={c: float(x[3 + k]) for k, c in enumerate(systems) if k > 0})


def _doppler_velocity(p: PreparedEpoch, idx: np.ndarray, r: np.ndarray):
    """(v_e, clock drift m/s) from Doppler of the used satellites, or (None, NaN) with < 4."""
    dop = p.doppler_hz[idx]
    good = np.isfinite(dop) & np.isfinite(p.wavelength_m[idx])
    if good.sum() < 4:
        return None, float("nan")
    j = idx[good]
    d = p.r_sat_e[j] - r
    u = d / np.linalg.norm(d, axis=1)[:, None]
    rate = -p.wavelength_m[j] * p.doppler_hz[j] + p.sat_clock_drift_mps[j]
    y = rate - np.einsum("ij,ij->i", u, p.v_sat_e[j])
    h = np.hstack([-u, np.ones((len(j), 1))])
    el = p.elevation_rad[j]
    s = np.where(np.isfinite(el), np.maximum(np.sin(el), 0.05), 1.0)
    w = (s / DOPPLER_SIGMA_MPS) ** 2
    try:
        x = np.linalg.solve(h.T @ (h * w[:, None]), (h * w[:, None]).T @ y)
    except np.linalg.LinAlgError:
        return None, float("nan")
    return x[:3], float(x[3])


def spp_epoch(epoch: GnssEpoch, store: EphemerisStore, *, dgps=None, klobuchar=None, r_init_e=None,
              elevation_mask_rad: float = math.radians(10.0), signal: str = "L1C", raim: bool = True,
              max_passes: int = 4, systems: str = "G") -> SppSolution | None:
    """prepare_epoch + solve_spp, re-preparing at the solution (elevation, atmosphere and Sagnac
    depend on the position) until the position moves by less than 1 m between passes.

    Starts from ``r_init_e`` (e.g. the previous solution) or the earth centre; the first pass from
    the earth centre has no elevation mask, models or RAIM.  ``systems``: see
    :func:`companion.gnss.prepare.prepare_epoch` (GPS only by default).
    """
    r0 = np.zeros(3) if r_init_e is None else np.asarray(r_init_e, dtype=float)
    sol = None
    sol_known = False            # was ``sol`` computed at a known position (mask, models, RAIM)?
    for _ in range(max_passes):
        known = np.linalg.norm(r0) > 1.0e6
        prep = prepare_epoch(epoch, store, r0, dgps=dgps, elevation_mask_rad=elevation_mask_rad,
                             klobuchar=klobuchar, signal=signal, systems=systems)
        new = solve_spp(prep, r0, raim=raim and known)
        if new is None:
            break
        moved = float(np.linalg.norm(new.r_e - r0))
        sol, sol_known = new, known
        r0 = new.r_e
        if known and moved < 1.0:
            break
    # never return a first-pass solution (no mask, no atmosphere, no RAIM)
    return sol if sol_known else None
