"""Score a post-processed trajectory against a log's truth, beside the autopilot's own estimate.

A SITL DataFlash log carries the simulator's truth (``SIM``: latitude, longitude in degrees,
altitude in metres, at the loop's ``TimeUS``) and the autopilot EKF's output (``POS``).  Both
trajectories (ours and the EKF's) are compared with the truth *linearly interpolated to each
sample's boot time*, over the same time span (from our first solution to our last, inside the
truth's span), so the two figures are like for like.  Horizontal error = the north/east
difference on the WGS-84 ellipsoid's local radii (meridian M, prime vertical N) at the truth
point; at the log's scale (100 m) the approximation error is below a micrometre.

Pure: numpy arrays in, dicts out.
"""
from __future__ import annotations

import math

import numpy as np

WGS84_A_M = 6378137.0
WGS84_E2 = 6.69437999014e-3


def _radii(lat_rad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    s2 = np.sin(lat_rad) ** 2
    w = np.sqrt(1.0 - WGS84_E2 * s2)
    return WGS84_A_M * (1.0 - WGS84_E2) / w ** 3, WGS84_A_M / w


def ne_errors_m(t_s, lat_deg, lon_deg, truth) -> tuple[np.ndarray, np.ndarray]:
    """North/east errors (m) of the samples against ``truth`` (rows: t_us, lat deg, lon deg, alt m)
    interpolated to ``t_s`` (boot time, s), and the mask of samples inside the truth's span."""
    t_s = np.asarray(t_s, float)
    tt = truth[:, 0] * 1e-6
    inside = (t_s >= tt[0]) & (t_s <= tt[-1])
    lat_t = np.radians(np.interp(t_s, tt, truth[:, 1]))
    lon_t = np.radians(np.interp(t_s, tt, truth[:, 2]))
    M, N = _radii(lat_t)
    dn = (np.radians(np.asarray(lat_deg, float)) - lat_t) * M
    dlon = (np.radians(np.asarray(lon_deg, float)) - lon_t + math.pi) % (2 * math.pi) - math.pi
    de = dlon * N * np.cos(lat_t)
    return np.c_[dn, de], inside


def up_errors_m(t_s, alt_m, truth) -> np.ndarray:
    return np.asarray(alt_m, float) - np.interp(np.asarray(t_s, float), truth[:, 0] * 1e-6, truth[:, 3])


def stats(err: np.ndarray) -> dict:
    """RMS, mean, 95th percentile and maximum of error magnitudes (m)."""
    e = np.abs(np.asarray(err, float))
    if e.size == 0:
        return {"n": 0, "rms_m": None, "mean_m": None, "p95_m": None, "max_m": None}
    return {"n": int(e.size), "rms_m": float(np.sqrt(np.mean(e ** 2))), "mean_m": float(np.mean(e)),
            "p95_m": float(np.percentile(e, 95)), "max_m": float(np.max(e))}


def score_against_truth(ours_t_s, ours_lat_deg, ours_lon_deg, ours_alt_m, truth, reference=None,
                        reference_name: str = "autopilot EKF") -> dict:
    """Horizontal (and vertical) errors of our trajectory and of ``reference`` (same row layout
    as ``truth``, e.g. EKF3's POS) against ``truth`` over our span.  Returns a JSON-able dict."""
    ours_t_s = np.asarray(ours_t_s, float)
    out: dict = {"truth_samples": int(len(truth))}
    if len(ours_t_s) == 0 or len(truth) < 2:
        out["ours"] = stats(np.zeros(0))
        return out
    ne, inside = ne_errors_m(ours_t_s, ours_lat_deg, ours_lon_deg, truth)
    t0, t1 = float(ours_t_s[inside].min(initial=math.inf)), float(ours_t_s[inside].max(initial=-math.inf))
    out["span_boot_s"] = [t0, t1]
    out["ours"] = {"horizontal": stats(np.hypot(ne[inside, 0], ne[inside, 1])),
                   "vertical": stats(up_errors_m(ours_t_s[inside], np.asarray(ours_alt_m)[inside], truth))}
    if reference is not None and len(reference):
        rt = reference[:, 0] * 1e-6
        sel = (rt >= t0) & (rt <= t1)
        rne, rin = ne_errors_m(rt[sel], reference[sel, 1], reference[sel, 2], truth)
        out["reference_name"] = reference_name
        out["reference"] = {"horizontal": stats(np.hypot(rne[rin, 0], rne[rin, 1])),
                            "vertical": stats(up_errors_m(rt[sel][rin], reference[sel, 3][rin], truth))}
        a, b = out["ours"]["horizontal"]["rms_m"], out["reference"]["horizontal"]["rms_m"]
        out["ours_at_or_below_reference"] = bool(a is not None and b is not None and a <= b)
    return out


def format_score(score: dict, truth_name: str = "truth") -> list[str]:
    """Printable lines of :func:`score_against_truth`'s result."""
    lines = []
    span = score.get("span_boot_s")
    if span is None:
        return [f"against {truth_name}: no solution inside the truth's span"]
    def row(name, s):
        h, v = s["horizontal"], s["vertical"]
        return (f"  {name:<22} horizontal RMS {h['rms_m']:.3f} m (p95 {h['p95_m']:.3f}, max {h['max_m']:.3f}; "
                f"n {h['n']})   vertical RMS {v['rms_m']:.3f} m")
    lines.append(f"against {truth_name}, boot time {span[0]:.1f}-{span[1]:.1f} s (forward filter only):")
    lines.append(row("ours", score["ours"]))
    if "reference" in score:
        lines.append(row(score["reference_name"], score["reference"]))
        lines.append("  ours at or below the reference: " + ("yes" if score["ours_at_or_below_reference"] else "NO"))
    return lines


__all__ = ["ne_errors_m", "up_errors_m", "stats", "score_against_truth", "format_score"]
