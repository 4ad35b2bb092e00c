"""The MAVLink parameter protocol on the companion's component: the ground station (Mission Planner,
QGroundControl, MAVProxy) reads and sets the installation and output settings as parameters.

A parameter is a view of one key of the configuration (:mod:`companion.config`), or of one
element of a vector key; a PARAM_SET builds the whole configuration again through the same
validation a file goes through (ranges, choices, cross-checks), so the ground station can set
nothing a file could not.  A refused value is answered with the unchanged value (the protocol's way
of saying no) and the reason as STATUSTEXT.  An accepted one is persisted to the configuration file
(atomically, the previous file kept as ``.bak`` once) and handed to ``on_change``.

Encoding: numbers are MAV_PARAM_TYPE_REAL32; a choice (``CC_OUT_MODE``) is MAV_PARAM_TYPE_INT32
holding the index of the choice, C-cast into the float field as ArduPilot and Mission Planner do
(MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST).  Received floats are float32: they are rounded to
7 significant digits before validation so 0.3 stays 0.3 in the file.  The moving baseline is unset
while all three of its parameters are 0 (a set baseline is at least 5 cm long).
"""
from __future__ import annotations

import dataclasses
import logging
import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from ..config import Config, ConfigError, config_from_dict
from .mavlink_codec import ENCODER, mavlink2 as mav
from .mavlink_encode import statustext_chunks

log = logging.getLogger(__name__)

PARAM_ID_LEN = 16


@dataclass(frozen=True)
class Parameter:
    """One parameter: its MAVLink id, the dotted configuration key, the element of a vector key."""

    param_id: str
    key: str                        # 'gnss.lever_arm_b_m'
    index: int | None = None        # element of a vector key
    choices: tuple[str, ...] = ()   # a choice key, sent as the INT32 index of its value
    unset_vector: bool = False      # an optional vector: all zeros = unset (None)

    @property
    def param_type(self) -> int:
        return mav.MAV_PARAM_TYPE_INT32 if self.choices else mav.MAV_PARAM_TYPE_REAL32


_OUTPUT_MODES = ("vision", "odometry", "gps_input")

#: what the ground station can read and set; ids at most 16 characters, prefix CC_ (companion computer)
PARAMETERS: tuple[Parameter, ...] = (
    Parameter("CC_LEVER_X", "gnss.lever_arm_b_m", 0),
    Parameter("CC_LEVER_Y", "gnss.lever_arm_b_m", 1),
    Parameter("CC_LEVER_Z", "gnss.lever_arm_b_m", 2),
    Parameter("CC_BASELINE_X", "gnss.moving_baseline_b_m", 0, unset_vector=True),
    Parameter("CC_BASELINE_Y", "gnss.moving_baseline_b_m", 1, unset_vector=True),
    Parameter("CC_BASELINE_Z", "gnss.moving_baseline_b_m", 2, unset_vector=True),
    Parameter("CC_GPS_LAT_S", "gnss.gps_raw_latency_s"),
    Parameter("CC_OUT_MODE", "output.mode", choices=_OUTPUT_MODES),
    Parameter("CC_OUT_RATE", "output.rate_hz"),
    Parameter("CC_MAX_SIG_H", "output.max_sigma_h_m"),
    Parameter("CC_MAX_SIG_V", "output.max_sigma_v_m"),
    Parameter("CC_MAX_SIG_YAW", "output.max_sigma_yaw_deg"),
    Parameter("CC_MAX_HPL", "output.max_hpl_m"),
    Parameter("CC_NV_RATE", "output.named_value_rate_hz"),
)
assert all(len(p.param_id) <= PARAM_ID_LEN for p in PARAMETERS)
assert len({p.param_id for p in PARAMETERS}) == len(PARAMETERS)

def _float32_decimal(x: float) -> float:
    """A float32 value as the decimal number the user typed (7 significant digits)."""
    return float(f"{float(x):.7g}")


def _param_id_text(raw) -> str:
    if isinstance(raw, (bytes, bytearray)):
        raw = raw.decode("ascii", "replace")
    return str(raw).split("\x00", 1)[0]


def _section(d: dict, dotted: str) -> tuple[dict, str]:
    *path, name = dotted.split(".")
    for p in path:
        d = d.setdefault(p, {})
    return d, name


def _get(cfg: Config, dotted: str):
    obj = cfg
    for p in dotted.split("."):
        obj = getattr(obj, p)
    return obj


class ParameterServer:
    """Answers PARAM_REQUEST_LIST / PARAM_REQUEST_READ / PARAM_SET addressed to our component.

    ``handle(msg)`` returns the messages to send (PARAM_VALUE, STATUSTEXT); the caller owns the
    link.  ``persist``: write accepted changes to ``config.source_path`` (when it has one)."""

    def __init__(self, config: Config, *, system_id: int, component_id: int, persist: bool = True,
                 on_change: Callable[[Config, tuple[str, ...]], None] | None = None):
        self.config = config
        self.system_id = system_id
        self.component_id = component_id
        self.persist = persist
        self.on_change = on_change
        self._by_id = {p.param_id: (i, p) for i, p in enumerate(PARAMETERS)}
        self.counters = {"requests": 0, "sets accepted": 0, "sets refused": 0, "unknown ids": 0,
                         "persist errors": 0}

    # ------------------------------------------------------------------ values
    def value(self, p: Parameter) -> float:
        v = _get(self.config, p.key)
        if p.choices:
            return float(p.choices.index(v))
        if p.index is not None:
            return float(0.0 if v is None else v[p.index])
        return float(v)

    def param_value(self, index: int):
        p = PARAMETERS[index]
        return ENCODER.param_value_encode(p.param_id.encode("ascii"), self.value(p), p.param_type,
                                       len(PARAMETERS), index)

    # ------------------------------------------------------------------ protocol
    def _for_us(self, msg) -> bool:
        return (msg.target_system in (0, self.system_id)
                and msg.target_component in (0, self.component_id))

    def handle(self, msg) -> list:
        kind = msg.get_type()
        if kind not in ("PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET") or not self._for_us(msg):
            return []
        self.counters["requests"] += 1
        if kind == "PARAM_REQUEST_LIST":
            return [self.param_value(i) for i in range(len(PARAMETERS))]
        if kind == "PARAM_REQUEST_READ":
            if msg.param_index >= 0:
                return [self.param_value(msg.param_index)] if msg.param_index < len(PARAMETERS) else []
            hit = self._by_id.get(_param_id_text(msg.param_id))
            if hit is None:
                self.counters["unknown ids"] += 1
                return []
            return [self.param_value(hit[0])]
        return self._set(_param_id_text(msg.param_id), float(msg.param_value))

    def _set(self, param_id: str, raw_value: float) -> list:
        hit = self._by_id.get(param_id)
        if hit is None:                  # another component's parameter (broadcast set): not ours
            self.counters["unknown ids"] += 1
            return []
        index, p = hit
        try:
            new = self._config_with(p, raw_value)
        except ConfigError as e:
            self.counters["sets refused"] += 1
            reason = str(e).replace(f"{self._where(p)}: ", "").replace(f"{p.key}: ", "")
            text = f"{param_id} refused: {reason}"
            log.warning("%s (%s)", text, p.key)
            return [self.param_value(index), *statustext_chunks(mav.MAV_SEVERITY_WARNING, text)]
        changed = new != self.config
        self.config = new
        self.counters["sets accepted"] += 1
        if changed:
            self._persist()
            if self.on_change is not None:
                self.on_change(new, (p.key,))
        return [self.param_value(index)]

    def _where(self, p: Parameter) -> str:
        return f"PARAM_SET {p.param_id}"

    def _config_with(self, p: Parameter, raw_value: float) -> Config:
        if not math.isfinite(raw_value):
            raise ConfigError(f"{self._where(p)}: {p.key}: must be a finite number, got {raw_value}")
        data = tomllib.loads(self.config.to_toml(comments=False))
        section, name = _section(data, p.key)
        if p.choices:
            k = int(round(raw_value))
            if not 0 <= k < len(p.choices) or k != raw_value:
                raise ConfigError(f"{self._where(p)}: must be an index 0..{len(p.choices) - 1} "
                                  f"({', '.join(p.choices)}), got {raw_value:g}")
            section[name] = p.choices[k]
        elif p.index is not None:
            vec = list(section.get(name) or (0.0, 0.0, 0.0))
            vec[p.index] = _float32_decimal(raw_value)
            if p.unset_vector and not any(vec):
                section.pop(name, None)
            else:
                section[name] = vec
        else:
            current = _get(self.config, p.key)
            section[name] = int(round(raw_value)) if isinstance(current, int) else _float32_decimal(raw_value)
        new = config_from_dict(data, where=self._where(p))
        return dataclasses.replace(new, source_path=self.config.source_path)

    def _persist(self) -> None:
        path = self.config.source_path
        if not (self.persist and path and Path(path).is_file()):      # a config from a string: nowhere to save
            return
        target = Path(path)
        try:
            backup = target.with_name(target.name + ".bak")
            if target.exists() and not backup.exists():
                backup.write_bytes(target.read_bytes())
            tmp = target.with_name(target.name + ".tmp")
            text = ("# written by the companion when a ground station set a parameter "
                    "(the file before the first change: " + backup.name + ")\n" + self.config.to_toml())
            tmp.write_text(text)
            os.chmod(tmp, target.stat().st_mode & 0o777 if target.exists() else 0o600)
            os.replace(tmp, target)
        except OSError as e:
            self.counters["persist errors"] += 1
            log.error("parameter change not saved to %s: %s", path, e)
