"""The raw GNSS an autopilot's own log carries, as records for the replay's pipeline.

* **ArduPilot** (``GPS_RAW_DATA = 1`` with a u-blox): the ``GRXH``/``GRXS`` records, rebuilt into
  RXM-RAWX frames (:mod:`companion.io.dataflash_raw`), fed as the receiver's UBX stream at their
  ``TimeUS``.  ArduPilot logs no ephemerides: ``--nav`` (RINEX) is needed.
* **PX4** (``GPS_DUMP_COMM``): the receiver's bytes from ``gps_dump``.  With 1 the whole stream
  (UBX: RXM-RAWX and, when the receiver sends them, RXM-SFRBX ephemerides), fed chunk by chunk at
  their timestamps, as the service reads a serial port; with 2 the RTCM 3 the receiver was set to
  output for PPK (MSM observations of the vehicle's own antenna, no ephemerides: ``--nav``),
  decoded and fed as the rover's epochs at the chunk that completed them.

``--base`` adds a base station (RINEX observations or an RTCM 3 capture), fed at its epochs' GPS
times on the log's boot clock; ``--nav`` also brings its header's Klobuchar model.
"""
from __future__ import annotations

import dataclasses

from .messages import SECONDS_PER_WEEK

NAV_HINT = "give --nav (a RINEX navigation file of the day, e.g. IGS BRDC)"


def logged_raw(dlog, nav_path, base_path) -> dict:
    """What the log's raw records give: ``items`` ((t_us, 'ubx'|'decoded', bytes|[messages]) in
    log order), ``first`` (the messages to feed before them: ephemerides, base position), ``base``
    (base epochs), ``notes``, ``counters``, ``klobuchar``; or why not (``reason``: a note, the
    replay goes on loosely coupled; ``refusal``: the replay stops)."""
    if dlog.raw_epochs:
        return _ardupilot(dlog, nav_path, base_path)
    if dlog.raw_stream:
        return _px4(dlog, nav_path, base_path)
    return {"reason": "", "notes": [] if nav_path is None else [
        "--nav given, but the log has no raw observations (ArduPilot: GRXH/GRXS with GPS_RAW_DATA 1; "
        "PX4: gps_dump with GPS_DUMP_COMM)"]}


def _ardupilot(dlog, nav_path, base_path) -> dict:
    from .io.dataflash_raw import log_frames
    frames, counters = log_frames(dlog)
    n = len(dlog.raw_epochs)
    if nav_path is None:
        return {"reason": f"{n} raw GNSS epochs (GRXH/GRXS) in the log, not used: {NAV_HINT} to use them tightly "
                          f"coupled", "notes": [], "counters": counters}
    if not frames:
        return {"reason": f"{n} raw GNSS epochs (GRXH/GRXS), none with a usable measurement", "notes": [],
                "counters": counters}
    t_first = dlog.raw_epochs[0].week * SECONDS_PER_WEEK + dlog.raw_epochs[0].rcv_tow_s
    out = _with_inputs(nav_path, base_path, t_first)
    if "refusal" not in out:
        out["notes"].insert(0, f"raw observations: {len(frames)} u-blox epochs from the log's GRXH/GRXS records "
                               f"(RXM-RAWX rebuilt, companion.io.dataflash_raw), ephemerides from {nav_path}: "
                               f"tightly coupled")
        out.update(items=[(t_us, "ubx", frame) for t_us, frame in frames], counters=counters)
    return out


def _px4(dlog, nav_path, base_path) -> dict:
    from .io.capture_format import stream_kind
    chunks = dlog.raw_stream
    kind = stream_kind(b"".join(c for _, c in chunks[:400]))
    t_first = _first_gps_time(dlog)
    if kind == "ubx":
        out = _with_inputs(nav_path, base_path, t_first) if nav_path is not None or base_path is not None else \
            {"reason": "", "notes": [], "first": [], "base": []}
        if "refusal" not in out:
            out["notes"].insert(0, f"raw observations: the receiver's UBX stream from the log's gps_dump "
                                   f"({len(chunks)} chunks, GPS_DUMP_COMM 1): tightly coupled"
                                   + ("" if nav_path else "; ephemerides from its RXM-SFRBX"))
            out["items"] = [(t_us, "ubx", c) for t_us, c in chunks]
        return out
    if kind == "rtcm":
        if nav_path is None:
            return {"reason": f"the receiver's RTCM output in the log's gps_dump (GPS_DUMP_COMM 2) is not used: "
                              f"{NAV_HINT}", "notes": []}
        out = _with_inputs(nav_path, base_path, t_first)
        if "refusal" not in out:
            items, counters = _rtcm_rover_items(chunks, t_first)
            out["notes"].insert(0, f"raw observations: the receiver's RTCM output from the log's gps_dump "
                                   f"(GPS_DUMP_COMM 2, {counters['rover epochs']} epochs), ephemerides from "
                                   f"{nav_path}: tightly coupled")
            out.update(items=items, counters=counters)
        return out
    return {"reason": f"the log's gps_dump ({len(chunks)} chunks) holds neither UBX nor RTCM 3 frames: not used",
            "notes": []}


def _rtcm_rover_items(chunks, t_gps_hint: float):
    """The vehicle's own MSM epochs (as the rover's), and any ephemerides, at the chunk that
    completed each; its own 1005/1006 is not a base and is left out (counted)."""
    from collections import Counter
    from .io.rtcm import RtcmDecoder
    from .messages import BaseStationPosition, GnssEpoch
    dec = RtcmDecoder(week_hint=int(t_gps_hint // SECONDS_PER_WEEK))
    counters: Counter = Counter()
    items = []
    for t_us, chunk in chunks:
        msgs = []
        for m in dec.feed(chunk):
            if isinstance(m, GnssEpoch):
                msgs.append(dataclasses.replace(m, source="rover"))
                counters["rover epochs"] += 1
            elif isinstance(m, BaseStationPosition):
                counters["own antenna positions (1005/1006, not used)"] += 1
            else:
                msgs.append(m)
        if msgs:
            items.append((t_us, "decoded", msgs))
    return items, counters


def _first_gps_time(dlog) -> float:
    """GPS time of the log's first fix with a week (0 when none)."""
    for rows in dlog.gps.values():
        for r in rows:
            if r[3] > 0:
                return float(r[3]) * SECONDS_PER_WEEK + float(r[2]) * 1e-3
    return 0.0


def _with_inputs(nav_path, base_path, t_gps_obs: float) -> dict:
    """``first`` (ephemerides of ``nav_path``, the base position), ``base`` (its epochs),
    ``notes``, ``klobuchar``; or a ``refusal`` when a file cannot be read."""
    from .replay_receiver import nav_klobuchar, read_base, read_nav
    try:
        first, shifted, channels = read_nav(nav_path, t_gps_obs) if nav_path is not None else ([], 0, {})
        position, base = read_base(base_path, channels, t_gps_obs) if base_path is not None else (None, [])
    except (OSError, ValueError, IndexError) as exc:
        return {"refusal": f"cannot read the RINEX input: {exc}", "reason": "", "notes": []}
    notes = []
    if shifted:
        notes.append(f"{shifted} ephemerides of {nav_path} were 1024 weeks off the observations: moved back")
    if position is not None:
        first.append(position)
        notes.append(f"base station from {base_path} ({len(base)} epochs)")
    return {"reason": "", "first": first, "base": base, "notes": notes,
            "klobuchar": nav_klobuchar(nav_path) if nav_path is not None else None}


def raw_records(raw: dict, tb):
    """(t_boot_us, order, kind, item) of the logged raw stream for the merge with the MAVLink
    messages: ``first`` just before the first item, each item at its time, each base epoch at its
    GPS time on the log's boot clock."""
    items = raw.get("items") or []
    if not items:
        return []
    out = [(items[0][0] - 1, 1, "decoded", raw["first"])] if raw.get("first") else []
    out += [(t_us, 1, kind, item) for t_us, kind, item in items]
    out += [(tb.to_boot(e.t_gps) * 1e6, 1, "decoded", [e]) for e in raw.get("base") or []]
    return sorted(out, key=lambda x: x[0])


__all__ = ["logged_raw", "raw_records"]
