"""RTKLIB demo5 on the same RINEX files as ``companion gnss --mode rtk``, and the comparison of the two
(``--against-demo5``; the tests' reference, tests/test_rtk_vs_demo5.py).

demo5 is rtklibexplorer's branch of RTKLIB ("RTKLIB ver.EX 2.5.0"), reached through the pyrtklib5
binding (the ``[rtklib]`` extra; wheels for x86_64 only).  It runs in a child process, so a crash
of the C library cannot take ours with it, from a configuration written here with our run's
options: kinematic, L1+L2 (or L1 alone), the same systems, elevation mask and solution direction, fix-and-hold,
ratio 3, GLONASS integers as ours decided them, the base antenna where ours put it, the rover's
antenna height as ours read it from its header (both programs then solve the rover's marker); every other option
is demo5's own default.  Compressed RINEX (Hatanaka, gzip) is expanded first: RTKLIB would call
external tools for it.
"""
from __future__ import annotations

import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..extras import MissingExtra, available, install_hint
from ..messages import SECONDS_PER_WEEK

#: RTKLIB's navsys bits (pos1-navsys)
_NAVSYS_BITS = {"G": 1, "S": 2, "R": 4, "E": 8, "J": 16, "C": 32}
#: our solution directions, RTKLIB's pos1-soltype names too
_DIRECTIONS = ("forward", "backward", "combined")

_RUNNER = """
import sys, pyrtklib5 as r
conf, out, *files = sys.argv[1:]
r.resetsysopts()
if not r.loadopts(conf, r.sysopts[0]):
    sys.exit("demo5 could not read its configuration")
popt, sopt, fopt = r.prcopt_t(), r.solopt_t(), r.filopt_t()
r.getsysopts(popt, sopt, fopt)
sys.exit(r.postpos(r.gtime_t(), r.gtime_t(), 0.0, 0.0, popt, sopt, fopt, files, len(files), out, "", ""))
"""


def demo5_available() -> bool:
    """pyrtklib5 installed (found, not loaded: only the child process loads the C library)."""
    return available("pyrtklib5")


def require_demo5() -> None:
    """Raise :class:`~companion.extras.MissingExtra` naming the ``[rtklib]`` extra when demo5 is absent."""
    if not demo5_available():
        raise MissingExtra(f"comparing with RTKLIB demo5 needs pyrtklib5, which is not installed: "
                           f"{install_hint('pyrtklib5', 'rtklib')} (wheels for x86_64 Linux)")


def epoch_key(t_gps: float) -> int:
    """An epoch's key for matching two programs' solutions: its GPS time in centiseconds (a 5-Hz or
    10-Hz rover's epochs stay apart; .pos files print the time of week to the millisecond)."""
    return round(t_gps * 100.0)


@dataclass
class Demo5Run:
    """demo5's solutions: (GPS time s, ECEF position m, Q: 1 fixed, 2 float) per epoch."""

    solutions: list[tuple[float, np.ndarray, int]]
    version: str                           # the program line of its solution file
    pos_text: str = ""                     # its solution file as written

    @property
    def fixed(self) -> list[tuple[float, np.ndarray]]:
        return [(t, r) for t, r, q in self.solutions if q == 1]


def _plain(src, work: Path, index: int | str) -> str:
    """``src`` as plain RINEX in ``work`` (hatanaka expands Hatanaka and gzip and leaves plain RINEX
    as it is)."""
    from ..extras import require
    hatanaka = require("hatanaka", "rinex", "reading compressed RINEX for demo5")
    out = work / f"{index}_{Path(src).name.split('.')[0]}"
    out.write_bytes(hatanaka.decompress(Path(src).read_bytes()))
    return str(out)


def _joined_plain(srcs, work: Path, index: int) -> str:
    """Several observation files of one receiver as one plain RINEX for demo5: the first file,
    then the epochs of the others (RTKLIB sorts them and drops what repeats); their observation
    types must be the same, as one header describes them all."""
    texts = [Path(_plain(src, work, f"{index}.{k}")).read_text(errors="replace") for k, src in enumerate(srcs)]

    def split(text: str) -> tuple[list[str], str]:
        head, _, body = text.partition("END OF HEADER")
        types = [ln for ln in head.splitlines() if "TYPES OF OBSERV" in ln or "SYS / # / OBS TYPES" in ln]
        return types, body.split("\n", 1)[1] if "\n" in body else ""
    types0, _ = split(texts[0])
    out = texts[0].rstrip("\n") + "\n"
    for src, text in zip(srcs[1:], texts[1:]):
        types, body = split(text)
        if types != types0:
            raise RuntimeError(f"demo5 is given a receiver's files as one: {src} has other observation types "
                               f"than {srcs[0]}")
        out += body.rstrip("\n") + "\n"
    joined = work / f"{index}_joined.obs"
    joined.write_text(out)
    return str(joined)


def _antenna_lines(antennas: str | None, types: dict) -> list[str]:
    """demo5's receiver antenna options: the calibration file, each end's type, and the elevation
    variations applied as well as the offsets (pos1-posopt2, as ours does)."""
    if antennas is None or not types:
        return []
    return [f"file-rcvantfile    ={Path(antennas).resolve()}", "pos1-posopt2       =on",
            *(f"ant{k}-anttype      ={types[who]}" for k, who in ((1, "rover"), (2, "base")) if who in types)]


def run_demo5(rover, base, navs, base_antenna_e, *, rover_antenna_delta_hen=(0.0, 0.0, 0.0), systems: str = "GEJ",
              mask_deg: float = 10.0, glonass_ar: str = "off", direction: str = "forward",
              frequencies: str = "l1+l2", static: bool = False, iono: str = "off",
              antennas: str | None = None, antenna_types: dict | None = None,
              work: Path | None = None) -> Demo5Run:
    """demo5's kinematic RTK of ``rover`` against ``base`` (RINEX observation files; each may be
    several files of one receiver) with the
    navigation files ``navs``, the base antenna at ``base_antenna_e`` (ECEF, m), the rover's
    antenna ``rover_antenna_delta_hen`` (up, east, north, m) above its marker (the RTK run's
    ``info['rover_antenna_delta_hen_m']``, from the rover header); ``frequencies``
    RTKLIB's pos1-frequency ('l1' as a single-frequency receiver); ``static``: its static mode
    (the rover stood still); ``iono`` 'est': the differential ionosphere estimated (its est-stec;
    'off' is its broadcast model, which cancels over a baseline); ``antennas``: a receiver antenna
    calibration file (ANTEX or NGS), with ``antenna_types`` ('rover' / 'base' -> the type ours
    calibrated; a receiver not named keeps its phase centres at the ARP); ``work``: where its files
    go (a temporary folder when None)."""
    require_demo5()
    if direction not in _DIRECTIONS:
        raise ValueError(f"direction must be one of {', '.join(_DIRECTIONS)}, not {direction!r}")
    if frequencies not in ("l1", "l1+l2", "l1+l2+l3"):
        raise ValueError(f"frequencies must be l1, l1+l2 or l1+l2+l3, not {frequencies!r}")
    if iono not in ("off", "est"):
        raise ValueError(f"iono must be off or est, not {iono!r}")
    with tempfile.TemporaryDirectory(prefix="companion-demo5-") as tmp:
        work = Path(work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        rovers, bases = ([f] if isinstance(f, (str, Path)) else list(f) for f in (rover, base))
        files = [_plain(rovers[0], work, 0) if len(rovers) == 1 else _joined_plain(rovers, work, 0),
                 _plain(bases[0], work, 1) if len(bases) == 1 else _joined_plain(bases, work, 1),
                 *(_plain(f, work, i + 2) for i, f in enumerate(navs))]
        up, east, north = (float(v) for v in rover_antenna_delta_hen)
        conf = work / "demo5.conf"
        conf.write_text("\n".join([
            f"pos1-posmode       ={'static' if static else 'kinematic'}",
            f"pos1-frequency     ={frequencies}",
            f"pos1-soltype       ={direction}",
            f"pos1-elmask        ={mask_deg:g}",
            f"pos1-navsys        ={sum(_NAVSYS_BITS[s] for s in dict.fromkeys(systems))}",
            f"pos1-ionoopt       ={'est-stec' if iono == 'est' else 'brdc'}",
            "pos1-tropopt       =saas",
            "pos1-sateph        =brdc",
            "pos2-armode        =fix-and-hold",
            f"pos2-gloarmode     ={'on' if glonass_ar == 'on' else 'off'}",
            "pos2-arthres       =3",
            "pos2-maxage        =30",
            f"ant1-antdele       ={east!r}",
            f"ant1-antdeln       ={north!r}",
            f"ant1-antdelu       ={up!r}",
            "ant2-postype       =xyz",
            *(f"ant2-pos{i + 1}          ={float(v)!r}" for i, v in enumerate(base_antenna_e)),
            *_antenna_lines(antennas, antenna_types or {}),
            "out-solformat      =xyz",
            "out-timeform       =tow",
            "",
        ]))
        out = work / "demo5.pos"
        proc = subprocess.run([sys.executable, "-c", _RUNNER, str(conf), str(out), *files],
                              capture_output=True, text=True, timeout=3600)
        if proc.returncode != 0 or not out.exists():
            raise RuntimeError(f"RTKLIB demo5 failed (exit {proc.returncode}): {proc.stderr.strip()[-500:]}")
        text = out.read_text()
    sols, version = [], "RTKLIB demo5"
    for ln in text.splitlines():
        f = ln.split()
        if ln.startswith("% program"):
            version = ln.split(":", 1)[1].strip()
        if ln.startswith("%") or len(f) < 6:
            continue
        sols.append((int(f[0]) * SECONDS_PER_WEEK + float(f[1]), np.array([float(v) for v in f[2:5]]), int(f[5])))
    return Demo5Run(sols, version, text)


@dataclass
class Comparison:
    ours_fixed: int
    demo5_fixed: int
    demo5_solved: int
    both_fixed: int
    apart_m: np.ndarray = field(repr=False)          # per epoch both fixed: |ours - demo5|
    rms_ours_m: float | None = None                  # against the truth, on the epochs both fixed
    rms_demo5_m: float | None = None
    version: str = ""

    def summary(self) -> dict:
        out = {"demo5": self.version, "fixed_ours": self.ours_fixed, "fixed_demo5": self.demo5_fixed,
               "solved_demo5": self.demo5_solved, "both_fixed": self.both_fixed}
        if self.both_fixed:
            out.update(apart_median_m=float(np.median(self.apart_m)), apart_max_m=float(self.apart_m.max()))
        if self.rms_ours_m is not None:
            out.update(rms_3d_both_fixed_ours_m=self.rms_ours_m, rms_3d_both_fixed_demo5_m=self.rms_demo5_m)
        return out

    def line(self) -> str:
        s = (f"{self.version} on the same files: {self.demo5_fixed} fixed of {self.demo5_solved} "
             f"(ours {self.ours_fixed}); on the {self.both_fixed} epochs both fixed")
        if not self.both_fixed:
            return s + ": none"
        s += f" {np.median(self.apart_m):.4f} m apart (median), {self.apart_m.max():.4f} m at most"
        if self.rms_ours_m is not None:
            s += f"; RMS 3-D against the truth there: ours {self.rms_ours_m:.4f} m, demo5 {self.rms_demo5_m:.4f} m"
        return s


def compare(ours, theirs: Demo5Run, truth_e=None) -> Comparison:
    """Ours (solutions with ``t_gps``, ``r_e`` and ``quality``) against demo5's run, epoch by epoch."""
    ours_fixed = {epoch_key(s.t_gps): s.r_e for s in ours if s.quality == 1}
    theirs_fixed = {epoch_key(t): r for t, r in theirs.fixed}
    both = sorted(set(ours_fixed) & set(theirs_fixed))
    apart = np.array([np.linalg.norm(ours_fixed[t] - theirs_fixed[t]) for t in both])
    c = Comparison(len(ours_fixed), len(theirs_fixed), len(theirs.solutions), len(both), apart, version=theirs.version)
    if truth_e is not None and both:
        truth_e = np.asarray(truth_e, float)

        def rms(points) -> float:
            return float(np.sqrt(np.mean([np.sum((p - truth_e) ** 2) for p in points])))
        c.rms_ours_m = rms([ours_fixed[t] for t in both])
        c.rms_demo5_m = rms([theirs_fixed[t] for t in both])
    return c


__all__ = ["Comparison", "Demo5Run", "compare", "demo5_available", "epoch_key", "require_demo5", "run_demo5"]
