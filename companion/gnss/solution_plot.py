"""``companion gnss --plot``: one PNG of a post-processed run, for a person to look at rather than
read -- the track coloured by solution quality (RTKLIB's Q), the east / north / up offsets over time
(from the truth when it is given, else from the median position) with the solutions' own
3-sigma, and the satellites per epoch with the RTK ratio; with ``--against-demo5`` demo5's fixed
solutions beside ours.  Needs the ``[plot]`` extra."""
from __future__ import annotations

import math

import numpy as np

from ..nav.earth import C_n_e, ecef_to_geodetic
from .pos_format import PosRecord

#: RTKLIB's solution qualities, the colours rtkplot gives them
QUALITY_STYLE = {1: ("fixed", "tab:green"), 2: ("float", "tab:orange"), 4: ("DGPS", "tab:blue"),
                 5: ("single", "tab:red")}


def enu_offsets(records: list[PosRecord], ref_e) -> tuple[np.ndarray, np.ndarray]:
    """(east/north/up offsets from ``ref_e``, n x 3 m; their 1-sigma, n x 3 m) of the solutions."""
    lat, lon, _ = ecef_to_geodetic(np.asarray(ref_e, float))
    C_e_n = C_n_e(lat, lon).T
    ned = np.array([C_e_n @ (np.asarray(r.r_e, float) - ref_e) for r in records]).reshape(-1, 3)
    var = np.array([np.diag(C_e_n @ np.asarray(r.cov_e, float) @ C_e_n.T) for r in records]).reshape(-1, 3)
    enu = ned[:, [1, 0, 2]] * np.array([1.0, 1.0, -1.0])
    sig = np.sqrt(np.maximum(var[:, [1, 0, 2]], 0.0))
    return enu, sig


def plot_solutions(path, records: list[PosRecord], title: str, truth_e=None, other=None) -> None:
    """``other``: (label, GPS times s, ECEF positions n x 3 m) of another program's fixed solutions
    (``--against-demo5``), drawn beside ours in grey."""
    from ..extras import pyplot
    plt = pyplot("companion gnss --plot")
    from matplotlib.ticker import MaxNLocator
    ref = (np.asarray(truth_e, float) if truth_e is not None
           else np.median(np.array([r.r_e for r in records]), axis=0))
    enu, sig = enu_offsets(records, ref)
    t = np.array([r.t_gps for r in records]) - records[0].t_gps
    q = np.array([r.quality for r in records])
    fig = plt.figure(figsize=(13, 8))
    grid = fig.add_gridspec(3, 2, width_ratios=(1.0, 1.3))
    track = fig.add_subplot(grid[:, 0])
    axes = [fig.add_subplot(grid[i, 1]) for i in range(3)]
    for value, (name, colour) in QUALITY_STYLE.items():
        sel = q == value
        if sel.any():
            track.plot(enu[sel, 0], enu[sel, 1], ".", ms=3, color=colour, label=f"{name} ({int(sel.sum())})")
    other_enu = None
    if other is not None and len(other[1]):
        other_label, other_t, other_r = other
        other_enu = enu_offsets([PosRecord(float(tt), np.asarray(rr, float), np.zeros((3, 3)), 1, 0)
                                 for tt, rr in zip(other_t, other_r)], ref)[0]
        other_t = np.asarray(other_t, float) - records[0].t_gps
        track.plot(other_enu[:, 0], other_enu[:, 1], "x", ms=3, color="0.45",
                   label=f"{other_label} fixed ({len(other_t)})")
    if truth_e is not None:
        track.plot([0.0], [0.0], "k+", ms=12, label="truth")
    track.set_xlabel("east [m]")
    track.set_ylabel("north [m]")
    track.set_aspect("equal", adjustable="datalim")
    track.legend(loc="best", fontsize=8)
    track.set_title("track" + (" (from the truth)" if truth_e is not None else " (from the median position)"))
    for ax, names in ((axes[0], ((0, "east"), (1, "north"))), (axes[1], ((2, "up"),))):
        for i, name in names:
            ax.plot(t, enu[:, i], lw=0.8, label=name)
            ax.fill_between(t, enu[:, i] - 3 * sig[:, i], enu[:, i] + 3 * sig[:, i], alpha=0.15, lw=0)
            if other_enu is not None:
                ax.plot(other_t, other_enu[:, i], "x", ms=2.5, color="0.45",
                        label=f"{other_label} fixed" if i in (0, 2) else None)
        ax.set_ylabel("error [m]" if truth_e is not None else "offset [m]")
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
    for value, (name, colour) in QUALITY_STYLE.items():          # quality along the time axis
        sel = q == value
        if sel.any():
            axes[1].plot(t[sel], np.full(int(sel.sum()), axes[1].get_ylim()[0]), "|", color=colour, ms=8)
    n_sats = [r.n_sats for r in records]
    axes[2].plot(t, n_sats, color="0.3", lw=0.8, label="satellites")
    axes[2].set_ylabel("satellites")
    axes[2].set_ylim(0, max(n_sats, default=0) + 1)                # 16 against 17 is not a swing
    axes[2].yaxis.set_major_locator(MaxNLocator(integer=True))
    axes[2].set_xlabel("time [s]")
    ratio = np.array([r.ratio for r in records], float)
    if np.any(ratio > 0):
        r2 = axes[2].twinx()
        r2.semilogy(t, np.where(ratio > 0, ratio, math.nan), ".", ms=2, color="tab:purple", label="ratio")
        r2.axhline(3.0, color="tab:purple", lw=0.6, ls="--")
        r2.text(t[0], 3.0, " fix threshold 3", color="tab:purple", fontsize=7, va="bottom")
        r2.set_ylabel("LAMBDA ratio", color="tab:purple")
    axes[2].grid(alpha=0.3)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


__all__ = ["QUALITY_STYLE", "enu_offsets", "plot_solutions"]
