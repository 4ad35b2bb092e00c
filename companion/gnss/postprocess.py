"""`companion gnss`: RTKLIB-style post-processing of RINEX files (SPP, code DGPS or carrier-phase RTK),
or of a u-blox capture (RXM-RAWX + RXM-SFRBX, decoded as the service decodes its receiver) for SPP/DGPS.

Solutions are at the rover's marker and the base antenna is its marker plus the header's
``ANTENNA: DELTA H/E/N``, as RTKLIB applies them; ``--pos`` writes RTKLIB's solution format
(:mod:`companion.gnss.pos_format`: Q 5 single, 4 DGPS, 1 fixed / 2 float RTK) that rtkplot and
pos2kml read; ``--kml`` / ``--gpx`` the same epochs as tracks (:mod:`companion.io.track_export`).
``--mode rtk`` is :mod:`companion.gnss.rtk_cli` (on :mod:`companion.gnss.rtk_post`: L1+L2 double
differences, LAMBDA).

Pipeline per rover epoch: (optional) divergence-free carrier smoothing of rover and base code
(:class:`CarrierSmoother`), base corrections from the latest base epoch at or before the rover
epoch (+0.5 s), then :func:`spp_epoch` (WLS + RAIM FDE, one receiver clock plus an inter-system
bias per extra constellation) on each system's single-frequency code (``--freq l1``: GPS/QZSS L1 C/A,
Galileo E1, BeiDou B1I) or its iono-free pair (``--freq if``).

``--sys`` (default: every one of G, E, C, J with both observations and ephemerides in the files, as a
multi-GNSS receiver's user expects; 'G' reproduces the GPS-only processing) selects the
constellations.  The summary reports the satellites used per epoch by constellation.

Defaults (measured on the GEONET 0759/3040 data, see tests/test_spp_dgps_geonet.py): signal L1C
with Klobuchar + Saastamoinen standalone (the C1/P2 iono-free combination was worse on these files:
its noise is x3 and C1-P1 biases enter it amplified), carrier smoothing on (600 s window).  Without
broadcast Klobuchar coefficients (RINEX converted from RTCM has none) standalone L1 uses RTKLIB's
default ones (:data:`KLOBUCHAR_DEFAULT`) rather than no model (tests/test_spp_multignss.py: GPS
8.29 m without a model, 3.24 m with it).
"""
from __future__ import annotations

import json
import logging
import math
import sys
from struct import error as struct_error
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.capture_format import is_receiver_capture, is_rtcm_capture, is_ubx_capture
from ..messages import BaseStationPosition
from ..nav.earth import ecef_to_geodetic, ecef_to_ned
from .dgps import DgpsCorrector
from .ephemeris_store import EphemerisStore
from .pos_format import Q_DGPS, Q_SINGLE, PosRecord, parse_gpst, span_text, write_pos
from .prepare import CarrierSmoother
from .atmosphere import KLOBUCHAR_DEFAULT
from .rinex import nav_reading_notes, read_rinex_nav, read_rinex_nav_header_iono
from .rinex_obs import read_rinex_obs_files, reading_notes
from .glonass import frequency_channels, with_fdma_wavelengths
from .signals import GLONASS, PREPARED_SYSTEMS, SUPPORTED_SYSTEMS
from .rtk_post import RTK_POST_SYSTEMS, antenna_delta_e, check_epochs
from .spp import SppSolution, spp_epoch

log = logging.getLogger(__name__)


#: ``--freq`` -> the ``signal`` of :func:`companion.gnss.prepare.prepare_epoch`
FREQ_SIGNALS = {"l1": "L1C", "if": "IF"}


class GnssProcessingError(Exception):
    """A user-facing error: bad input files or no usable data."""


@dataclass
class ProcessOptions:
    mode: str = "spp"                     # 'spp' | 'dgps'
    signal: str = "L1C"                   # 'L1C' | 'IF'
    elevation_mask_rad: float = math.radians(10.0)
    smoothing: bool = True
    smoothing_window_s: float = 600.0
    dgps_max_age_s: float = 30.0
    raim: bool = True
    systems: str = "G"                    # constellations used: letters of 'GECJ'


def process(rover_epochs, store: EphemerisStore, opts: ProcessOptions, *, klobuchar=None, base_epochs=None,
            base: BaseStationPosition | None = None, progress=None) -> list[SppSolution | None]:
    """One solution (or None) per rover epoch.  ``progress(i, n)`` is called after each epoch."""
    sm_r = CarrierSmoother(window_s=opts.smoothing_window_s) if opts.smoothing else None
    sm_b = CarrierSmoother(window_s=opts.smoothing_window_s) if opts.smoothing else None
    dg = None
    if opts.mode == "dgps":
        if base_epochs is None or base is None:
            raise GnssProcessingError("DGPS needs base observations and a base position")
        dg = DgpsCorrector(max_age_s=opts.dgps_max_age_s, signal=opts.signal, systems=opts.systems)
    out: list[SppSolution | None] = []
    bi = 0
    r_prev = None
    n = len(rover_epochs)
    for k, ep in enumerate(rover_epochs):
        if sm_r is not None:
            ep = sm_r.apply(ep)
        if dg is not None:
            while bi < len(base_epochs) and base_epochs[bi].t_gps <= ep.t_gps + 0.5:
                b = base_epochs[bi]
                bi += 1
                if sm_b is not None:
                    b = sm_b.apply(b)
                dg.update_base(b, base, store)
        sol = spp_epoch(ep, store, dgps=dg, klobuchar=klobuchar, r_init_e=r_prev, systems=opts.systems,
                        elevation_mask_rad=opts.elevation_mask_rad, signal=opts.signal, raim=opts.raim)
        if sol is None and r_prev is not None:   # retry cold: the previous position may be the problem
            sol = spp_epoch(ep, store, dgps=dg, klobuchar=klobuchar, elevation_mask_rad=opts.elevation_mask_rad,
                            signal=opts.signal, raim=opts.raim, systems=opts.systems)
        if sol is not None:
            r_prev = sol.r_e
        out.append(sol)
        if progress is not None:
            progress(k + 1, n)
    return out


def median_spp_position(epochs, store: EphemerisStore, systems: str, klobuchar=None) -> tuple[np.ndarray, int, np.ndarray]:
    """A receiver's position from its own observations: the median of its single-point solutions
    (carrier-smoothed, RAIM) over ``epochs`` (RTKLIB's "average of single" base position, robust
    to a few bad epochs).  Returns (ECEF m, solutions used, their north/east/down standard
    deviations m); GnssProcessingError when none solves."""
    opts = ProcessOptions(mode="spp", systems=systems, signal="L1C")
    sols = [s for s in process(epochs, store, opts, klobuchar=klobuchar or KLOBUCHAR_DEFAULT) if s is not None]
    if not sols:
        raise GnssProcessingError(f"no single-point solution of the base in {len(epochs)} epochs ({systems}): "
                                  f"give --base-xyz X,Y,Z")
    r = np.array([s.r_e for s in sols])
    med = np.median(r, axis=0)
    return med, len(sols), np.array([ecef_to_ned(x, med) for x in r]).std(axis=0)


def statistics(solutions, truth_e) -> dict:
    """rms_3d_m, rms_h_m, rms_v_m, p95_3d_m, max_3d_m, mean_ned_m over the solved epochs."""
    err = np.array([ecef_to_ned(s.r_e, truth_e) for s in solutions if s is not None])
    if len(err) == 0:
        return {}
    e3 = np.linalg.norm(err, axis=1)
    eh = np.linalg.norm(err[:, :2], axis=1)
    return {"rms_3d_m": float(np.sqrt(np.mean(e3 ** 2))), "rms_h_m": float(np.sqrt(np.mean(eh ** 2))),
            "rms_v_m": float(np.sqrt(np.mean(err[:, 2] ** 2))), "p95_3d_m": float(np.percentile(e3, 95)),
            "max_3d_m": float(np.max(e3)), "mean_ned_m": [float(x) for x in err.mean(axis=0)]}


def parse_xyz(text: str, what: str) -> np.ndarray:
    try:
        v = np.array([float(x) for x in text.replace(" ", "").split(",")])
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise GnssProcessingError(f"{what}: expected 'X,Y,Z' in metres, got {text!r}")
    return v


_SYSTEM_NAMES = {"G": "GPS", "R": "GLONASS", "E": "Galileo", "C": "BeiDou", "J": "QZSS"}


def parse_systems(text: str | None, supported: str = SUPPORTED_SYSTEMS) -> str | None:
    """'G,E,C,J' / 'GECJ' / 'all' -> 'GECJ' (letters of ``supported``, in its order); None or
    'auto' -> None (decided from the files)."""
    if text is None or text.strip().lower() == "auto":
        return None
    if text.strip().lower() == "all":
        return supported
    letters = "".join(c for c in text.upper() if c not in ", ")
    bad = sorted(set(letters) - set(supported))
    if bad or not letters:
        names = ", ".join(_SYSTEM_NAMES.get(c, c) for c in supported)
        raise GnssProcessingError(f"--sys: expected letters of {','.join(supported)} ({names}), got {text!r}"
                                  + (f" ({','.join(bad)} not supported in this mode)" if bad else ""))
    return "".join(c for c in supported if c in letters)


def epochs_of(msgs, systems: str, source: str) -> list:
    """The decoded GnssEpochs among ``msgs``, cut to ``systems`` (epochs left empty dropped), as ``source``."""
    from ..messages import GnssEpoch
    out = []
    for m in msgs:
        if isinstance(m, GnssEpoch):
            obs = tuple(o for o in m.observations if o.sat[0] in systems)
            if obs:
                out.append(GnssEpoch(m.t_gps, obs, source=source))
    return out


def load_ubx_capture(path: str, wanted: str | None, store: EphemerisStore, source: str = "rover"):
    """Observations (RXM-RAWX) and broadcast ephemerides (RXM-SFRBX: GPS/QZSS LNAV, Galileo I/NAV,
    BeiDou D1/D2, GLONASS strings when ``wanted`` names R; added to ``store``) of a u-blox capture,
    decoded as the service decodes its receiver's stream; the epochs tagged as ``source`` ('rover'
    or 'base').  Returns (header-like dict without a marker position or antenna delta, with the
    receiver's model when the capture has UBX-MON-VER, epochs, Klobuchar)."""
    from ..io.capture_format import is_dataflash_log
    from ..io.ubx import UbxDecoder, decode_ubx_file
    from ..messages import GpsEphemeris
    from .glonass import GlonassEphemeris
    try:
        if is_dataflash_log(path):       # an ArduPilot log's RXM-RAWX (GRXH/GRXS), rebuilt
            from ..io.dataflash_raw import capture_bytes
            data, counters = capture_bytes(path)
            dec = UbxDecoder()
            msgs = dec.feed(data)
            log.info("%s: RXM-RAWX rebuilt from GRXH/GRXS: %s", path, dict(counters))
        else:
            msgs, dec = decode_ubx_file(str(path))
    except (ValueError, IndexError, struct_error) as exc:
        raise GnssProcessingError(f"cannot decode the u-blox capture {path}: {exc}") from exc
    keep = wanted or SUPPORTED_SYSTEMS
    n_eph = 0
    for m in msgs:
        if isinstance(m, (GpsEphemeris, GlonassEphemeris)) and m.sat[0] in keep:
            store.add(m)
            n_eph += 1
    epochs = epochs_of(msgs, keep, source)
    log.info("%s: %d RXM-RAWX epochs, %d ephemerides from RXM-SFRBX", path, len(epochs), n_eph)
    klob = getattr(getattr(dec, "ephemerides", None), "klobuchar", None)
    # the model decides GLONASS's integers (RTK's --glonass-ar auto: one model at both ends); a
    # capture without MON-VER does not say it ('' = unknown: GLONASS stays float)
    return {"approx_position_e": None, "antenna_delta_hen_m": None, "receiver": dec.receiver_model}, epochs, klob


#: receivers tag epochs a millisecond or so off the second (GEONET's 30.001 s): --start / --end
#: take them within this (RTKLIB's DTTOL)
WINDOW_TOLERANCE_S = 0.025


def read_navigation(path, systems: str) -> list:
    """``read_rinex_nav`` of one ``--nav`` file, saying what it left out."""
    counts: dict = {}
    ephs = read_rinex_nav(path, systems, counts)
    if note := nav_reading_notes(counts):
        print(f"navigation file {path}: {note}")
    return ephs


def say_reading_notes(who: str, hdr: dict) -> str:
    """Print what reading an observation file left out or reordered ('' and nothing printed when
    nothing); ``who``: 'rover file', 'base files'..."""
    note = reading_notes(hdr)
    if note:
        print(f"{who}: {note}")
    return note


def time_window(args) -> tuple[float, float] | None:
    """``--start`` / ``--end`` (GPST) as GPS seconds, widened by :data:`WINDOW_TOLERANCE_S`; None
    when neither is given."""
    start, end = getattr(args, "start", None), getattr(args, "end", None)
    if start is None and end is None:
        return None
    try:
        window = (parse_gpst(start) - WINDOW_TOLERANCE_S if start else -math.inf,
                  parse_gpst(end) + WINDOW_TOLERANCE_S if end else math.inf)
    except ValueError as exc:
        raise GnssProcessingError(f"--start / --end: {exc}") from exc
    if window[0] > window[1]:
        raise GnssProcessingError(f"--start {start} is after --end {end}")
    return window


def in_window(epochs, window, path, hdr: dict | None = None) -> list:
    """The epochs inside ``window`` (all when None); a clear error when none is (the file's span said)."""
    if window is None:
        return epochs
    kept = [e for e in epochs if window[0] <= e.t_gps <= window[1]]
    if not kept:
        span = (hdr or {}).get("file_span_t_gps") or ((epochs[0].t_gps, epochs[-1].t_gps) if epochs else None)
        raise GnssProcessingError(f"no epoch of {path} between --start and --end"
                                  + (f": it covers {span_text(*span)}" if span else ""))
    return kept


def observation_files(args, who: str = "base") -> list[str]:
    """``--rover``'s or ``--base``'s files (``who``): several RINEX files of one receiver, or one
    capture."""
    given = getattr(args, who, None)
    files = [given] if isinstance(given, str) else list(given or [])
    if len(files) > 1 and any(is_receiver_capture(p) or is_rtcm_capture(p) for p in files):
        raise GnssProcessingError(f"--{who}: several files only as RINEX observation files of one "
                                  f"{'station' if who == 'base' else 'receiver'}; a u-blox or RTCM capture is "
                                  "given alone")
    return files


def base_files(args) -> list[str]:
    """``--base``'s files (several RINEX files of one station, or one capture)."""
    return observation_files(args, "base")


def rover_files(args) -> list[str]:
    """``--rover``'s files (several RINEX files of one receiver, or one capture)."""
    return observation_files(args, "rover")


def files_label(paths) -> str:
    """A title's name for observation files: the first file's name, and how many more."""
    return Path(paths[0]).name + (f" and {len(paths) - 1} more" if len(paths) > 1 else "")


def _load(args):
    bases = base_files(args)
    rovers = rover_files(args)
    for p in [*rovers, *(args.nav or []), *bases]:
        if not Path(p).is_file():
            raise GnssProcessingError(f"file not found: {p}")
    wanted = parse_systems(getattr(args, "sys", None), PREPARED_SYSTEMS)   # GLONASS when asked
    store = EphemerisStore()
    klob = None
    ubx_rover = ubx_base = None
    base_is_ubx = args.mode == "dgps" and len(bases) == 1 and is_ubx_capture(bases[0])
    window = time_window(args)
    if is_receiver_capture(rovers[0]):
        ubx_rover = load_ubx_capture(rovers[0], wanted, store)
        klob = ubx_rover[2]
    elif not args.nav and not base_is_ubx:
        raise GnssProcessingError("--nav is required with a RINEX rover file (a u-blox .ubx capture brings "
                                  "its own ephemerides in RXM-SFRBX)")
    if base_is_ubx:
        # its ephemerides join the rover's before the systems are chosen
        ubx_base = load_ubx_capture(bases[0], wanted, store, source="base")
        klob = klob or ubx_base[2]
    for p in args.nav or []:
        try:
            for e in read_navigation(p, wanted or SUPPORTED_SYSTEMS):
                store.add(e)
            klob = klob or read_rinex_nav_header_iono(p)
        except (ValueError, IndexError) as exc:
            raise GnssProcessingError(f"cannot read navigation file {p}: {exc}") from exc
    if len(store) == 0:
        raise GnssProcessingError("no ephemeris of " + (f"the selected systems ({wanted})" if wanted else "GPS, Galileo, "
                                  "BeiDou or QZSS") + (" in the navigation file(s)" if args.nav else
                                                       " in the capture's RXM-SFRBX (give --nav)"))
    if ubx_rover is not None:
        hdr, rover = ubx_rover[0], ubx_rover[1]
    else:
        try:
            hdr, rover = read_rinex_obs_files(rovers, wanted or SUPPORTED_SYSTEMS, window, moving=True)
        except (ValueError, IndexError) as exc:
            raise GnssProcessingError(f"cannot read rover observation file(s) {' '.join(rovers)}: {exc}") from exc
        say_reading_notes("rover files" if len(rovers) > 1 else "rover file", hdr)
    if not rover and window is None:
        raise GnssProcessingError(f"no observation epochs in {' '.join(rovers)}")
    rover = in_window(rover, window, ' '.join(rovers), hdr)
    # default: every supported system that has both observations and ephemerides
    with_eph = {s[0] for s in store.sats}
    observed = {o.sat[0] for ep in rover for o in ep.observations}
    systems = "".join(c for c in (wanted or SUPPORTED_SYSTEMS) if c in with_eph and (c in observed or wanted))
    if not systems:
        raise GnssProcessingError(f"no system has both observations ({''.join(sorted(observed))}) and "
                                  f"ephemerides ({''.join(sorted(with_eph))})")
    base_epochs = base = None
    if args.mode == "dgps":
        if not bases:
            raise GnssProcessingError("--mode dgps needs --base")
        if ubx_base is not None:
            bhdr = ubx_base[0]
            base_epochs = epochs_of(ubx_base[1], systems, "base")     # cut to the systems chosen
        else:
            try:
                # the rover's span and the oldest correction it may use: a base file of hours is not read whole
                age = ProcessOptions.dgps_max_age_s
                bhdr, base_epochs = read_rinex_obs_files(bases, systems,
                                                         (rover[0].t_gps - age, rover[-1].t_gps + age))
            except (ValueError, IndexError) as exc:
                raise GnssProcessingError(f"cannot read base observation file(s) {' '.join(bases)}: {exc}") \
                    from exc
            say_reading_notes("base files" if len(bases) > 1 else "base file", bhdr)
        if args.base_xyz and args.base_xyz.strip().lower() == "spp":
            raise GnssProcessingError("--base-xyz spp: only with --mode rtk (DGPS corrections from a base position "
                                      "metres off shift the rover by as much); give --base-xyz X,Y,Z")
        if args.base_xyz:
            r_b = parse_xyz(args.base_xyz, "--base-xyz")
        elif bhdr["approx_position_e"] is not None:
            r_b = bhdr["approx_position_e"]
        else:
            raise GnssProcessingError("base position unknown: give --base-xyz X,Y,Z (the base file has none: no "
                                      "APPROX POSITION XYZ, or a u-blox capture)")
        r_b = np.asarray(r_b, float)
        base = BaseStationPosition(station_id=0, r_e=r_b + antenna_delta_e(r_b, bhdr.get("antenna_delta_hen_m")))
        try:
            check_epochs(rover, bhdr, base_epochs)          # a base of another day: both spans said
        except ValueError as exc:
            raise GnssProcessingError(str(exc)) from exc
        t_r = {round(e.t_gps) for e in rover}
        if not t_r & {round(e.t_gps) for e in base_epochs}:
            raise GnssProcessingError("no epochs in common between rover and base observations")
    if GLONASS in systems:       # RINEX gives its FDMA observations no wavelength: the channels do
        channels = frequency_channels(e for sat in store.sats if sat[0] == GLONASS for e in store.all(sat))
        rover = with_fdma_wavelengths(rover, channels)
        base_epochs = with_fdma_wavelengths(base_epochs, channels) if base_epochs else base_epochs
    t0, t1 = rover[0].t_gps, rover[-1].t_gps
    if not any(store.select_with_reason(s, 0.5 * (t0 + t1))[0] for s in store.sats) and \
            not any(store.select_with_reason(s, t0)[0] for s in store.sats):
        toes = [e.t_oe_gps for sat in store.sats for e in store.all(sat) if hasattr(e, "t_oe_gps")]
        raise GnssProcessingError(f"no ephemeris valid during the observation period ({span_text(t0, t1)})"
                                  + (f"; the navigation file(s) are of {span_text(min(toes), max(toes))}"
                                     if toes else ""))
    return store, klob, hdr, rover, base_epochs, base, systems


def satellites_by_system(solutions) -> dict[str, dict[str, float]]:
    """system -> {'mean', 'min', 'max'} satellites used per solved epoch (0 where it had none)."""
    solved = [s for s in solutions if s is not None]
    letters = sorted({c for s in solved for c in s.n_sats_by_system}, key=lambda c: RTK_POST_SYSTEMS.find(c) % 99)
    out = {}
    for c in letters:
        n = [s.n_sats_by_system.get(c, 0) for s in solved]
        out[c] = {"mean": float(np.mean(n)), "min": int(min(n)), "max": int(max(n))}
    return out


def epoch_progress(label: str, min_epochs: int):
    """``progress(i, n)`` printing "label: i/n epochs (p %)" to stderr every 5 % of a run of at least
    ``min_epochs`` epochs (one updating line on a terminal, one line per step in a log)."""
    tty = sys.stderr.isatty()

    def progress(i, n):
        if n >= min_epochs and (i % max(1, n // 20) == 0 or i == n):
            print(f"\r{label}: {i}/{n} epochs ({100 * i // n} %)", end="\n" if (i == n or not tty) else "",
                  file=sys.stderr, flush=True)
    return progress


def run(args) -> int:
    """Entry point of `companion gnss`; returns the process exit code."""
    if getattr(args, "plot", None):
        from ..extras import pyplot
        pyplot("companion gnss --plot")          # a missing [plot] extra fails now, not after the processing
    try:
        return _run(args)
    except GnssProcessingError as exc:
        print(f"companion gnss: error: {exc}", file=sys.stderr)
        return 2


def _run(args) -> int:
    if args.mode == "rtk":
        from .rtk_cli import run_rtk
        return run_rtk(args)
    if getattr(args, "direction", "forward") != "forward":
        raise GnssProcessingError(f"--direction {args.direction} applies to --mode rtk (spp and dgps solve each "
                                  f"epoch on its own)")
    if getattr(args, "iono", "off") != "off":
        raise GnssProcessingError(f"--iono {args.iono} applies to --mode rtk (spp uses the broadcast model or, with "
                                  f"--freq if, the iono-free pair; dgps the base's corrections)")
    named = [o for o, a in (("--antennas", "antennas"), ("--rover-antenna", "rover_antenna"),
                            ("--base-antenna", "base_antenna")) if getattr(args, a, None)]
    if named:
        raise GnssProcessingError(f"{', '.join(named)} applies to --mode rtk (the phase centres are millimetres "
                                  f"to centimetres: below what spp and dgps resolve)")
    store, klob, hdr, rover, base_epochs, base, systems = _load(args)
    signal = FREQ_SIGNALS[getattr(args, "freq", None) or "l1"]
    opts = ProcessOptions(mode=args.mode, elevation_mask_rad=math.radians(args.elevation_mask_deg),
                          signal=signal, systems=systems)
    iono = "iono-free" if signal == "IF" else ("DGPS corrections" if args.mode == "dgps" else "Klobuchar (broadcast)")
    if klob is None and signal != "IF" and args.mode == "spp":
        klob, iono = KLOBUCHAR_DEFAULT, "Klobuchar (RTKLIB's default coefficients: none broadcast)"
    truth = parse_xyz(args.truth_xyz, "--truth-xyz") if args.truth_xyz else None
    sols = process(rover, store, opts, klobuchar=klob, base_epochs=base_epochs, base=base,
                   progress=epoch_progress(args.mode, min_epochs=500))
    for s in sols:                          # antenna -> marker
        if s is not None:
            s.r_e = s.r_e - antenna_delta_e(s.r_e, hdr.get("antenna_delta_hen_m"))
    solved = [s for s in sols if s is not None]
    if not solved:
        raise GnssProcessingError(f"no epoch could be solved ({len(rover)} epochs; ephemeris rejections: "
                                  f"{dict(store.rejections)})")
    by_sys = satellites_by_system(sols)
    summary = {"mode": args.mode, "signal": opts.signal, "epochs": len(rover), "solved": len(solved),
               "elevation_mask_deg": args.elevation_mask_deg, "systems": systems, "ionosphere": iono,
               "satellites_by_system": by_sys, "constellations_used": sum(1 for v in by_sys.values() if v["max"] > 0)}
    if truth is not None:
        summary.update(statistics(sols, truth))
    print(f"companion gnss {args.mode}: {len(solved)}/{len(rover)} epochs solved"
          + (f", RMS 3-D {summary['rms_3d_m']:.3f} m, horizontal {summary['rms_h_m']:.3f} m, "
             f"95% 3-D {summary['p95_3d_m']:.3f} m, max {summary['max_3d_m']:.3f} m" if "rms_3d_m" in summary else ""))
    print(f"satellites used per epoch ({opts.signal}, {iono}): "
          + ", ".join(f"{c} {v['mean']:.1f} ({v['min']}-{v['max']})" for c, v in by_sys.items()))
    rows = []
    for s in solved:
        lat, lon, h = ecef_to_geodetic(s.r_e)
        row = {"t_gps": s.t_gps, "r_e": [float(x) for x in s.r_e], "lat_deg": math.degrees(lat),
               "lon_deg": math.degrees(lon), "h_m": h, "clock_bias_m": s.clock_bias_m, "n_sats": s.n_sats,
               "sats": s.sats, "excluded": s.excluded, "pdop": s.pdop, "hdop": s.hdop, "vdop": s.vdop,
               "raim_ok": s.raim_ok, "n_sats_by_system": s.n_sats_by_system, "clock_system": s.clock_system,
               "isb_m": s.isb_m}
        if truth is not None:
            row["err_ned_m"] = [float(x) for x in ecef_to_ned(s.r_e, truth)]
        rows.append(row)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({**summary, "solutions": rows}, fh, indent=1)
    q = Q_DGPS if args.mode == "dgps" else Q_SINGLE
    records = [PosRecord(s.t_gps, s.r_e, s.cov_r_e, q, s.n_sats) for s in solved]
    rovers = rover_files(args)
    write_tracks(args, records, f"companion gnss {args.mode}: {files_label(rovers)}")
    write_plot(args, records, f"companion gnss {args.mode} ({opts.signal}): {files_label(rovers)}", truth)
    if args.pos:
        write_pos(args.pos, records,
                  program=f"companion gnss {args.mode} ({opts.signal})",
                  inputs=[*rovers, *(args.nav or []), *base_files(args)],
                  options={"pos mode": "single" if args.mode == "spp" else "dgps",
                           "elev mask": f"{args.elevation_mask_deg:.1f} deg", "navi sys": ",".join(systems),
                           "ionos opt": iono})
    return 0


def write_plot(args, records, name: str, truth, other=None) -> None:
    """``--plot``: the run as one PNG (companion.gnss.solution_plot); ``other``: another program's
    fixed solutions to draw beside ours (label, GPS times, ECEF positions)."""
    if getattr(args, "plot", None) and records:
        from .solution_plot import plot_solutions
        plot_solutions(args.plot, records, name, truth_e=truth, other=other)


def write_tracks(args, records, name: str) -> None:
    """``--kml`` / ``--gpx``: the epochs of the .pos file as tracks (companion.io.track_export)."""
    kml, gpx = getattr(args, "kml", None), getattr(args, "gpx", None)
    if not (kml or gpx):
        return
    from ..io.track_export import points_from_pos_records, write_gpx, write_kml
    points = points_from_pos_records(records)
    if kml:
        write_kml(kml, points, name)
    if gpx:
        write_gpx(gpx, points, name)
