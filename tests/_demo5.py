"""RTKLIB demo5 (rtklibexplorer's branch, "RTKLIB ver.EX 2.5.0", through the pyrtklib5 binding) on
the same RINEX files as our RTK: the reference the issue measures us against.

demo5 runs in a child process (a crash of the C library cannot take the test worker with it),
from a configuration written here: kinematic, L1+L2, forward, fix-and-hold, ratio 3, the base at
a given ECEF position plus its header's antenna height, every other option demo5's own default.  Hatanaka/gzip files are
expanded first (RTKLIB calls external tools for those).  Installed with the tests (pyproject's
``test`` extra; wheels for x86_64 only)."""
from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np

#: RTKLIB's navsys bits (pos1-navsys)
_NAVSYS_BITS = {"G": 1, "S": 2, "R": 4, "E": 8, "J": 16, "C": 32}

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
    return importlib.util.find_spec("pyrtklib5") is not None


def _plain(src, work: Path, index: int) -> str:
    """``src`` as plain RINEX in ``work`` (hatanaka expands Hatanaka and gzip, and leaves plain
    RINEX as it is)."""
    import hatanaka
    out = work / f"{index}_{Path(src).name.split('.')[0]}"
    out.write_bytes(hatanaka.decompress(Path(src).read_bytes()))
    return str(out)


def run_demo5(rover, base, navs, base_xyz, work: Path, *, systems: str = "GEJ", mask_deg: float = 10.0,
              glonass_ar: str = "off") -> dict[int, tuple[np.ndarray, int]]:
    """demo5's kinematic solutions: GPS time (s, rounded) -> (ECEF position, Q: 1 fixed, 2 float)."""
    work.mkdir(parents=True, exist_ok=True)
    files = [_plain(f, work, i) for i, f in enumerate([rover, base, *navs])]
    # the base antenna above its marker as the base header gives it, as our RTK applies it (RTKLIB
    # applies the header's only where the base position comes from the header too)
    up, east, north = _antenna_delta_hen(files[1])
    conf = work / "demo5.conf"
    conf.write_text("\n".join([
        "pos1-posmode       =kinematic",
        "pos1-frequency     =l1+l2",
        "pos1-soltype       =forward",
        f"pos1-elmask        ={mask_deg:g}",
        f"pos1-navsys        ={sum(_NAVSYS_BITS[s] for s in systems)}",
        "pos1-ionoopt       =brdc",
        "pos1-tropopt       =saas",
        "pos1-sateph        =brdc",
        "pos2-armode        =fix-and-hold",
        f"pos2-gloarmode     ={glonass_ar}",
        "pos2-arthres       =3",
        "pos2-maxage        =30",
        "ant2-postype       =xyz",
        *(f"ant2-pos{i + 1}          ={v!r}" for i, v in enumerate(base_xyz)),
        f"ant2-antdele       ={east!r}",
        f"ant2-antdeln       ={north!r}",
        f"ant2-antdelu       ={up!r}",
        "out-solformat      =xyz",
        "out-timeform       =tow",
        "",
    ]))
    out = work / "demo5.pos"
    proc = subprocess.run([sys.executable, "-c", _RUNNER, str(conf), str(out), *files],
                          capture_output=True, text=True, timeout=600)
    if proc.returncode != 0 or not out.exists():
        raise RuntimeError(f"demo5 failed ({proc.returncode}): {proc.stderr[-500:]}")
    sols = {}
    for ln in out.read_text().splitlines():
        f = ln.split()
        if ln.startswith("%") or len(f) < 6:
            continue
        sols[round(int(f[0]) * 604800 + float(f[1]))] = (np.array([float(v) for v in f[2:5]]), int(f[5]))
    return sols


def _antenna_delta_hen(rinex_obs: str) -> tuple[float, float, float]:
    with open(rinex_obs, errors="replace") as f:
        for ln in f:
            if "ANTENNA: DELTA H/E/N" in ln[60:]:
                return tuple(float(v) for v in ln[:42].split())
            if "END OF HEADER" in ln[60:]:
                break
    return (0.0, 0.0, 0.0)


def demo5_version(work: Path) -> str:
    """The program line demo5 writes at the top of its solution file."""
    for ln in (work / "demo5.pos").read_text().splitlines():
        if ln.startswith("% program"):
            return ln.split(":", 1)[1].strip()
    return "unknown"
