"""INS error analysis: our mechanization run free-inertially against the analytic Schuler solution.

``python -m sitl ins-errors [--case N] [--hours H] [--rate HZ] [--json PATH] [--plot PATH]``

Seed 004 eqs 1-2 give the horizontal velocity error of a free INS from its initial velocity
errors, tilts, gyro drifts and accelerometer biases; eqs 3-4 the latitude/longitude errors as
their integrals (dLat = int dV_n dt / R_M, dLon = int dV_e dt / (R_N cos(lat))).  That solution
assumes a *stationary* (or slow) INS with level errors and neglects the earth-rate (Foucault)
coupling.  So the cases come in two groups:

* **stationary** (the analytic solution holds): at the equator, where the earth rate has no
  vertical component, so the north and east channels do not couple.  These are propagated with
  :func:`companion.nav.free_inertial.run_free_inertial` and compared with
  :func:`~companion.nav.free_inertial.schuler_velocity_error`; ``schuler_max_rel_dev`` is the
  largest ``max|num - analytic| / max|analytic|`` over them.
* **moving** (seed 001's cases as flown): a vehicle on a rhumb line at constant speed, heading and
  height.  The truth is generated as in ``sitl.simulate`` (ECEF velocity from the NED velocity,
  position by the mechanization's trapezoid rule, error-free increments by the exact inverse
  ``invert_step``); the mechanization is run twice along it, error-free and with the case's
  errors, and the error is their difference in local NED.  Here transport rate (V/R = 4e-5 rad/s at
  260 m/s, comparable to the earth rate) and Coriolis couple the channels, so the stationary
  solution is shown for reference only and not counted in ``schuler_max_rel_dev``.

Seed 001's case values the paper leaves open (documented choices):
* case 1: V0 = 260 m/s, azimuth 45 deg, accelerometer bias 0.01 m/s^2 on the along-track (body x)
  accelerometer; latitude 45 deg N (not given), height 1000 m; no other error.
* case 2: V0 = 100 m/s, azimuth 15 deg, gyro drift 0.01 deg/h on each body axis and initial
  misalignment 1 arcmin about body x and y (levelling) and 5 arcmin about z (heading); same place.
* "at rest" versions of both at the equator, where eqs 1-2 hold: case 1's bias along azimuth
  45 deg; case 2's drift and tilt about north.  Case 2's drifts and tilts on body x and y at
  azimuth 15 deg are also run at rest but reported as *approximate*: their east components couple
  with the earth rate (north at the equator: an east tilt turns into heading error at Omega),
  which eqs 1-2 neglect -- about 4 % in velocity and 6 % in position after 2 h.

In every run the vertical channel is held (as an altimeter would, and as eqs 1-4 assume).
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from scipy.integrate import cumulative_trapezoid

from companion.nav.earth import (C_n_e, geodetic_to_ecef, radii_of_curvature, rotation_from_rotvec)
from companion.nav.free_inertial import (FreeInertialCase, fit_sinusoid_period, run_free_inertial,
                                          schuler_velocity_error)
from companion.nav.strapdown import invert_step, strapdown_step

PAPER_SCHULER_PERIOD_MIN = 84.4
PAPER_001_CASE1_LAT_ERR_ARCMIN_2H = 1.0     # seed 001: latitude error ~1 arc-minute after 2 h
ARCMIN = math.pi / (180.0 * 60.0)
DEG_PER_H = math.pi / 180.0 / 3600.0


def _yaw(az_rad: float) -> np.ndarray:
    c, s = math.cos(az_rad), math.sin(az_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass
class MovingCase:
    """A vehicle on a rhumb line (constant NED velocity, heading = azimuth, level), with errors
    given in *body* axes (x along track, y right, z down)."""

    name: str
    speed_mps: float
    azimuth_deg: float
    lat_deg: float = 45.0
    lon_deg: float = 30.0
    h_m: float = 1000.0
    accel_bias_b_mps2: tuple = (0.0, 0.0, 0.0)
    gyro_bias_b_radps: tuple = (0.0, 0.0, 0.0)
    tilt0_b_rad: tuple = (0.0, 0.0, 0.0)       # initial attitude error about body axes
    dv0_n_mps: tuple = (0.0, 0.0, 0.0)
    hours: float = 2.0
    rate_hz: float = 5.0

    def stationary_equivalent(self) -> FreeInertialCase:
        """The same errors expressed in NED at the start, for the (stationary) analytic solution."""
        Cbn = _yaw(math.radians(self.azimuth_deg))
        return FreeInertialCase(self.name + " (analytic, stationary)", self.lat_deg, self.lon_deg, self.h_m,
                                dv0_n_mps=tuple(self.dv0_n_mps),
                                tilt0_n_rad=tuple(Cbn @ np.array(self.tilt0_b_rad)),
                                accel_bias_n_mps2=tuple(Cbn @ np.array(self.accel_bias_b_mps2)),
                                gyro_bias_n_radps=tuple(Cbn @ np.array(self.gyro_bias_b_radps)),
                                hours=self.hours, rate_hz=self.rate_hz)


def run_moving(case: MovingCase):
    """Error (with-error run minus error-free run) along a rhumb-line trajectory.

    Returns (t_s, dv_ne (N,2), dpos_ne (N,2), max deviation of the error-free run from truth, m),
    sampled at 1 Hz.  Both runs use the same error-free increments (from ``invert_step`` on the
    truth); the with-error run adds the body-frame biases and starts from the case's errors."""
    tau = 1.0 / case.rate_hz
    n_steps = int(round(case.hours * 3600.0 * case.rate_hz))
    az = math.radians(case.azimuth_deg)
    v_n = case.speed_mps * np.array([math.cos(az), math.sin(az), 0.0])
    Cbn = _yaw(az)
    lat, lon = math.radians(case.lat_deg), math.radians(case.lon_deg)
    r_t = geodetic_to_ecef(lat, lon, case.h_m)
    Cne = C_n_e(lat, lon)
    v_t, C_t = Cne @ v_n, Cne @ Cbn
    # the two runs
    r_f, v_f, C_f = r_t.copy(), v_t.copy(), C_t.copy()
    r_x = r_t.copy()
    v_x = v_t + Cne @ np.array(case.dv0_n_mps, float)
    C_x = rotation_from_rotvec(C_t @ np.array(case.tilt0_b_rad, float)) @ C_t
    ba = np.array(case.accel_bias_b_mps2, float) * tau
    bg = np.array(case.gyro_bias_b_radps, float) * tau
    decim = max(1, int(round(case.rate_hz)))
    ts, dvs, dps = [0.0], [Cne.T @ (v_x - v_f)], [Cne.T @ (r_x - r_f)]
    max_free_dev = 0.0
    for k in range(1, n_steps + 1):
        # truth: NED velocity along the rhumb line, position by the mechanization's trapezoid rule
        m, nn = radii_of_curvature(lat)
        lat += v_n[0] * tau / (m + case.h_m)
        lon += v_n[1] * tau / ((nn + case.h_m) * math.cos(lat))
        Cne1 = C_n_e(lat, lon)
        v_t1, C_t1 = Cne1 @ v_n, Cne1 @ Cbn
        dth, dv = invert_step(r_t, v_t, C_t, v_t1, C_t1, tau)
        r_t = r_t + (v_t + v_t1) * (0.5 * tau)
        v_t, C_t, Cne = v_t1, C_t1, Cne1
        r_f, v_f, C_f = strapdown_step(r_f, v_f, C_f, dth, dv, tau)
        r_x, v_x, C_x = strapdown_step(r_x, v_x, C_x, dth + bg, dv + ba, tau)
        up = -Cne[:, 2]
        # hold the vertical channel of the erroneous run to the error-free one
        r_x = r_x - up * float((r_x - r_f) @ up)
        v_x = v_x - up * float((v_x - v_f) @ up)
        if k % decim == 0:
            max_free_dev = max(max_free_dev, float(np.max(np.abs(r_f - r_t))))
            ts.append(k * tau)
            dvs.append(Cne.T @ (v_x - v_f))
            dps.append(Cne.T @ (r_x - r_f))
    return np.array(ts), np.array(dvs)[:, :2], np.array(dps)[:, :2], max_free_dev


def analytic_position_error(case: FreeInertialCase, t_s: np.ndarray) -> np.ndarray:
    """Seed 004 eqs 3-4: (north, east) position error in metres, the time integral of the analytic
    velocity error (trapezoid on a 1-s grid: relative error ~ (nu dt)^2/12 ~ 1e-7)."""
    grid = np.arange(0.0, float(t_s[-1]) + 1.0, 1.0)
    dv = schuler_velocity_error(case, grid)
    pos = cumulative_trapezoid(dv, grid, axis=0, initial=0.0)
    return np.column_stack([np.interp(t_s, grid, pos[:, 0]), np.interp(t_s, grid, pos[:, 1])])


def lat_lon_errors_arcmin(dpos_ne: np.ndarray, lat_rad: float, h_m: float = 0.0) -> np.ndarray:
    """(dLat, dLon) in arc-minutes from north/east position errors (eqs 3-4's R and R cos(lat))."""
    m, n = radii_of_curvature(lat_rad)
    return np.column_stack([dpos_ne[:, 0] / (m + h_m), dpos_ne[:, 1] / ((n + h_m) * math.cos(lat_rad))]) / ARCMIN


def default_cases(hours: float = 2.0, rate_hz: float = 5.0):
    """(stationary cases where eqs 1-2 hold, stationary cases where they are approximate because
    of the neglected earth-rate coupling, moving cases of seed 001)."""
    az1, az2 = math.radians(45.0), math.radians(15.0)
    b1 = 0.01
    drift = 0.01 * DEG_PER_H
    tilt = 1.0 * ARCMIN
    C2 = _yaw(az2)
    stationary = [
        FreeInertialCase("at rest: initial velocity error (0.1, -0.05) m/s", dv0_n_mps=(0.10, -0.05, 0.0)),
        FreeInertialCase("at rest: seed 001 case 1 bias 0.01 m/s^2 along az 45 deg",
                         accel_bias_n_mps2=(b1 * math.cos(az1), b1 * math.sin(az1), 0.0)),
        FreeInertialCase("at rest: seed 001 case 2 drift 0.01 deg/h + tilt 1' about north",
                         tilt0_n_rad=(tilt, 0.0, 0.0), gyro_bias_n_radps=(drift, 0.0, 0.0)),
    ]
    # approximate: tilt and drift about east couple with the earth rate (north at the equator),
    # which eqs 1-2 neglect; reported, not counted in schuler_max_rel_dev
    approximate = [
        FreeInertialCase("at rest: seed 001 case 2 drifts 0.01 deg/h + tilts 1' on body x,y (az 15 deg)",
                         tilt0_n_rad=tuple(C2 @ np.array([tilt, tilt, 0.0])),
                         gyro_bias_n_radps=tuple(C2 @ np.array([drift, drift, 0.0]))),
    ]
    stationary = [replace(c, hours=hours, rate_hz=rate_hz) for c in stationary]
    approximate = [replace(c, hours=hours, rate_hz=rate_hz) for c in approximate]
    moving = [
        MovingCase("seed 001 case 1: 260 m/s, az 45 deg, accel bias 0.01 m/s^2 (body x)", 260.0, 45.0,
                   accel_bias_b_mps2=(b1, 0.0, 0.0), hours=hours, rate_hz=rate_hz),
        MovingCase("seed 001 case 2: 100 m/s, az 15 deg, drifts 0.01 deg/h, misalignment 1'/1'/5'", 100.0, 15.0,
                   gyro_bias_b_radps=(drift, drift, drift), tilt0_b_rad=(tilt, tilt, 5.0 * tilt),
                   hours=hours, rate_hz=rate_hz),
    ]
    return stationary, approximate, moving


def _metrics(t, dv_num, dp_num, fic: FreeInertialCase):
    an_v = schuler_velocity_error(fic, t)
    an_p = analytic_position_error(fic, t)
    amp = float(np.max(np.abs(an_v)))
    rel = float(np.max(np.abs(dv_num - an_v)) / amp)
    comp = int(np.argmax(np.max(np.abs(dv_num), axis=0)))
    try:
        period_s, _ = fit_sinusoid_period(t, dv_num[:, comp], PAPER_SCHULER_PERIOD_MIN * 60.0)
    except Exception:  # pragma: no cover - degenerate fit
        period_s = float("nan")
    lat = math.radians(fic.lat_deg)
    ll_num = lat_lon_errors_arcmin(dp_num, lat, fic.h_m)
    ll_an = lat_lon_errors_arcmin(an_p, lat, fic.h_m)
    pos_amp = float(np.max(np.abs(an_p)))
    return {"amplitude_mps": amp, "max_rel_dev": rel, "fitted_period_min": period_s / 60.0,
            "pos_max_rel_dev": float(np.max(np.abs(dp_num - an_p)) / pos_amp) if pos_amp > 0 else float("nan"),
            "lat_err_arcmin_end": float(ll_num[-1, 0]), "lat_err_arcmin_end_analytic": float(ll_an[-1, 0]),
            "lon_err_arcmin_end": float(ll_num[-1, 1]), "lon_err_arcmin_end_analytic": float(ll_an[-1, 1]),
            "max_abs_lat_err_arcmin": float(np.max(np.abs(ll_num[:, 0]))),
            "_series": {"t_s": t, "dv_num": dv_num, "dv_an": an_v, "ll_num": ll_num, "ll_an": ll_an}}


def run_ins_errors(case_index: int | None = None, hours: float = 2.0, rate_hz: float = 5.0) -> dict:
    """All cases (or the one numbered ``case_index``, 1-based over stationary then moving)."""
    t_start = time.perf_counter()
    stationary, approximate, moving = default_cases(hours, rate_hz)
    allc = ([("stationary", c) for c in stationary] + [("approximate", c) for c in approximate]
            + [("moving", c) for c in moving])
    picked = range(len(allc)) if case_index is None else [case_index - 1]
    out = {"hours": hours, "rate_hz": rate_hz, "cases": []}
    for i in picked:
        kind, c = allc[i]
        if kind in ("stationary", "approximate"):
            t, dv, dp = run_free_inertial(c)
            m = _metrics(t, dv, dp, c)
            m.update(holds=kind == "stationary")
        else:
            t, dv, dp, free_dev = run_moving(c)
            m = _metrics(t, dv, dp, c.stationary_equivalent())
            m.update(holds=False, error_free_run_max_dev_m=free_dev)
        m.update(index=i + 1, name=c.name, kind=kind)
        out["cases"].append(m)
    held = [c["max_rel_dev"] for c in out["cases"] if c["holds"]]
    out["schuler_max_rel_dev"] = max(held) if held else None
    out["schuler_period_paper_min"] = PAPER_SCHULER_PERIOD_MIN
    c1 = [c for c in out["cases"] if c["name"].startswith("seed 001 case 1")]
    if c1:
        out["paper_001_case1"] = {"paper_lat_err_arcmin_2h": PAPER_001_CASE1_LAT_ERR_ARCMIN_2H,
                                  "ours_lat_err_arcmin_end": c1[0]["lat_err_arcmin_end"],
                                  "ours_max_abs_lat_err_arcmin": c1[0]["max_abs_lat_err_arcmin"],
                                  "analytic_lat_err_arcmin_end": c1[0]["lat_err_arcmin_end_analytic"]}
    out["elapsed_s"] = time.perf_counter() - t_start
    return out


def format_table(res: dict) -> str:
    head = (f"{'#':>2} | {'case':<78} | {'analytic holds':>14} | {'amplitude':>11} | {'max rel dev':>11} | "
            f"{'period':>15} | {'dLat end [arcmin]':>19}")
    lines = [f"free-inertial error over {res['hours']:g} h at {res['rate_hz']:g} Hz: ours vs seed 004 eqs 1-4",
             head, "-" * len(head)]
    for c in res["cases"]:
        lines.append(f"{c['index']:>2} | {c['name']:<78} | {'yes' if c['holds'] else 'no (' + c['kind'] + ')':>14} | "
                     f"{c['amplitude_mps']:7.4f} m/s | {100 * c['max_rel_dev']:10.2f}% | "
                     f"{c['fitted_period_min']:6.2f} (84.4) | {c['lat_err_arcmin_end']:8.3f} ({c['lat_err_arcmin_end_analytic']:7.3f})")
    lines.append("-" * len(head))
    if res["schuler_max_rel_dev"] is not None:
        lines.append(f"schuler_max_rel_dev (cases where the analytic solution holds): "
                     f"{100 * res['schuler_max_rel_dev']:.2f} %")
    p = res.get("paper_001_case1")
    if p:
        lines.append(f"seed 001 case 1 latitude error after {res['hours']:g} h: paper ~{p['paper_lat_err_arcmin_2h']:g}', "
                     f"ours {p['ours_lat_err_arcmin_end']:.2f}' (max |dLat| {p['ours_max_abs_lat_err_arcmin']:.2f}'), "
                     f"stationary analytic {p['analytic_lat_err_arcmin_end']:.2f}'")
    lines.append("dLat column: ours (analytic); period: fitted (paper's 84.4 min)")
    return "\n".join(lines)


def plot(res: dict, path: str) -> None:
    from companion.extras import pyplot
    plt = pyplot("python -m sitl ins-errors --plot")

    n = len(res["cases"])
    fig, axes = plt.subplots(n, 2, figsize=(12, 2.6 * n), squeeze=False)
    for row, c in zip(axes, res["cases"]):
        s = c["_series"]
        tm = s["t_s"] / 60.0
        for j, lab in enumerate(("north", "east")):
            row[0].plot(tm, s["dv_num"][:, j], label=f"dV_{lab[0]} ours")
            row[0].plot(tm, s["dv_an"][:, j], "--", label=f"dV_{lab[0]} analytic")
        row[1].plot(tm, s["ll_num"][:, 0], label="dLat ours")
        row[1].plot(tm, s["ll_an"][:, 0], "--", label="dLat analytic")
        row[1].plot(tm, s["ll_num"][:, 1], label="dLon ours")
        row[1].plot(tm, s["ll_an"][:, 1], "--", label="dLon analytic")
        row[0].set_title(f"{c['index']}: {c['name'][:70]}", fontsize=8)
        row[0].set_ylabel("m/s")
        row[1].set_ylabel("arcmin")
        for a in row:
            a.grid(alpha=0.3)
            a.legend(fontsize=6, ncol=2)
    for a in axes[-1]:
        a.set_xlabel("time [min]")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _jsonable(res: dict) -> dict:
    out = dict(res)
    out["cases"] = [{k: v for k, v in c.items() if not k.startswith("_")} for c in res["cases"]]
    return out


def cmd_ins_errors(args) -> int:
    res = run_ins_errors(args.case, args.hours, args.rate)
    print(format_table(res))
    print(f"({res['elapsed_s']:.1f} s)")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(_jsonable(res), indent=2))
        print(f"wrote {args.json}")
    if args.plot:
        Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
        plot(res, args.plot)
        print(f"wrote {args.plot}")
    return 0


def register(sub) -> None:
    p = sub.add_parser("ins-errors", help="free-inertial error of the mechanization vs the analytic Schuler "
                                          "solution (seeds 001, 004)")
    p.add_argument("--case", type=int, default=None,
                   help="run only this case (1-3: at rest, analytic solution holds; 4: at rest, approximate "
                        "(earth-rate coupling); 5-6: seed 001 moving)")
    p.add_argument("--hours", type=float, default=2.0)
    p.add_argument("--rate", type=float, default=5.0, help="free-inertial integration rate, Hz (default 5)")
    p.add_argument("--json", help="write the figures as JSON here")
    p.add_argument("--plot", help="write a PNG of the error curves here")
    p.set_defaults(func=cmd_ins_errors)
