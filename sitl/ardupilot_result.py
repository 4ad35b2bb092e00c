"""The figures of ``python -m sitl ardupilot`` from what its ground station recorded.

``records``: {message type: [(t_mono_s, message)]} (pymavlink messages, or anything with the same
attributes, e.g. a re-loaded ``records.pkl``); ``statustext``: [(t_mono_s, text)].  Windows:
*ground* from the first estimate to arming, *flight* from the takeoff command to disarming.
"""
from __future__ import annotations

import numpy as np

from . import ardupilot_score as S

ESTIMATE_TYPES = {"vision": "VISION_POSITION_ESTIMATE", "odometry": "ODOMETRY", "gps_input": "GPS_INPUT"}


def _r(x, nd: int = 3):
    return None if x is None else round(float(x), nd)


def boot_time_map(records):
    """t_mono_s -> autopilot boot time, from the boot-stamped ATTITUDE and LOCAL_POSITION_NED."""
    pairs = sorted((t, m.time_boot_ms * 1e-3) for mtype in ("ATTITUDE", "LOCAL_POSITION_NED")
                   for t, m in records.get(mtype, ()))
    recv, boot = np.array(pairs).T
    off = S.boot_offset(recv, boot)
    return lambda t: np.asarray(t, float) - off(t)


def our_estimates(records, output: str, ref_e7, origin_e7):
    """Our estimates as (t_boot_s, NE m about ref_e7, yaw rad or NaN)."""
    recs = [m for _, m in records.get(ESTIMATE_TYPES[output], ())]
    if output == "gps_input":       # absolute: latitude and longitude
        t = np.array([m.time_usec for m in recs]) * 1e-6
        ne = S.ned_from_latlon_e7([m.lat for m in recs], [m.lon for m in recs], *ref_e7)
        return t, ne, np.full(len(recs), np.nan)
    if output == "vision":
        t = np.array([m.usec for m in recs]) * 1e-6
        yaw = np.array([m.yaw for m in recs])
    else:
        t = np.array([m.time_usec for m in recs]) * 1e-6
        yaw = np.array([S.quat_yaw(m.q) for m in recs])
    # NED about the companion's origin -> about ref_e7 (flat Earth about nearby points)
    shift = S.ned_from_latlon_e7([origin_e7[0]], [origin_e7[1]], *ref_e7)[0]
    return t, np.array([[m.x, m.y] for m in recs]).reshape(-1, 2) + shift, yaw


def position_figures(t, ne, truth, ref_e7, flight, ground_end) -> dict:
    te, err = S.horizontal_errors(t, ne, truth, *ref_e7)
    fl = S.in_window(te, flight)
    return {"rms_h_m": _r(S.rms(err[fl])), "max_error_h_m": _r(float(np.max(err[fl])) if np.any(fl) else None),
            "rms_h_m_ground": _r(S.rms(err[te <= ground_end]))}


def yaw_figures(t, yaw, truth, flight, ground_end) -> dict:
    t = np.asarray(t, float)
    ty = t[truth.covers(t)]
    err = S.yaw_errors_deg(t, yaw, truth)
    g = ty <= ground_end
    tg, eg = ty[g], err[g]
    return {"yaw_rms_deg_ground": _r(S.rms(eg), 2),
            # how the heading error develops at rest: RMS per minute
            "yaw_rms_deg_ground_per_min": [_r(S.rms(eg[(tg >= a) & (tg < a + 60.0)]), 2)
                                           for a in np.arange(tg[0], tg[-1], 60.0)] if tg.size else [],
            "yaw_err_deg_ground_last": _r(eg[-1], 2) if eg.size else None,
            "yaw_rms_deg_flight": _r(S.rms(err[S.in_window(ty, flight)]), 2)}


def ext_nav_used(records, texts, output: str) -> bool:
    if output == "gps_input":       # EKF3 on GPS, and GPS2 (ours) has a 3-D fix
        return any("using GPS" in t for t in texts) and any(m.fix_type >= 3 for _, m in records.get("GPS2_RAW", ()))
    return any("using external nav" in t for t in texts)


def score(records, statustext, res: dict, output: str) -> dict:
    texts = [t for _, t in statustext]
    out: dict = {"statustext": texts, "failsafes": S.failsafes(texts),
                 "ext_nav_used": ext_nav_used(records, texts, output), "armed": res.get("armed", False),
                 "rms_h_m": None, "max_error_h_m": None, "yaw_rms_deg_ground": None, "ekf_rms_h_m": None}
    sims = records.get("SIMSTATE", ())
    if not sims or not records.get("ATTITUDE"):
        out["score_error"] = "no SIMSTATE/ATTITUDE recorded"
        return out
    to_boot = boot_time_map(records)
    truth = S.Truth(to_boot([t for t, _ in sims]), [m.lat for _, m in sims], [m.lng for _, m in sims],
                    [m.yaw for _, m in sims])
    ref = (truth.lat_e7[0], truth.lon_e7[0])
    ev = {k: float(to_boot(v)) for k, v in res.get("events_mono_s", {}).items()}
    flight = (ev["takeoff"], ev["disarmed"]) if "takeoff" in ev and "disarmed" in ev else None
    ground_end = ev.get("armed", ev.get("disarmed", np.inf))
    co = res.get("companion_origin")
    origin_e7 = (round(co[0] * 1e7), round(co[1] * 1e7)) if co else None
    # ours
    recv = [t for t, _ in records.get(ESTIMATE_TYPES[output], ())]
    out["estimates_received"] = len(recv)
    t_last = sims[-1][0]        # to the end of the recording: estimates that stop are counted
    out["estimate_rate_hz"] = round((len(recv) - 1) / (t_last - recv[0]), 2) if len(recv) > 1 else None
    if recv and (origin_e7 is not None or output == "gps_input"):
        t, ne, yaw = our_estimates(records, output, ref, origin_e7 or ref)
        out.update(position_figures(t, ne, truth, ref, flight, ground_end))
        if output != "gps_input":
            out.update(yaw_figures(t, yaw, truth, flight, ground_end))
    # the autopilot's own: ATTITUDE yaw, LOCAL_POSITION_NED about the origin it reports
    att = records["ATTITUDE"]
    ekf_yaw = yaw_figures(np.array([m.time_boot_ms for _, m in att]) * 1e-3, [m.yaw for _, m in att], truth,
                          flight, ground_end)
    out["ekf_yaw_rms_deg_ground"] = ekf_yaw["yaw_rms_deg_ground"]
    out["ekf_yaw_rms_deg_ground_per_min"] = ekf_yaw["yaw_rms_deg_ground_per_min"]
    out.update(ekf_position_figures(records, truth, ref, origin_e7, flight, ground_end))
    out["companion_mode_flight"] = companion_modes(records, res.get("events_mono_s", {}))
    return out


def companion_modes(records, events_mono: dict) -> dict:
    """Fractions of the companion's CC_MODE reports (1 tight, 2 loose, 0 none) in flight (takeoff
    to disarm, receive times), {} without reports."""
    a, b = events_mono.get("takeoff"), events_mono.get("disarmed")
    modes = [m.value for t, m in records.get("NAMED_VALUE_FLOAT", ())
             if m.name.rstrip("\x00") == "CC_MODE" and a is not None and b is not None and a <= t <= b]
    names = {1.0: "tight", 2.0: "loose", 0.0: "none"}
    return {names.get(v, str(v)): round(modes.count(v) / len(modes), 3) for v in sorted(set(modes))} if modes else {}


def ekf_position_figures(records, truth, ref, origin_e7, flight, ground_end) -> dict:
    """The autopilot's own position (LOCAL_POSITION_NED about the GPS_GLOBAL_ORIGIN it reports)
    against the truth, and its origin against ours; {} before it reported both."""
    out = {}
    org = records.get("GPS_GLOBAL_ORIGIN", [(None, None)])[-1][1]
    lp = records.get("LOCAL_POSITION_NED", ())
    if org is not None and lp:
        out["ekf_origin_e7"] = (org.latitude, org.longitude)
        if origin_e7 is not None:
            d = S.ned_from_latlon_e7([org.latitude], [org.longitude], *origin_e7)[0]
            out["ekf_origin_minus_ours_m"] = [round(float(x), 3) for x in d]
        shift = S.ned_from_latlon_e7([org.latitude], [org.longitude], *ref)[0]
        ekf = position_figures(np.array([m.time_boot_ms for _, m in lp]) * 1e-3,
                               np.array([[m.x, m.y] for _, m in lp]) + shift, truth, ref, flight, ground_end)
        out["ekf_rms_h_m"], out["ekf_max_error_h_m"] = ekf["rms_h_m"], ekf["max_error_h_m"]
    return out


def companion_figures(field_log_dir) -> dict:
    """From the companion's last health record: whether ArduPilot's GPS_GLOBAL_ORIGIN confirmed the
    origin our outputs use (companion.io.origin) and what its GPS-port probe did
    (companion.io.serial_control); {} without a field log."""
    import json
    from companion.io.fieldlog import read_field_log
    h = None
    try:
        for rec in read_field_log(field_log_dir):
            if rec.kind == "event":
                obj = json.loads(rec.payload)
                if obj.get("event") in ("health", "stop"):
                    h = obj["health"]
    except (OSError, ValueError):
        return {}
    if h is None:
        return {}
    out = {}
    if "origin" in h:
        o = h["origin"]
        out.update({"origin_confirmed": o["confirmed"], "origin_mismatch_m": o["mismatch_m"],
                    "origin_source": o["source"]})
    if "serial_control" in h:
        sc = h["serial_control"]
        out["gps_port"] = {k: sc.get(k) for k in ("state", "probes", "claims", "raw epochs", "autopilot_gps_back_s")}
    return out
