"""The receivers' antenna calibrations of the engine's RTK (``[filter] rtk_antennas``): the file read
once at start-up, the rover's type from the configuration, the base's from the configuration or,
by default, from what the base says it is (RTCM 1007/1008/1033, as they arrive).

A type the configuration names and the file lacks stops the start-up (a typo must not pass for a
calibration); a type the base names and the file lacks leaves the base's phase centres at its ARP,
counted and in the health report, as does a base that names none.
"""
from __future__ import annotations

import dataclasses
import hashlib
import logging
from pathlib import Path

from ..gnss.antenna_calibration import AntennaCalibration, read_antenna_file, receiver_antenna

log = logging.getLogger(__name__)


def file_sha256(path: str) -> str | None:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()
    except OSError:
        return None


def antennas_digest(config) -> dict:
    """What a field log's config record adds: the calibration file's SHA-256, so that a replay
    elsewhere knows whether the file it is given is the one the flight used."""
    path = config.filter.rtk_antennas
    digest = file_sha256(path) if path else None
    return {"rtk_antennas_sha256": digest} if digest else {}


def antennas_preflight(config) -> str | None:
    """The start-up's check: None, or why the configured calibrations cannot be used."""
    f = config.filter
    if not (f.rtk_enabled and f.rtk_antennas):
        return None
    try:
        RtkAntennas(f.rtk_antennas, f.rtk_rover_antenna, f.rtk_base_antenna)
    except ValueError as exc:
        return str(exc)
    return None


def for_replay(config, logged_sha256: str | None, path: str | None = None):
    """(configuration, note or None) to replay a field log made with ``config``: its calibration
    file where it was (or ``path``, ``companion replay --antennas-file``); without one here the
    replay runs uncalibrated and says that its solutions will differ from the logged ones, and a
    file that is not the logged one (another SHA-256) is said to be."""
    f = config.filter
    if not (f.rtk_enabled and (f.rtk_antennas or path)):
        return config, None
    use = path or f.rtk_antennas
    digest = file_sha256(use)
    if digest is None:
        off = dataclasses.replace(f, rtk_antennas="", rtk_rover_antenna="", rtk_base_antenna="")
        return (dataclasses.replace(config, filter=off),
                f"the antenna calibrations the log was made with ({use}) are not here: replayed without them, so "
                f"RTK solutions differ from the logged ones by the antennas' offsets (give the file with "
                f"--antennas-file)")
    note = None
    if logged_sha256 and digest != logged_sha256:
        note = f"{use} is not the antenna calibration file the log was made with (another SHA-256)"
    return dataclasses.replace(config, filter=dataclasses.replace(f, rtk_antennas=use)), note


class RtkAntennas:
    """Which calibration each receiver has, and why (:meth:`status` for the health report)."""

    def __init__(self, path: str, rover_type: str = "", base_type: str = ""):
        try:
            self._table = read_antenna_file(path)
        except (OSError, ValueError) as exc:
            raise ValueError(f"[filter] rtk_antennas: cannot read {path}: {exc}") from exc
        self.path = path
        self._base_asked = base_type or None
        self.rover, self._rover_info = receiver_antenna(self._table, rover_type or None, None, "rover", path)
        if not rover_type:
            self._rover_info["notes"] = ["no [filter] rtk_rover_antenna: phase centres taken at the ARP"]
        self.base: AntennaCalibration | None = None
        self._base_info: dict = {"type": None, "from": "base's RTCM 1007/1008/1033", "calibration": None,
                                 "notes": ["the base has not named its antenna yet"]}
        self._base_named: str | None = None
        self._names_seen = 0                  # the base's antenna names so far (a flapping one is logged 5 times)
        if self._base_asked:
            self.base, self._base_info = receiver_antenna(self._table, self._base_asked, None, "base", path)

    def base_named(self, name: str) -> bool:
        """The base named its antenna ``name``; True when that changes the base's calibration
        (ignored when the configuration names the base's type)."""
        if self._base_asked or name == self._base_named:
            return False
        self._base_named = name
        cal, info = receiver_antenna(self._table, None, name, "base", self.path)
        info["from"] = "base's RTCM 1007/1008/1033"
        self._base_info = info
        self._names_seen += 1
        if self._names_seen <= 5:
            log.info("RTK base antenna %r: %s", name, info["calibration"] or "; ".join(info["notes"]))
        changed = (cal is None) != (self.base is None) or (cal is not None and cal.name != self.base.name)
        self.base = cal
        return changed

    def status(self) -> dict:
        return {"file": self.path, "rover": dict(self._rover_info), "base": dict(self._base_info)}


__all__ = ["RtkAntennas", "antennas_digest", "antennas_preflight", "file_sha256", "for_replay"]
