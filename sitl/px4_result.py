"""The figures of ``python -m sitl px4`` from what its ground station recorded.

Same keys and windows as :mod:`sitl.ardupilot_result` (*ground*: first estimate to arming;
*flight*: takeoff to disarming), and its helpers.  Differences: the truth is SIH's
HIL_STATE_QUATERNION from the display link, mapped to PX4 boot time with ATTITUDE of the same
link; "EKF fuses our estimate" is EKF2's ``cs_ev_pos`` flag (``listener
estimator_status_flags``) in every sample from takeoff to the land command, with GNSS not fused;
failsafes are STATUSTEXTs, PX4 console warnings, a HEARTBEAT state of CRITICAL/EMERGENCY while
armed and any mode change we did not command.
"""
from __future__ import annotations

import numpy as np

from . import ardupilot_score as S
from .ardupilot_result import (
    ekf_position_figures,
    _r,
    boot_time_map,
    our_estimates,
    position_figures,
    yaw_figures,
)
from .px4_gcs import mode_name

OUTPUT = "vision"
CONSOLE_FAILSAFE_WORDS = ("failsafe", "emergency", "navigation error", "position estimate invalid")


def truth_from(records) -> S.Truth:
    """SIH truth as a function of PX4 boot time (``time_usec`` of HIL_STATE_QUATERNION is 0)."""
    att = records.get("DISPLAY_ATTITUDE", ())
    hil = records.get("HIL_STATE_QUATERNION", ())
    # 1 s windows: PX4's simulated clock runs at ~0.99x wall time, so a long window would bias
    # the offset floor by the drift within it (5 s x 1 % = 50 ms = 25 cm at 5 m/s)
    att_recv = np.array([t for t, _ in att])
    att_boot = np.array([m.time_boot_ms * 1e-3 for _, m in att])
    off = S.boot_offset(att_recv, att_boot, window_s=1.0)
    t_recv = np.array([t for t, _ in hil])
    t_boot = t_recv - off(t_recv)
    # when the harness is busy, datagrams wait in the socket and are read in a burst: their
    # receive times are late.  PX4 sends the link's messages in order, so a truth sample is no
    # newer than the ATTITUDE read after it (its own time stamp; +1 SIH step) and no older than
    # the one read before it
    k = np.searchsorted(att_recv, t_recv)
    after = np.where(k < len(att_boot), att_boot[np.minimum(k, len(att_boot) - 1)] + 0.004, np.inf)
    before = np.where(k > 0, att_boot[np.maximum(k - 1, 0)], -np.inf)
    t_boot = np.clip(t_boot, before, np.maximum(before, after))
    return S.Truth(t_boot, [m.lat for _, m in hil], [m.lon for _, m in hil],
                   [S.quat_yaw(m.attitude_quaternion) for _, m in hil])


def ekf_flag_figures(flag_samples, window) -> dict:
    """EKF2 control status during ``window`` (boot s): share of samples with each flag set."""
    names = ("cs_ev_pos", "cs_ev_hgt", "cs_ev_yaw", "cs_gps", "cs_mag_hdg", "cs_mag_3d", "cs_baro_hgt",
             "cs_inertial_dead_reckoning")
    sel = [f for t, f in flag_samples if window is not None and window[0] <= t <= window[1]]
    out = {"ekf_flag_samples_flight": len(sel),
           "ekf_flags_flight": {n: _r(np.mean([bool(f.get(n)) for f in sel]), 2) if sel else None for n in names}}
    out["ext_nav_used"] = len(sel) >= 2 and all(f.get("cs_ev_pos") and not f.get("cs_gps") for f in sel)
    return out


def gps_raw_best_lag_s(records, truth, ref_e7, window, lags_s=np.arange(-0.2, 0.2001, 0.01)):
    """The shift of GPS_RAW_INT's ``time_usec`` that best fits the truth in flight (the receiver's
    output latency if positive), or None: what ``gnss.gps_raw_latency_s`` should be."""
    g = [m for _, m in records.get("GPS_RAW_INT", ()) if m.fix_type >= 3]
    if window is None or len(g) < 10:
        return None
    t = np.array([m.time_usec for m in g]) * 1e-6
    sel = S.in_window(t, window)
    if np.count_nonzero(sel) < 10:
        return None
    ne = S.ned_from_latlon_e7([m.lat for m in g], [m.lon for m in g], *ref_e7)[sel]
    r = [S.rms(S.horizontal_errors(t[sel] - lag, ne, truth, *ref_e7)[1]) for lag in lags_s]
    return _r(lags_s[int(np.argmin(r))], 2)


def failsafes(texts, console_lines, states, modes, commanded) -> list[str]:
    """Everything that reports a failsafe; ``modes``: [(t, custom_mode, armed)] as PX4 reported them,
    ``commanded``: [(t, custom_mode)] we asked for."""
    out = list(S.failsafes(texts))
    out += [f"console: {line.strip()}" for line in console_lines
            if any(w in line.lower() for w in CONSOLE_FAILSAFE_WORDS)]
    out += [f"state {s} while armed" for t, s, armed in states if armed and s >= 5]   # CRITICAL, EMERGENCY
    allowed = {cm for _, cm in commanded}
    t_first = commanded[0][0] if commanded else np.inf
    out += [f"mode changed to {mode_name(cm)} by the autopilot" for t, cm, armed in modes
            if armed and t > t_first and cm not in allowed]
    return out


def score(records, statustext, res: dict, *, flag_samples, console_lines, states, modes, commanded) -> dict:
    texts = [t for _, t in statustext]
    out: dict = {"statustext": texts, "failsafes": failsafes(texts, console_lines, states, modes, commanded),
                 "armed": res.get("armed", False), "ext_nav_used": False, "rms_h_m": None,
                 "max_error_h_m": None, "yaw_rms_deg_ground": None, "ekf_rms_h_m": None}
    if not records.get("HIL_STATE_QUATERNION") or not records.get("DISPLAY_ATTITUDE") or not records.get("ATTITUDE"):
        out["score_error"] = "no HIL_STATE_QUATERNION/ATTITUDE recorded"
        return out
    truth = truth_from(records)
    to_boot = boot_time_map(records)
    ref = (truth.lat_e7[0], truth.lon_e7[0])
    ev = {k: float(to_boot(v)) for k, v in res.get("events_mono_s", {}).items()}
    flight = (ev["takeoff"], ev["disarmed"]) if "takeoff" in ev and "disarmed" in ev else None
    airborne = (ev["takeoff"], ev.get("land", ev["disarmed"])) if flight else None
    ground_end = ev.get("armed", ev.get("disarmed", np.inf))
    out.update(ekf_flag_figures([(float(to_boot(t)), f) for t, f in flag_samples], airborne))
    co = res.get("companion_origin")
    origin_e7 = (round(co[0] * 1e7), round(co[1] * 1e7)) if co else None
    est = records.get("VISION_POSITION_ESTIMATE", ())
    recv = [t for t, _ in est]
    out["estimates_received"] = len(recv)
    t_last = records["HIL_STATE_QUATERNION"][-1][0]
    out["estimate_rate_hz_run"] = round((len(recv) - 1) / (t_last - recv[0]), 2) if len(recv) > 1 else None
    # the rate EKF2 flew on (takeoff to touchdown): PX4 SITL may step its UTC clock once disarmed
    # (seen: +5.8 s after a landing under load), a time jump the companion re-initialises on
    if airborne is not None:
        t_recv_boot = to_boot(np.array(recv)) if recv else np.array([])
        n_air = int(np.count_nonzero((t_recv_boot >= airborne[0]) & (t_recv_boot <= airborne[1])))
        out["estimate_rate_hz"] = round(n_air / (airborne[1] - airborne[0]), 2)
    else:
        out["estimate_rate_hz"] = None
    if recv:
        # stamp (IMU sample time) to arrival here, both in PX4 boot time: our output latency
        lat = to_boot(np.array(recv)) - np.array([m.usec for _, m in est]) * 1e-6
        out["estimate_latency_ms"] = {"median": _r(1e3 * np.median(lat), 1), "p95": _r(1e3 * np.percentile(lat, 95), 1)}
    if recv and origin_e7 is not None:
        t, ne, yaw = our_estimates(records, OUTPUT, ref, origin_e7)
        out.update(position_figures(t, ne, truth, ref, flight, ground_end))
        out.update(yaw_figures(t, yaw, truth, flight, ground_end))
    out["gps_raw_best_lag_s"] = gps_raw_best_lag_s(records, truth, ref, airborne)
    att = records["ATTITUDE"]
    ekf_yaw = yaw_figures(np.array([m.time_boot_ms for _, m in att]) * 1e-3, [m.yaw for _, m in att], truth,
                          flight, ground_end)
    out["ekf_yaw_rms_deg_ground"] = ekf_yaw["yaw_rms_deg_ground"]
    out["ekf_yaw_rms_deg_flight"] = ekf_yaw["yaw_rms_deg_flight"]
    out.update(ekf_position_figures(records, truth, ref, origin_e7, flight, ground_end))
    return out
