"""The error-state layout: an ordered list of named blocks built from configuration.

What RTKLIB's index macros (``NP``, ``NI``, ``NT``, ``IB(s,f)`` in ``rtkpos.c``) and KF-GINS's
``enum StateID`` do with numbers, as one object: nobody writes a state index, everybody asks the
layout by name (``layout.slice("position")``, ``layout.index("clock")``), and blocks can be added
and removed at run time (per-satellite, per-signal float ambiguities as satellites rise, set and
slip) without disturbing the others.

Two kinds of block, in this order:

* **core** blocks, whose transition couples them (Phi = I + F tau, :mod:`.filter`): the INS errors
  (attitude, position, velocity, accelerometer and gyro biases) and the receiver clock with its
  drift.  They form the prefix ``0 .. n_core - 1`` and are propagated densely.
* **identity** blocks, whose transition is the identity (random walks): the IMU time-tag offset
  ``dt_imu``, inter-system biases (Galileo, BeiDou, QZSS clocks minus GPS's, absent unless
  configured), and blocks added at run time.  Their propagation is process noise only; their
  cross-covariance with the core is multiplied by the core's transition (P_core,x <- Phi_core
  P_core,x), so they never cost an n x n product.

The covariance itself lives in the filter (:meth:`.filter.ErrorStateKalmanFilter.add_block`); this
module keeps the indices, plus :func:`insert_block` and :func:`delete_block` for the matrix.
The always-present blocks also have attributes (``att``, ``pos``, ``vel``, ``ba``, ``bg``: slices;
``clk``, ``drift``, ``toff``: integers), cached for the IMU-rate path where a look-up by string
would cost more than the arithmetic.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

ATTITUDE = "attitude"          # psi, rad (ECEF axes)
POSITION = "position"          # dr, m (ECEF)
VELOCITY = "velocity"          # dv, m/s (ECEF)
ACCEL_BIAS = "accel_bias"      # dba, m/s^2 (body)
GYRO_BIAS = "gyro_bias"        # dbg, rad/s (body)
CLOCK = "clock"                # receiver clock bias (GPS time), m
CLOCK_DRIFT = "clock_drift"    # its rate, m/s
DT_IMU = "dt_imu"              # IMU time-tag offset, s
REFERENCE_SYSTEM = "G"         # the receiver clock state is GPS's; other systems add a bias
ISB_SYSTEMS = ("R", "E", "C", "J")  # systems that may have an inter-system bias block


def isb_block_name(system: str) -> str:
    """Name of the inter-system bias block of a GNSS system (RINEX letter): ``isb_E`` etc."""
    return f"isb_{system}"


def system_of(sat: str) -> str:
    """The GNSS system of a satellite id in RINEX form ("G05" -> "G", "E11" -> "E")."""
    return sat[0]


@dataclass(frozen=True)
class Block:
    """One named block of the error state: indices ``start .. start + size - 1``."""

    name: str
    start: int
    size: int
    dense: bool          # part of the core whose transition is propagated densely

    @property
    def stop(self) -> int:
        return self.start + self.size

    @property
    def slice(self) -> slice:
        return slice(self.start, self.stop)


class StateLayout:
    """Ordered named blocks of the error state.  Build with :meth:`standard`; grow and shrink with
    :meth:`add_block` / :meth:`remove_block` (identity blocks, appended at the end)."""

    def __init__(self, blocks: Iterable[tuple[str, int, bool]]):
        self._blocks: list[Block] = []
        self._frozen = False
        for name, size, dense in blocks:
            self._append(name, size, dense)
        self._reindex()

    # ------------------------------------------------------------------ building
    @classmethod
    def standard(cls, inter_system_biases: Sequence[str] = ()) -> "StateLayout":
        """The INS core, one receiver clock (GPS time) with its drift, dt_imu, and one
        inter-system bias block per listed system (E, C, J: their clock minus GPS's, m)."""
        for s in inter_system_biases:
            if s not in ISB_SYSTEMS:
                raise ValueError(f"inter-system bias for {s!r}: expected one of {', '.join(ISB_SYSTEMS)}")
        if len(set(inter_system_biases)) != len(inter_system_biases):
            raise ValueError(f"inter-system biases listed twice: {list(inter_system_biases)}")
        blocks = [(ATTITUDE, 3, True), (POSITION, 3, True), (VELOCITY, 3, True), (ACCEL_BIAS, 3, True),
                  (GYRO_BIAS, 3, True), (CLOCK, 1, True), (CLOCK_DRIFT, 1, True), (DT_IMU, 1, False)]
        blocks += [(isb_block_name(s), 1, False) for s in inter_system_biases]
        return cls(blocks)

    def copy(self) -> "StateLayout":
        """A mutable copy (a filter takes one, so adding a block never changes another's layout)."""
        return StateLayout((b.name, b.size, b.dense) for b in self._blocks)

    def frozen(self) -> "StateLayout":
        """This layout, refusing :meth:`add_block` / :meth:`remove_block` (a shared default)."""
        self._frozen = True
        return self

    def add_block(self, name: str, size: int) -> Block:
        """Append an identity block (e.g. a float ambiguity ``"amb G05 L1C"``).  The covariance
        is the filter's business: use :meth:`.filter.ErrorStateKalmanFilter.add_block`."""
        if self._frozen:
            raise RuntimeError("this layout is shared and frozen: add blocks to a filter's own copy")
        self._append(name, size, False)
        self._reindex()
        return self._blocks[-1]

    def remove_block(self, name: str) -> Block:
        """Remove an identity block; the blocks after it move up.  Returns the removed block
        (with the indices it had)."""
        if self._frozen:
            raise RuntimeError("this layout is shared and frozen: remove blocks from a filter's own copy")
        b = self.block(name)
        if b.dense or name in _FIXED:
            raise ValueError(f"block {name!r} is part of the standard layout and cannot be removed")
        self._blocks = [x for x in self._blocks if x.name != name]
        self._reindex()
        return b

    def _append(self, name: str, size: int, dense: bool) -> None:
        if any(b.name == name for b in self._blocks):
            raise ValueError(f"state block {name!r} exists already")
        if int(size) != size or size < 1:
            raise ValueError(f"state block {name!r}: size must be a positive integer, not {size!r}")
        if dense and self._blocks and not self._blocks[-1].dense:
            raise ValueError(f"dense block {name!r} after an identity block: the core must come first")
        start = self._blocks[-1].stop if self._blocks else 0
        self._blocks.append(Block(name, start, int(size), bool(dense)))

    def _reindex(self) -> None:
        start = 0
        blocks = []
        for b in self._blocks:
            blocks.append(Block(b.name, start, b.size, b.dense))
            start += b.size
        self._blocks = blocks
        self._by_name = {b.name: b for b in blocks}
        self.n = start
        self.n_core = sum(b.size for b in blocks if b.dense)
        missing = [name for name in _FIXED if name not in self._by_name]
        if missing:
            raise ValueError(f"a layout needs the blocks {', '.join(missing)}")
        # the always-present blocks, cached for the hot paths (no string look-ups at IMU rate)
        self.att = self.slice(ATTITUDE)
        self.pos = self.slice(POSITION)
        self.vel = self.slice(VELOCITY)
        self.ba = self.slice(ACCEL_BIAS)
        self.bg = self.slice(GYRO_BIAS)
        self.clk = self.index(CLOCK)
        self.drift = self.index(CLOCK_DRIFT)
        self.toff = self.index(DT_IMU)
        self.isb_index = {name[4:]: b.start for name, b in self._by_name.items()
                          if name.startswith("isb_") and b.size == 1}

    # ------------------------------------------------------------------ look-ups
    @property
    def blocks(self) -> tuple[Block, ...]:
        return tuple(self._blocks)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(b.name for b in self._blocks)

    def __contains__(self, name: str) -> bool:
        return name in self._by_name

    def __len__(self) -> int:
        return self.n

    def block(self, name: str) -> Block:
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"no state block {name!r} (blocks: {', '.join(self.names)})") from None

    def slice(self, name: str) -> slice:
        return self.block(name).slice

    def index(self, name: str) -> int:
        """The index of a one-state block (``index("clock")``)."""
        b = self.block(name)
        if b.size != 1:
            raise ValueError(f"state block {name!r} has {b.size} states: use slice()")
        return b.start

    def identity_blocks(self) -> tuple[Block, ...]:
        return tuple(b for b in self._blocks if not b.dense)

    def extra_blocks(self) -> tuple[Block, ...]:
        """Blocks beyond the fixed ones (inter-system biases, run-time blocks): the engine keeps
        their nominal values in a dictionary by name."""
        return tuple(b for b in self._blocks if b.name not in _FIXED)

    def clock_columns(self, system: str) -> tuple[int, ...]:
        """Columns a pseudorange of ``system`` depends on with coefficient one: the receiver
        clock, plus the system's inter-system bias when the layout has one."""
        isb = self.isb_index.get(system)
        return (self.clk,) if isb is None else (self.clk, isb)

    def zeros(self, rows: int) -> np.ndarray:
        """An empty Jacobian of ``rows`` measurements over this layout."""
        return np.zeros((rows, self.n))

    def __repr__(self) -> str:
        return "StateLayout(" + ", ".join(f"{b.name}[{b.start}:{b.stop}]" for b in self._blocks) + ")"


_FIXED = (ATTITUDE, POSITION, VELOCITY, ACCEL_BIAS, GYRO_BIAS, CLOCK, CLOCK_DRIFT, DT_IMU)


def insert_block(P: np.ndarray, start: int, size: int, variance) -> np.ndarray:
    """The covariance with ``size`` new, uncorrelated states inserted at ``start`` with the given
    variance(s); every other entry is kept."""
    n = P.shape[0]
    out = np.zeros((n + size, n + size))
    keep = np.r_[0:start, start + size:n + size]
    out[np.ix_(keep, keep)] = P
    out[start:start + size, start:start + size] = np.diag(np.broadcast_to(np.asarray(variance, float), (size,)))
    return out


def delete_block(P: np.ndarray, start: int, size: int) -> np.ndarray:
    """The covariance without states ``start .. start + size - 1``: the marginal of the others."""
    keep = np.r_[0:start, start + size:P.shape[0]]
    return P[np.ix_(keep, keep)].copy()


DEFAULT_LAYOUT = StateLayout.standard().frozen()
