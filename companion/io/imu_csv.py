"""An IMU recorded as CSV (a logger beside the receiver, a phone, a lab IMU) -> samples in the
units and frame the filter uses: GPS time (s), angular rate (rad/s) and specific force (m/s^2) in
body FRD.

``columns`` maps the seven quantities to the file's column names: ``t`` (time), ``gx gy gz``
(rate), ``ax ay az`` (specific force), e.g. ``"t=time,gx=wx,gy=wy,gz=wz,ax=fx,ay=fy,az=fz"``;
the default is those short names themselves.  ``time``: 'gps' (seconds of GPS time: week * 604800
+ TOW) or 'unix' (seconds since 1970, UTC: leap seconds added).  ``gyro_unit`` 'rad/s' or
'deg/s'; ``accel_unit`` 'm/s2' or 'g' (9.80665).  ``rotation`` maps the sensor's axes onto body
FRD: three signed axis names, the body axis each sensor axis is, e.g. ``"x,-y,-z"`` for a sensor
in FLU (x forward, y left, z up); default ``"x,y,z"``.  A sample whose values are not finite, or
whose time does not increase, is dropped and counted.
"""
from __future__ import annotations

import csv
import math

import numpy as np

GPS_EPOCH_UNIX_S = 315964800.0           # 1980-01-06 00:00:00 UTC
STANDARD_GRAVITY_MPS2 = 9.80665
QUANTITIES = ("t", "gx", "gy", "gz", "ax", "ay", "az")


def parse_columns(spec: str | None) -> dict[str, str]:
    """'t=time,gx=wx,...' -> {'t': 'time', 'gx': 'wx', ...}; unnamed quantities keep their own name."""
    out = {q: q for q in QUANTITIES}
    for part in (spec or "").split(","):
        if not part.strip():
            continue
        key, sep, name = part.partition("=")
        key = key.strip()
        if not sep or key not in QUANTITIES or not name.strip():
            raise ValueError(f"--imu-columns: {part.strip()!r} is not QUANTITY=COLUMN with QUANTITY one of "
                             f"{', '.join(QUANTITIES)}")
        out[key] = name.strip()
    return out


def parse_rotation(spec: str | None) -> np.ndarray:
    """'x,-y,-z' -> the 3x3 matrix taking a sensor-frame vector into body FRD."""
    axes = {"x": 0, "y": 1, "z": 2}
    parts = [p.strip().lower() for p in (spec or "x,y,z").split(",")]
    R = np.zeros((3, 3))
    used = set()
    if len(parts) != 3:
        raise ValueError(f"--imu-rotation: {spec!r}: three signed axes expected, e.g. x,-y,-z")
    for i, p in enumerate(parts):
        sign = -1.0 if p.startswith("-") else 1.0
        name = p.lstrip("+-")
        if name not in axes or name in used:
            raise ValueError(f"--imu-rotation: {spec!r}: each of x, y, z once, with an optional sign")
        used.add(name)
        R[axes[name], i] = sign               # sensor axis i is body axis `name`
    return R


def read_imu_csv(path, *, columns: str | None = None, time: str = "gps", gyro_unit: str = "rad/s",
                 accel_unit: str = "m/s2", rotation: str | None = None,
                 leap_seconds: int = 18) -> tuple[np.ndarray, dict]:
    """(N, 7) array: GPS time s, rate rad/s (FRD), specific force m/s^2 (FRD); and counters."""
    if time not in ("gps", "unix"):
        raise ValueError(f"--imu-time: {time!r}: 'gps' or 'unix'")
    g_scale = {"rad/s": 1.0, "deg/s": math.pi / 180.0}.get(gyro_unit)
    a_scale = {"m/s2": 1.0, "g": STANDARD_GRAVITY_MPS2}.get(accel_unit)
    if g_scale is None or a_scale is None:
        raise ValueError(f"units: gyro 'rad/s' or 'deg/s' (got {gyro_unit!r}), accel 'm/s2' or 'g' (got {accel_unit!r})")
    cols = parse_columns(columns)
    R = parse_rotation(rotation)
    rows, counters = [], {"rows": 0, "dropped: not a number": 0, "dropped: time not increasing": 0}
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        missing = [c for c in cols.values() if c not in (reader.fieldnames or ())]
        if missing:
            raise ValueError(f"{path}: no column {', '.join(missing)} (columns: {', '.join(reader.fieldnames or ())}; "
                             f"map them with --imu-columns t=...,gx=...)")
        t_prev = -math.inf
        for rec in reader:
            counters["rows"] += 1
            try:
                v = [float(rec[cols[q]]) for q in QUANTITIES]
            except (TypeError, ValueError):
                counters["dropped: not a number"] += 1
                continue
            if not all(math.isfinite(x) for x in v):
                counters["dropped: not a number"] += 1
                continue
            if v[0] <= t_prev:
                counters["dropped: time not increasing"] += 1
                continue
            t_prev = v[0]
            rows.append(v)
    a = np.array(rows, float).reshape(-1, 7)
    if time == "unix":
        a[:, 0] = a[:, 0] - GPS_EPOCH_UNIX_S + leap_seconds
    a[:, 1:4] = (a[:, 1:4] * g_scale) @ R.T
    a[:, 4:7] = (a[:, 4:7] * a_scale) @ R.T
    return a, counters


__all__ = ["read_imu_csv", "parse_columns", "parse_rotation"]
