"""RTKLIB's own solutions in the tests: the fixed epochs of an ``rnx2rtkp`` .pos file written with
ECEF positions and GPS week / time of week (``-e``, or out-solformat=xyz, out-timeform=tow)."""
from __future__ import annotations

import numpy as np


def rtklib_fixed_xyz(path) -> dict[int, np.ndarray]:
    """GPS second (rounded) -> ECEF position (m) of every Q=1 epoch."""
    fixed = {}
    for ln in open(path).read().splitlines():
        f = ln.split()
        if not ln.startswith("%") and len(f) > 5 and f[5] == "1":
            fixed[round(int(f[0]) * 604800 + float(f[1]))] = np.array([float(v) for v in f[2:5]])
    return fixed
