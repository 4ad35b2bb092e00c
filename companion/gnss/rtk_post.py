"""Post-processed RTK from RINEX files: ``companion gnss --mode rtk`` (companion.gnss.rtk on a rover
and a base observation file and their navigation files): GPS, Galileo, BeiDou and QZSS from RINEX 3
(GPS from RINEX 2), and GLONASS with float ambiguities (its ephemerides from a RINEX 3 navigation
file), each system double-differenced within itself.

The base antenna is the base header position (or ``base_xyz``) plus its ``ANTENNA: DELTA H/E/N``;
solutions are reported at the rover's marker (antenna minus the rover's delta), as RTKLIB does.
The first rover epoch is positioned by SPP (the kinematic prior of the first RTK epoch).
Solution types as RTKLIB's: forward, backward (the epochs newest first, :class:`RtkFilter`'s
``backward``) or both passes combined per epoch (:mod:`.rtk_combine`).
"""
from __future__ import annotations

import dataclasses

import numpy as np

from ..nav.earth import C_n_e, ecef_to_geodetic
from .antenna_calibration import read_antenna_file, receiver_antenna
from .ephemeris_store import EphemerisStore
from .pos_format import PosRecord, span_text
from .rinex import read_rinex_nav
from .rinex_obs import read_rinex_obs
from ..rtk_signals import rtk_epoch
from .rtk import RtkConfig, RtkFilter, RtkSolution, pair_epochs
from .rtk_combine import combine
from .spp import spp_epoch


def antenna_delta_e(marker_r_e, delta_hen_m) -> np.ndarray:
    """ECEF offset of the antenna reference point from the marker (RINEX H up, E east, N north)."""
    if delta_hen_m is None:
        return np.zeros(3)
    h, e, n = (float(v) for v in delta_hen_m)
    lat, lon, _ = ecef_to_geodetic(np.asarray(marker_r_e, dtype=float))
    return C_n_e(lat, lon) @ np.array([n, e, -h])


#: the passes of each solution type (RTKLIB's forward / backward / combined)
DIRECTIONS = ("forward", "backward", "combined")

#: the systems the post-processing RTK can solve with, in RTKLIB's order (GLONASS float only)
RTK_POST_SYSTEMS = "GRECJ"


def solve_rtk_rinex(rover_obs, base_obs, navs, *, base_xyz=None, config: RtkConfig = RtkConfig(),
                    progress=None, direction: str = "forward", **antennas) -> tuple[list[RtkSolution], dict]:
    """(solutions at the rover marker, info) for every paired epoch that could be solved.
    ``direction``: 'forward' (each epoch from the ones before it), 'backward' (from the ones
    after it) or 'combined' (both passes, :func:`companion.gnss.rtk_combine.combine`);
    ``antennas``: :func:`solve_rtk_epochs`'s."""
    hr, rover = read_rinex_obs(rover_obs, config.systems)
    span = (rover[0].t_gps - config.max_base_age_s, rover[-1].t_gps + config.max_base_age_s) if rover else None
    hb, base = read_rinex_obs(base_obs, config.systems, span)
    ephs = []
    for n in navs:
        ephs += read_rinex_nav(n, config.systems)
    return solve_rtk_epochs(hr, rover, hb, base, ephs, base_xyz=base_xyz, config=config, progress=progress,
                            direction=direction, **antennas)


def solve_rtk_epochs(hr: dict, rover, hb: dict, base, ephs, *, base_xyz=None, config: RtkConfig = RtkConfig(),
                     progress=None, direction: str = "forward", antennas: str | None = None,
                     rover_antenna: str | None = None,
                     base_antenna: str | None = None) -> tuple[list[RtkSolution], dict]:
    """:func:`solve_rtk_rinex` on observations already read (``read_rinex_obs``'s headers and
    epochs of rover and base) and the ephemerides.  ``antennas``: an ANTEX or NGS calibration file
    for the receivers' phase centres (:mod:`.antenna_calibration`), of the antenna types their
    headers name or ``rover_antenna`` / ``base_antenna``."""
    if direction not in DIRECTIONS:
        raise ValueError(f"direction must be one of {', '.join(DIRECTIONS)}, not {direction!r}")
    check_epochs(rover, hb, base)
    # each system's tracking families to one code on both sides (a rover's L2L pairs a base's L2X)
    rover, base = [rtk_epoch(e) for e in rover], [rtk_epoch(e) for e in base]
    for who, hdr, epochs in (("rover", hr, rover), ("base", hb, base)):
        if not any(o.sat[0] in config.systems for e in epochs for o in e.observations):
            raise ValueError(f"the {who} file has no observations of the selected systems ({config.systems}); "
                             f"it has {''.join(sorted(hdr.get('obs_types', {}))) or 'none'}")
    if not any(e.sat[0] in config.systems for e in ephs):
        raise ValueError(f"the navigation file(s) hold no ephemeris of the selected systems ({config.systems})")
    store = EphemerisStore(ephs)
    t_mid = rover[len(rover) // 2].t_gps
    if not any(store.select(sat, t) is not None for sat in store.sats for t in (rover[0].t_gps, t_mid)):
        toes = [e.t_oe_gps for e in ephs if hasattr(e, "t_oe_gps")]
        raise ValueError(f"no ephemeris is valid during the rover's observations "
                         f"({span_text(rover[0].t_gps, rover[-1].t_gps)}); "
                         + (f"the navigation file(s) are of {span_text(min(toes), max(toes))}" if toes else ""))
    given = base_xyz if base_xyz is not None else hb.get("approx_position_e")
    # (np.asarray(None, float) is NaN, which np.any takes for a position: test for it)
    base_marker = None if given is None else np.asarray(given, dtype=float)
    if base_marker is None or base_marker.shape != (3,) or not np.all(np.isfinite(base_marker)) \
            or not np.any(base_marker):
        raise ValueError("the base position is neither given (--base-xyz X,Y,Z) nor in the base file (a RINEX "
                         "header's APPROX POSITION XYZ, an RTCM 1005/1006; a u-blox capture has none); --base-xyz "
                         "spp takes the median of the base's own single-point solutions (metres off: the rover's "
                         "positions inherit that, the baseline does not)")
    base_ant = base_marker + antenna_delta_e(base_marker, hb.get("antenna_delta_hen_m"))
    cals, antenna_info = {}, {}
    if antennas is not None:
        table = read_antenna_file(antennas)
        for who, asked, hdr in (("rover", rover_antenna, hr), ("base", base_antenna, hb)):
            cals[who], antenna_info[who] = receiver_antenna(table, asked, hdr.get("antenna"), who, antennas)
    elif rover_antenna or base_antenna:
        raise ValueError("an antenna type is named but no calibration file (ANTEX or NGS) is given")
    config, glonass_ar = glonass_ar_of(config, hr, hb)
    pairs = pair_epochs(rover, base, tol_s=config.max_base_age_s)
    passes = ("forward", "backward") if direction == "combined" else (direction,)
    done = 0

    def step():                      # one epoch pair of one pass done
        nonlocal done
        done += 1
        if progress is not None:
            progress(done, len(pairs) * len(passes))

    out, counters = {}, {}
    for name in passes:
        backward = name == "backward"
        filt = RtkFilter(base_ant, store, config, backward=backward, rover_antenna=cals.get("rover"),
                         base_antenna=cals.get("base"))
        out[name] = _solve_pass(filt, pairs[::-1] if backward else pairs, store, hr, config, step)
        if backward:
            out[name].reverse()
        counters.update(filt.counters if len(passes) == 1 else {f"{name}: {k}": v for k, v in filt.counters.items()})
    if direction == "combined":
        sols = combine(out["forward"], out["backward"], counters)
        for name in passes:
            counters[f"{name}: fixed epochs"] = sum(1 for s in out[name] if s.quality == 1)
    else:
        sols = out[direction]
    info = {"rover_epochs": len(rover), "base_epochs": len(base), "paired_epochs": len(pairs),
            "max_base_age_s": max((abs(r.t_gps - b.t_gps) for r, b in pairs), default=0.0),
            "solutions": len(sols), "fixed": sum(1 for s in sols if s.quality == 1), "direction": direction,
            "base_antenna_e": base_ant.tolist(),
            "rover_antenna_delta_hen_m": [float(v) for v in (hr.get("antenna_delta_hen_m")
                                                             if hr.get("antenna_delta_hen_m") is not None else (0, 0, 0))],
            "counters": counters, "glonass_ar": glonass_ar, "antennas": antenna_info}
    return sols, info


def check_epochs(rover, hb: dict, base) -> None:
    """ValueError unless both files have epochs, the base's during the rover's (its file's span
    said when it has none there: files of two different days)."""
    if not rover:
        raise ValueError("the rover file has no observation epochs")
    if not base:
        span = hb.get("file_span_t_gps")
        raise ValueError(f"the base file has no epochs during the rover's ({span_text(rover[0].t_gps, rover[-1].t_gps)})"
                         + (f": it covers {span_text(*span)}" if span else ": it has no observation epochs"))


def glonass_ar_of(config: RtkConfig, hr: dict, hb: dict) -> tuple[RtkConfig, str]:
    """``config`` with ``glonass_ar`` 'auto' decided from the two headers' receiver types (REC # /
    TYPE / VERS): 'on' when both name the same model, else 'off'; and the decision in words
    ('' without GLONASS)."""
    if "R" not in config.systems:
        return config, ""
    if config.glonass_ar != "auto":
        return config, f"{config.glonass_ar} (asked)"
    rover, base = (str(h.get("receiver") or "").strip() for h in (hr, hb))
    if rover and rover.upper() == base.upper():
        return dataclasses.replace(config, glonass_ar="on"), f"on (both receivers {rover})"
    why = f"receivers {rover or 'unknown'} / {base or 'unknown'}"
    return dataclasses.replace(config, glonass_ar="off"), f"off ({why}: their inter-channel biases may differ)"


def _solve_pass(filt: RtkFilter, pairs, store, hr: dict, config: RtkConfig, step) -> list[RtkSolution]:
    """One pass of ``filt`` over the (rover, base) epoch pairs in the order given; the first epoch
    positioned by SPP."""
    rover_delta = hr.get("antenna_delta_hen_m")
    sols: list[RtkSolution] = []
    r_prior = hr.get("approx_position_e")
    for r_ep, b_ep in pairs:
        prior = None
        if not filt.initialized:
            spp = spp_epoch(r_ep, store, r_init_e=r_prior, systems=config.systems)
            if spp is None:
                filt.counters["epochs without an SPP start"] = filt.counters.get("epochs without an SPP start", 0) + 1
                step()
                continue
            prior = spp.r_e
        sol = filt.process(r_ep, b_ep, prior)
        if sol is not None:
            sol.r_e = sol.r_e - antenna_delta_e(sol.r_e, rover_delta)
            sols.append(sol)
        step()
    return sols


def pos_records(sols: list[RtkSolution]) -> list[PosRecord]:
    return [PosRecord(s.t_gps, s.r_e, s.cov_e, s.quality, s.n_sats, s.age_s, s.ratio) for s in sols]


__all__ = ["DIRECTIONS", "RTK_POST_SYSTEMS", "solve_rtk_rinex", "solve_rtk_epochs", "pos_records", "antenna_delta_e",
           "glonass_ar_of"]
