"""``companion gnss --mode rtk``: the rover (RINEX or a u-blox capture) and the base (RINEX, an
RTCM 3 capture or a u-blox capture; its position given, in the file, or ``--base-xyz spp``) read,
the systems chosen (``--sys`` auto adds GLONASS where its integers can be fixed),
:func:`companion.gnss.rtk_post.solve_rtk_epochs` run, and the summary, JSON, ``.pos``, tracks and
plot written as the SPP / DGPS modes write theirs (:mod:`companion.gnss.postprocess`)."""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np

from ..io.capture_format import is_receiver_capture, is_rtcm_capture, is_ubx_capture
from ..messages import SECONDS_PER_WEEK, BaseStationPosition, GpsEphemeris
from ..nav.earth import C_n_e, ecef_to_geodetic, ecef_to_ned
from .ephemeris_store import EphemerisStore
from .pos_format import gpst_calendar, write_pos
from .postprocess import (GnssProcessingError, base_files, epoch_progress, epochs_of, files_label, in_window,
                          load_ubx_capture, median_spp_position, parse_systems, parse_xyz, read_navigation,
                          rover_files, satellites_by_system, say_reading_notes, statistics, time_window, write_plot,
                          write_tracks)
from .antenna_calibration import antenna_key
from .rinex import read_rinex_nav_header_iono
from .rinex_obs import read_rinex_obs_files
from .rtk import RtkConfig
from .rtk_post import RTK_POST_SYSTEMS, check_epochs, glonass_ar_of, pos_records, solve_rtk_epochs
from ..rtk_signals import RTK_FIRST_SIGNALS


def _rtk_base(paths: list[str], systems: str, week: int, t_gps_window: tuple[float, float] | None = None):
    """(header, epochs, ephemerides, Klobuchar or None) of an RTK base: RINEX observation files of
    one station (read as one), a u-blox capture (as a rover's: no position in it), or an RTCM 3
    capture (MSM4-7 or 1004/1012 observations, the 1005/1006 antenna reference point as its
    position, broadcast ephemerides, GLONASS's 1020 too, the 1033 receiver type) decoded as the
    service decodes its NTRIP stream;
    ``week``: the GPS week of the rover's first epoch (MSM carries the time of week only);
    ``t_gps_window``: the span a RINEX base is read over (the rover's)."""
    path = paths[0]
    if is_ubx_capture(path):
        return _ubx_epochs(path, systems, "base")
    if not is_rtcm_capture(path):
        hdr, epochs = read_rinex_obs_files(paths, systems, t_gps_window)
        return hdr, epochs, [], None
    from ..io.rtcm import decode_rtcm_file          # the RTCM stack only when a capture is read
    try:
        msgs, dec = decode_rtcm_file(str(path), week_hint=week)
    except (ValueError, IndexError) as exc:
        raise GnssProcessingError(f"cannot decode the RTCM capture {path}: {exc}") from exc
    epochs = epochs_of(msgs, systems, "base")
    arp = [m.r_e for m in msgs if isinstance(m, BaseStationPosition)]
    if not epochs:
        raise GnssProcessingError(f"no base observations of the selected systems ({systems}) in {path} "
                                  f"(MSM4-7 or 1004/1012 expected)")
    # the receiver type a 1033 names decides GLONASS's integers as a RINEX header's would
    desc = dec.base_descriptor
    hdr = {"approx_position_e": np.asarray(arp[-1], float) if arp else None, "antenna_delta_hen_m": None,
           "obs_types": {}, "receiver": desc.receiver if desc else None, "rtcm_descriptor": desc,
           "antenna": (desc.antenna or None) if desc else None}    # (1007/1008/1033: for --antennas)
    glonass = list(dec.glonass_history.values()) if "R" in systems else []
    return hdr, epochs, [m for m in msgs if isinstance(m, GpsEphemeris) and m.sat[0] in systems] + glonass, None


def _rtk_rover(paths: list[str], systems: str, window: tuple[float, float] | None = None):
    """(header, epochs, ephemerides, Klobuchar or None) of an RTK rover: RINEX observation files of
    one receiver (read as one), or a u-blox capture; ``window`` (GPS s): ``--start`` / ``--end``."""
    name = " ".join(map(str, paths))
    if not is_receiver_capture(paths[0]):
        hdr, epochs = read_rinex_obs_files(paths, systems, window, moving=True)
        return hdr, in_window(epochs, window, name, hdr), [], None
    hdr, epochs, ephs, klob = _ubx_epochs(paths[0], systems, "rover")
    return hdr, in_window(epochs, window, name), ephs, klob


def _ubx_epochs(path: str, systems: str, source: str):
    """(header, epochs, ephemerides, Klobuchar) of a u-blox capture: RXM-RAWX observations as the
    service decodes them, RXM-SFRBX ephemerides."""
    store = EphemerisStore()
    hdr, epochs, klob = load_ubx_capture(path, systems, store, source=source)
    if not epochs:
        raise GnssProcessingError(f"no RXM-RAWX epoch of the selected systems ({systems}) in {path}")
    return hdr, epochs, [e for sat in store.sats for e in store.all(sat)], klob


def _base_from_spp(base, ephs, systems: str, klobuchar) -> np.ndarray:
    """``--base-xyz spp``: the base's position from its own single-point solutions (the median;
    metres off, which the rover's absolute positions inherit while the baseline does not)."""
    store = EphemerisStore([e for e in ephs if isinstance(e, GpsEphemeris)])
    kepler = "".join(c for c in systems if c in "GECJ")
    r, n, sd = median_spp_position(base, store, kepler, klobuchar)
    print(f"base position from its own {n} single-point solutions (median, {kepler}): "
          f"{r[0]:.3f},{r[1]:.3f},{r[2]:.3f} (spread north/east/down {sd[0]:.1f}/{sd[1]:.1f}/{sd[2]:.1f} m); "
          f"the rover positions carry its error, the baseline does not")
    return r


def _auto_rtk_systems(cfg, hr: dict, hb: dict) -> str:
    """``--sys`` auto for RTK: the configured systems (G, E, C, J), and GLONASS when its integers
    can be fixed (``--glonass-ar`` on, or auto with one receiver model at both ends): as a float
    it cost fixes between two makes (README)."""
    with_r = "".join(c for c in RTK_POST_SYSTEMS if c in cfg.systems + "R")
    return with_r if glonass_ar_of(dataclasses.replace(cfg, systems=with_r), hr, hb)[0].glonass_ar == "on" \
        else cfg.systems


def _check_demo5_inputs(args) -> None:
    """``--against-demo5`` before any processing: demo5 installed, and RINEX files for it to read."""
    from .demo5_reference import require_demo5
    require_demo5()
    captures = [p for p in (*rover_files(args), *base_files(args)) if is_receiver_capture(p) or is_rtcm_capture(p)]
    if captures or not args.nav:
        raise GnssProcessingError("--against-demo5 needs RINEX rover and base files and --nav (demo5 is given the "
                                  "same files; " + (f"{', '.join(captures)} is a capture" if captures
                                                    else "no --nav given") + ")")


def _against_demo5(args, sols, info: dict, cfg: RtkConfig, direction: str, truth):
    """RTKLIB demo5 on the same files with this run's options, compared epoch by epoch: printed,
    returned (the JSON summary's entry, demo5's run), its solutions beside ``--pos``."""
    from .demo5_reference import compare, run_demo5
    print("running RTKLIB demo5 on the same files ...", flush=True)
    try:
        theirs = run_demo5(rover_files(args), base_files(args), args.nav, info["base_antenna_e"],
                           rover_antenna_delta_hen=info["rover_antenna_delta_hen_m"], systems=cfg.systems,
                           mask_deg=args.elevation_mask_deg, direction=direction,
                           frequencies="l1" if getattr(args, "freq", None) == "l1" else "l1+l2",
                           static=cfg.dynamics == "static", iono="est" if cfg.iono_states else "off",
                           antennas=getattr(args, "antennas", None),
                           antenna_types={who: a["entry"] for who, a in info["antennas"].items() if a["calibration"]},
                           glonass_ar="on" if info["glonass_ar"].startswith("on") else "off")
    except RuntimeError as exc:
        raise GnssProcessingError(str(exc)) from exc
    c = compare(sols, theirs, truth)
    print(c.line())
    if args.pos:
        demo5_pos = Path(args.pos).with_suffix(".demo5.pos")
        demo5_pos.write_text(theirs.pos_text)
        print(f"demo5's solutions: {demo5_pos}")
    return c.summary(), theirs


def _antenna_options(args) -> dict:
    """``--antennas`` / ``--rover-antenna`` / ``--base-antenna`` as solve_rtk_epochs' keywords."""
    names = {"rover_antenna": getattr(args, "rover_antenna", None), "base_antenna": getattr(args, "base_antenna", None)}
    path = getattr(args, "antennas", None)
    if path is None:
        if any(names.values()):
            raise GnssProcessingError("--rover-antenna / --base-antenna name a type in a calibration file: give "
                                      "--antennas FILE (ANTEX or NGS ant_info)")
        return {}
    if not Path(path).is_file():
        raise GnssProcessingError(f"file not found: {path}")
    return {"antennas": path, **names}


def _antenna_text(a: dict) -> str:
    """One receiver's antenna as the .pos header and the terminal say it."""
    if not a["calibration"]:
        return f"{a['type'] or 'no type'} ({'; '.join(a['notes']) or 'phase centres taken at the ARP'})"
    return f"{a['type']} (calibrated" + (f"; {', '.join(a['notes'])})" if a["notes"] else ")")


def _antenna_hint(rover_type: str | None, base_type: str | None) -> str | None:
    """Without --antennas, two different antenna types named: what it costs and what corrects it."""
    named = [t for t in (rover_type, base_type) if t and t.strip() and t.strip().upper() != "UNKNOWN"]
    if len(named) < 2 or antenna_key(named[0]) == antenna_key(named[1]):
        return None
    return (f"antennas: rover {rover_type}, base {base_type}, both phase centres taken at their reference points: "
            f"the heights carry their offsets (centimetres to a decimetre; --antennas igs20.atx calibrates them)")


def _antennas_line(antennas: dict, path: str) -> str:
    return f"antennas ({Path(path).name}): " + "; ".join(f"{who} {_antenna_text(a)}" for who, a in antennas.items())


def _fix_statistics(sols) -> tuple[dict, str]:
    """How the fixes came: the share, the first one's time from the start, the longest run of
    epochs without one (and when it began)."""
    fixed = [s.quality == 1 for s in sols]
    first = next((s.t_gps - sols[0].t_gps for s, f in zip(sols, fixed) if f), None)
    run = best = 0
    best_start = None
    for k, f in enumerate(fixed):
        run = 0 if f else run + 1
        if run > best:
            best, best_start = run, sols[k - run + 1].t_gps
    out = {"fix_rate": sum(fixed) / len(sols), "first_fix_s": first, "longest_unfixed_epochs": best}
    line = (f"fix: {100 * out['fix_rate']:.1f} % of the epochs"
            + (", none" if first is None else ", from the first epoch" if first == 0
               else f", the first {first:g} s after the start")
            + (f"; longest run without one: {best} epoch{'s' if best > 1 else ''} from {gpst_calendar(best_start)[11:19]}"
               if best and first is not None else ""))
    return out, line


def _static_result(last, n_epochs: int, truth) -> tuple[dict, str]:
    """``--static``: the last epoch's position (every epoch in it) as a survey result: the JSON
    entry and the line printed."""
    lat, lon, h = ecef_to_geodetic(last.r_e)
    C = C_n_e(lat, lon)
    sigma_ned = np.sqrt(np.maximum(np.diag(C.T @ last.cov_e @ C), 0.0))
    out = {"r_e": [float(v) for v in last.r_e], "lat_deg": math.degrees(lat), "lon_deg": math.degrees(lon),
           "height_m": float(h), "sigma_ned_m": [float(v) for v in sigma_ned], "fixed": last.quality == 1,
           "epochs": n_epochs}
    line = (f"static: {last.r_e[0]:.4f},{last.r_e[1]:.4f},{last.r_e[2]:.4f} (lat {math.degrees(lat):.9f}, "
            f"lon {math.degrees(lon):.9f}, h {h:.4f} m), sigma north/east/down "
            + "/".join(f"{1000 * v:.1f}" for v in sigma_ned) + f" mm, {'fixed' if last.quality == 1 else 'float'}, "
            f"from {n_epochs} epochs")
    if truth is not None:
        out["error_ned_m"] = [float(v) for v in ecef_to_ned(last.r_e, truth)]
        line += f"; {1000 * np.linalg.norm(last.r_e - truth):.1f} mm from --truth-xyz"
    return out, line


#: beyond this baseline the differential ionosphere, unless estimated (--iono est), is 1-3 cm
#: (1-2 ppm) and more at low elevation: enough to pull the float ambiguities onto wrong integers,
#: decimetres off (README: the 15-km car)
LONG_BASELINE_M = 10e3


def _baseline(sols, base_antenna_e, iono_est: bool) -> tuple[dict, str]:
    """(the JSON's 'baseline_m': median and max rover-base distance, the line for the terminal);
    a baseline over :data:`LONG_BASELINE_M` without the ionosphere estimated is said to be one."""
    d = np.linalg.norm(np.array([s.r_e for s in sols]) - np.asarray(base_antenna_e, float), axis=1)
    out = {"median": float(np.median(d)), "max": float(d.max())}
    line = f"baseline: {out['median'] / 1e3:.2f} km (median), {out['max'] / 1e3:.2f} km at most"
    if iono_est:
        line += "; the differential ionosphere estimated (--iono est)"
    elif out["max"] > LONG_BASELINE_M:
        line += (f"; over {LONG_BASELINE_M / 1e3:g} km the differential ionosphere, not estimated here, can make "
                 "a fix wrong by decimetres: --direction combined leaves fixes the two passes disagree on float, "
                 "--iono est estimates it (fixes then need longer unbroken tracking)")
    return out, line


def run_rtk(args) -> int:
    """``--mode rtk``: kinematic L1+L2 RTK against the base file (companion.gnss.rtk_post)."""
    bases = base_files(args)
    rovers = rover_files(args)
    for p in [*rovers, *(args.nav or []), *bases]:
        if not Path(p).is_file():
            raise GnssProcessingError(f"file not found: {p}")
    if not args.nav and not is_ubx_capture(rovers[0]) and not (len(bases) == 1 and (is_rtcm_capture(bases[0])
                                                                                    or is_ubx_capture(bases[0]))):
        raise GnssProcessingError("--mode rtk needs --nav (a u-blox .ubx capture or an RTCM 3 base can bring the "
                                  "ephemerides)")
    if not bases:
        raise GnssProcessingError("--mode rtk needs --base")
    against_demo5 = getattr(args, "against_demo5", False)
    if against_demo5:
        _check_demo5_inputs(args)
    base_spp = (args.base_xyz or "").strip().lower() == "spp"
    base_xyz = parse_xyz(args.base_xyz, "--base-xyz") if args.base_xyz and not base_spp else None
    truth = parse_xyz(args.truth_xyz, "--truth-xyz") if args.truth_xyz else None
    freq = getattr(args, "freq", None)
    if freq == "if":
        raise GnssProcessingError("--freq if is for spp/dgps: rtk differences each frequency's own carrier "
                                  "(both by default; --freq l1 for the first alone)")
    static = bool(getattr(args, "static", False))
    cfg = RtkConfig(elevation_mask_deg=args.elevation_mask_deg, glonass_ar=getattr(args, "glonass_ar", "auto"),
                    dynamics="static" if static else "kinematic", iono_states=getattr(args, "iono", "off") == "est",
                    **({"signals": RTK_FIRST_SIGNALS} if freq == "l1" else {}))
    freqs = "L1" if freq == "l1" else "L1+L2"
    direction = getattr(args, "direction", "forward")
    if static and direction != "forward":
        raise GnssProcessingError("--static: forward only (its last epoch already uses every epoch)")
    wanted = parse_systems(getattr(args, "sys", None), RTK_POST_SYSTEMS)
    if wanted:
        cfg = dataclasses.replace(cfg, systems=wanted)
    try:
        hr, rover, ephs, klob = _rtk_rover(rovers, wanted or RTK_POST_SYSTEMS, time_window(args))
        if not rover:
            raise GnssProcessingError(f"no observation epochs in {' '.join(rovers)}")
        # a base file of hours for a rover of minutes: only the rover's span (and a base age) is read
        span = (rover[0].t_gps - cfg.max_base_age_s, rover[-1].t_gps + cfg.max_base_age_s)
        hb, base, base_ephs, base_klob = _rtk_base(bases, wanted or RTK_POST_SYSTEMS,
                                                   int(rover[0].t_gps // SECONDS_PER_WEEK), span)
        check_epochs(rover, hb, base)
        notes = {who: note for who, h, label in (("rover", hr, "rover files" if len(rovers) > 1 else "rover file"),
                                                  ("base", hb, "base files" if len(bases) > 1 else "base file"))
                 if (note := say_reading_notes(label, h))}
        if not wanted:
            cfg = dataclasses.replace(cfg, systems=_auto_rtk_systems(cfg, hr, hb))
        ephs = [e for e in ephs + base_ephs if e.sat[0] in cfg.systems]
        for p in args.nav or []:
            ephs += read_navigation(p, cfg.systems)
        if not ephs and not args.nav:
            raise GnssProcessingError(f"no ephemeris of the selected systems ({cfg.systems}): neither capture "
                                      f"brings them (RXM-SFRBX, RTCM 1019/1042/1044/1045/1046); give --nav")
        if base_spp:
            navs_klob = next((k for k in map(read_rinex_nav_header_iono, args.nav or []) if k), None)
            base_xyz = _base_from_spp(base, ephs, cfg.systems, base_klob or klob or navs_klob)
        # an RTK epoch costs milliseconds (tens with four systems): a minute of 1-Hz data is worth a progress line
        sols, info = solve_rtk_epochs(hr, rover, hb, base, ephs, base_xyz=base_xyz, config=cfg,
                                      progress=epoch_progress("rtk", min_epochs=60), direction=direction,
                                      **_antenna_options(args))
    except (ValueError, IndexError) as exc:
        raise GnssProcessingError(str(exc)) from exc
    if not sols:
        raise GnssProcessingError(f"no epoch could be solved ({info['paired_epochs']} rover/base epoch pairs; "
                                  f"{info['counters']})")
    n_fix = sum(1 for s in sols if s.quality == 1)
    by_sys = satellites_by_system(sols)
    summary = {"mode": "rtk", "direction": direction, "signals": list(cfg.signals), "epochs": info["rover_epochs"],
               "paired_epochs": info["paired_epochs"], "solved": len(sols), "fixed": n_fix,
               "elevation_mask_deg": args.elevation_mask_deg, "systems": cfg.systems,
               "satellites_by_system": by_sys, "base_epochs": info["base_epochs"],
               "max_base_age_s": info["max_base_age_s"], "base_antenna_e": info["base_antenna_e"],
               "glonass_ar": info["glonass_ar"], "counters": info["counters"], "reading_notes": notes}
    if truth is not None:
        summary.update(statistics(sols, truth))
        fixed = [s for s in sols if s.quality == 1]
        if fixed:
            summary["fixed_stats"] = statistics(fixed, truth)
    solution = ("static" if static else direction) + (", L1" if freqs == "L1" else "")
    print(f"companion gnss rtk ({solution}): {len(sols)}/{info['paired_epochs']} epochs solved, {n_fix} fixed"
          + (f", RMS 3-D {summary['rms_3d_m']:.4f} m, horizontal {summary['rms_h_m']:.4f} m, "
             f"95% 3-D {summary['p95_3d_m']:.4f} m, max {summary['max_3d_m']:.4f} m" if "rms_3d_m" in summary else ""))
    if info["max_base_age_s"] >= 0.05:           # (a few microseconds apart: one epoch)
        print(f"base: {info['base_epochs']} epochs, each rover epoch solved against the nearest one, up to "
              f"{info['max_base_age_s']:.1f} s apart (at most {cfg.max_base_age_s:g} s)")
    print("satellites per epoch (common to rover and base, above the mask): "
          + ", ".join(f"{c} {v['mean']:.1f} ({v['min']}-{v['max']})" for c, v in by_sys.items()))
    glonass_used = bool(info["glonass_ar"]) and "R" in by_sys     # (decided for files with no GLONASS too)
    if glonass_used:
        print(f"GLONASS integers: {info['glonass_ar']}")
    fix_stats, line = _fix_statistics(sols)
    summary.update(fix_stats)
    print(line)
    summary["baseline_m"], line = _baseline(sols, info["base_antenna_e"], cfg.iono_states)
    summary["ionosphere"] = "estimated" if cfg.iono_states else "not modelled"
    print(line)
    if info["antennas"]:
        summary["antennas"] = info["antennas"]
        print(_antennas_line(info["antennas"], args.antennas))
    elif (hint := _antenna_hint(hr.get("antenna"), hb.get("antenna"))) is not None:
        print(hint)
    if static:
        summary["static_position"], line = _static_result(sols[-1], len(sols), truth)
        print(line)
    if hb.get("rtcm_descriptor") is not None:
        print(f"base: {hb['rtcm_descriptor'].line()}")
        summary["base_descriptor"] = hb["rtcm_descriptor"].as_dict()
    demo5_fixed = None
    if against_demo5:
        summary["against_demo5"], theirs = _against_demo5(args, sols, info, cfg, direction, truth)
        demo5_fixed = ("demo5", [t for t, _ in theirs.fixed], [r for _, r in theirs.fixed])
    if args.json:
        rows = [{"t_gps": s.t_gps, "r_e": [float(x) for x in s.r_e], "q": s.quality, "ns": s.n_sats,
                 "ratio": s.ratio, "n_fixed": s.n_fixed, "n_ambiguities": s.n_ambiguities,
                 "n_sats_by_system": s.n_sats_by_system, "age_s": s.age_s,
                 **({"err_ned_m": [float(x) for x in ecef_to_ned(s.r_e, truth)]} if truth is not None else {})}
                for s in sols]
        with open(args.json, "w") as fh:
            json.dump({**summary, "solutions": rows}, fh, indent=1)
    records = pos_records(sols)
    write_tracks(args, records, f"companion gnss rtk: {files_label(rovers)}")
    write_plot(args, records, f"companion gnss rtk ({','.join(by_sys) or ','.join(cfg.systems)}, {direction}): "
                              f"{files_label(rovers)}, {n_fix} of {len(sols)} fixed", truth, other=demo5_fixed)
    if args.pos:
        write_pos(args.pos, records, program=f"companion gnss rtk ({freqs}, LAMBDA, fix-and-hold)",
                  inputs=[*rovers, *bases, *(args.nav or [])],
                  options={"pos mode": "static" if static else "kinematic", "freqs": freqs, "solution": direction,
                           "elev mask": f"{args.elevation_mask_deg:.1f} deg",
                           "ionos opt": "estimation" if cfg.iono_states else "off",
                           **{f"antenna{k + 1}": _antenna_text(info["antennas"][who])
                              for k, who in enumerate(("rover", "base")) if who in info["antennas"]},
                           "navi sys": ",".join(by_sys) or ",".join(cfg.systems),   # the systems solved with
                           "amb res": f"fix and hold, ratio {cfg.ratio_threshold:g}"
                                      + (f"; GLONASS {info['glonass_ar'].split()[0]}" if glonass_used else "")})
    return 0


__all__ = ["run_rtk"]
