"""The receiver clock from the pseudoranges (a mixin of :class:`companion.nav.engine.NavEngine`):
the first epoch seeds the clock (and each other system's inter-system bias) from the data; later a
jump common to all pseudorange innovations (a clock reset or steering step, a base-clock step in
the corrections) re-seeds it."""
from __future__ import annotations

import logging
import math
from statistics import median

from .filter import MeasurementBatch
from .state_layout import isb_block_name, system_of
from .measurements import InsPoint

log = logging.getLogger("companion.nav.engine")


class ClockSeeding:
    """Clock (and inter-system bias) seeding of the NavEngine."""

    def _check_clock(self, ins: InsPoint, pr: MeasurementBatch) -> None:
        """First epoch: take the clock from the data.  Later: a jump common to all pseudorange
        innovations (receiver clock reset or steering step, a base-clock step in the corrections)
        re-seeds the clock state.  Common-mode means: the median innovation is far outside what the
        clock's own uncertainty allows, while the innovations agree with each other."""
        z = pr.z.tolist()
        common = median(z)           # statistics.median: much cheaper than numpy's for ~10 values
        L = self.layout
        P = self.kf.P
        if self.clock_initialized:
            r_med = median(pr.r_var.tolist())
            spread = median([abs(x - common) for x in z])
            if len(pr) < 3 or abs(common) < max(self.cfg.clock_jump_sigmas * math.sqrt(P[L.clk, L.clk] + r_med),
                                                 self.cfg.clock_jump_min_m):
                return
            if spread > 3.0 * math.sqrt(r_med):
                return  # not common-mode: a position problem, leave it to the gate
            self.counters["receiver clock jump re-seeded"] += 1
            log.warning("pseudoranges jumped together by %.1f m: clock state re-seeded", common)
        var0 = max(median(pr.r_var.tolist()), 1.0)
        if not self.clock_initialized and L.isb_index:
            common = self._seed_inter_system_biases(pr, z, var0)
        self.clock_bias_m += common
        pr.z = pr.z - common
        P[L.clk, :] = 0.0
        P[:, L.clk] = 0.0
        P[L.clk, L.clk] = var0
        self.clock_initialized = True

    def _seed_inter_system_biases(self, pr: MeasurementBatch, z: list[float], var0: float) -> float:
        """First epoch with several systems: the receiver clock from the reference system's
        pseudoranges (all of them if it has none here), each other system's bias from its own
        (median innovation minus the clock), so that no system's rows start tens of metres off.
        Returns the clock's share; the rows of the biased systems are corrected here."""
        L = self.layout
        by_system: dict[str, list[int]] = {}
        for k, sat in enumerate(pr.labels):
            col = L.isb_index.get(system_of(sat))
            by_system.setdefault(system_of(sat) if col is not None else "", []).append(k)
        ref_rows = by_system.get("") or list(range(len(z)))
        common = median([z[k] for k in ref_rows])
        P = self.kf.P
        for system, rows in by_system.items():
            if not system:
                continue
            bias = median([z[k] for k in rows]) - common
            name = isb_block_name(system)
            self.block_states[name] = self.block_states[name] + bias
            pr.z[rows] -= bias
            col = L.isb_index[system]
            P[col, :] = 0.0
            P[:, col] = 0.0
            P[col, col] = 2.0 * var0       # the difference of two medians
            self.counters[f"inter-system bias {system} seeded from the pseudoranges"] += 1
        return common
